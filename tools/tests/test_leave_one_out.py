"""tools/leave_one_out.py on a tiny category (three tetrahedra) and a BOP map whose model
is a fourth, in millimetres and turned: one dataset per instance, each instance the test
instance once, the model placed in the category frame in metres; bad input refused.

    python3 -m pytest tools/tests/test_leave_one_out.py
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

TOOL = Path(__file__).resolve().parents[1] / "leave_one_out.py"
TETRAHEDRON = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
FACES = ["f 1 3 2", "f 1 2 4", "f 1 4 3", "f 2 3 4"]


def write_obj(path: Path, vertices: np.ndarray) -> None:
    lines = ["v {} {} {}".format(*v) for v in vertices] + FACES
    path.write_text("\n".join(lines) + "\n")


def read_vertices(path: Path) -> np.ndarray:
    rows = [line.split()[1:4] for line in path.read_text().splitlines() if line.startswith("v ")]
    return np.array(rows, dtype=float)


def make_inputs(root: Path, model_scale_mm: float = 50.0) -> tuple[Path, Path]:
    category = root / "can_wo_model"
    (category / "train").mkdir(parents=True)
    write_obj(category / "canonical.obj", 0.05 * TETRAHEDRON)
    write_obj(category / "train" / "tall.obj", 0.05 * TETRAHEDRON * [1, 1, 2])
    write_obj(category / "train" / "wide.obj", 0.05 * TETRAHEDRON * [2, 1, 1])
    info = {"category": "can_wo_model", "up_axis": "z", "units": "m", "instances": ["mean", "tall", "wide"]}
    (category / "info.json").write_text(json.dumps(info))
    bop = root / "bop"
    (bop / "models").mkdir(parents=True)
    write_obj(bop / "models" / "obj_000007.obj", model_scale_mm * TETRAHEDRON)
    placement = {"rotation": [0, 0, np.pi / 2], "translation": [0.01, 0, 0]}
    entry = {"category": "../can_wo_model", "model": "models/obj_000007.obj", "model_to_category": placement}
    (bop / "map.json").write_text(json.dumps({"7": entry}))
    return category, bop / "map.json"


def run(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(TOOL), *map(str, args)], capture_output=True, text=True)


def test_each_instance_is_left_out_once(tmp_path: Path) -> None:
    category, map_path = make_inputs(tmp_path)
    out = tmp_path / "loo"
    result = run(category, map_path, "7", out, "--name", "flat")
    assert result.returncode == 0, result.stderr
    names = sorted(p.name for p in out.iterdir())
    assert names == ["can_wo_flat", "can_wo_mean", "can_wo_tall", "can_wo_wide"]
    for name in names:
        left_out = name.removeprefix("can_wo_")
        info = json.loads((out / name / "info.json").read_text())
        assert info["up_axis"] == "z" and info["left_out"] == left_out
        assert [p.stem for p in (out / name / "test").iterdir()] == [left_out]
        train = sorted(p.stem for p in (out / name / "train").iterdir())
        assert left_out not in train and len(train) == 2
    # The category's canonical stays where it is not the one left out.
    np.testing.assert_allclose(read_vertices(out / "can_wo_tall" / "canonical.obj"), 0.05 * TETRAHEDRON)
    # The model: millimetres to metres, turned a quarter about z, moved 1 cm along x.
    flat = read_vertices(out / "can_wo_flat" / "test" / "flat.obj")
    expected = 0.05 * TETRAHEDRON @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]).T + [0.01, 0, 0]
    np.testing.assert_allclose(flat, expected, atol=1e-7)
    # Where it is: the rest's with the fewest vertices (a tie: the first by name).
    assert sorted(p.stem for p in (out / "can_wo_mean" / "train").iterdir()) == ["tall", "wide"]
    np.testing.assert_allclose(read_vertices(out / "can_wo_mean" / "canonical.obj"), expected, atol=1e-7)


def test_bad_input_is_refused_and_writes_nothing(tmp_path: Path) -> None:
    category, map_path = make_inputs(tmp_path, model_scale_mm=0.5)
    result = run(category, map_path, "7", tmp_path / "loo")
    assert result.returncode == 1 and "under a millimetre" in result.stderr
    result = run(category, map_path, "8", tmp_path / "loo")
    assert result.returncode == 1 and "no obj_id 8" in result.stderr
    assert not (tmp_path / "loo").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".loo")] == []
    (tmp_path / "taken").mkdir()
    result = run(category, map_path, "7", tmp_path / "taken")
    assert result.returncode == 1 and "exists" in result.stderr
