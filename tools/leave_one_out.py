#!/usr/bin/env python3
"""Category datasets that leave each instance out in turn: one scanned category and the
BOP model of its test object become N datasets, each with one instance as its test
instance and the others as its canonical and training shapes, for `vkdr gen-frames` and
`vkdr eval-frames` on instances the shared frames do not show (a flat can, a small one).

    pip install numpy
    python3 tools/leave_one_out.py ../shared/real/ycbv-dev/dataset/can_wo_002_master_chef_can \\
        ../shared/real/ycbv-dev/bop/map.json 1 /tmp/loo --name 002_master_chef_can
    vkdr gen-frames --dataset /tmp/loo --frames 4 --out /tmp/loo-frames
    vkdr eval-frames /tmp/loo-frames --spaces /tmp/loo-spaces --out /tmp/loo-eval

CATEGORY is a category folder (`canonical.obj`, `train/*.obj`, `info.json` with its
`up_axis` and `instances`); MAP and OBJ_ID name the BOP model of its test object (an OBJ
in millimetres, placed in the category frame by the map's `model_to_category`). The
canonical's name is the one of `info.json`'s `instances` that `train/` lacks. Each output
dataset `OUT/<category>_wo_<name>/` (the category's name up to a `_wo_` of its own) holds that instance in `test/`; its canonical is the
category's, or where the canonical is the one left out, the one of the rest with the fewest
vertices (the registration deforms the canonical's: a scanned model's thousands cost).
Meshes are written as vertices and faces only (no normals or texture coordinates). OUT is
written into a temporary folder beside it and renamed when whole: a failure leaves none.
"""

import argparse
import json
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np


def read_obj(path: Path) -> tuple[np.ndarray, list[str]]:
    """The vertices (V x 3) and the face lines (vertex indices only) of an OBJ file."""
    vertices, faces = [], []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        try:
            if fields[0] == "v":
                vertices.append([float(x) for x in fields[1:4]])
            elif fields[0] == "f":
                faces.append("f " + " ".join(f.split("/")[0] for f in fields[1:]))
        except ValueError as error:
            raise ValueError(f"{path}:{number}: {error}") from error
    if not vertices or not faces:
        raise ValueError(f"{path}: no vertices or no faces")
    return np.array(vertices), faces


def write_obj(path: Path, vertices: np.ndarray, faces: list[str], comment: str) -> None:
    lines = [f"# {comment}"]
    lines += ["v {:.7g} {:.7g} {:.7g}".format(*v) for v in vertices]
    lines += faces
    path.write_text("\n".join(lines) + "\n")


def rotation(axis_angle: list[float]) -> np.ndarray:
    """The rotation matrix of an axis-angle vector (Rodrigues)."""
    r = np.asarray(axis_angle, dtype=float)
    angle = np.linalg.norm(r)
    if angle < 1e-12:
        return np.eye(3)
    k = r / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def bop_model(map_path: Path, obj_id: str) -> tuple[np.ndarray, list[str]]:
    """The map's model of obj_id in the category frame, in metres: vertices, faces."""
    entries = json.loads(map_path.read_text())
    if obj_id not in entries:
        raise ValueError(f"{map_path}: no obj_id {obj_id} (it has {', '.join(entries)})")
    entry = entries[obj_id]
    model = map_path.parent / entry["model"]
    if model.suffix.lower() != ".obj":
        raise ValueError(f"{model}: only OBJ models are read here")
    vertices, faces = read_obj(model)
    placement = entry["model_to_category"]
    vertices = vertices / 1000.0 @ rotation(placement["rotation"]).T + placement["translation"]
    if np.ptp(vertices, axis=0).max() < 1e-3:
        raise ValueError(f"{model}: under a millimetre across; the map declares millimetres")
    return vertices, faces


def category_shapes(category: Path) -> tuple[dict, dict[str, Path], str]:
    """The category's info.json, its shapes by name and the canonical's name."""
    info = json.loads((category / "info.json").read_text())
    shapes = {p.stem: p for p in sorted((category / "train").glob("*.obj"))}
    rest = [n for n in info.get("instances", []) if n not in shapes]
    canonical = rest[0] if len(rest) == 1 else "canonical"
    if canonical in shapes:
        raise ValueError(f"{category}: a training shape is named {canonical}")
    shapes[canonical] = category / "canonical.obj"
    return info, shapes, canonical


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("category", type=Path, help="a category folder")
    parser.add_argument("map", type=Path, help="a BOP map.json (vkdr eval-frames' map)")
    parser.add_argument("obj_id", help="the map's object whose model joins the instances")
    parser.add_argument("out", type=Path, help="a folder that does not exist yet")
    parser.add_argument("--name", help="the model's instance name (default: obj_ and its id)")
    args = parser.parse_args()
    if args.out.exists():
        print(f"leave_one_out.py: {args.out} exists; name a new folder", file=sys.stderr)
        return 1
    try:
        info, shapes, canonical = category_shapes(args.category)
        meshes = {name: read_obj(path) for name, path in shapes.items()}
        vertices, faces = bop_model(args.map, args.obj_id)
        name = args.name or f"obj_{args.obj_id.zfill(6)}"
        if name in meshes:
            raise ValueError(f"{args.category}: already has an instance named {name}")
        meshes[name] = (vertices, faces)
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as error:
        print(f"leave_one_out.py: {error}", file=sys.stderr)
        return 1
    args.out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{args.out.name}.", dir=args.out.parent))
    try:
        # The category's name without what its own folder left out.
        stem = re.sub(r"_wo_.*$", "", str(info.get("category", args.category.name)))
        for left_out in sorted(meshes):
            root = staging / f"{stem}_wo_{left_out}"
            (root / "train").mkdir(parents=True)
            (root / "test").mkdir()
            rest = sorted(n for n in meshes if n != left_out)
            base = canonical if canonical != left_out else min(rest, key=lambda n: len(meshes[n][0]))
            for shape in [left_out] + rest:
                folder = "test" if shape == left_out else "train"
                path = root / "canonical.obj" if shape == base else root / folder / f"{shape}.obj"
                write_obj(path, *meshes[shape], f"{shape}: metres, the category frame")
            (root / "info.json").write_text(
                json.dumps(
                    {
                        "category": root.name,
                        "up_axis": info.get("up_axis", "y"),
                        "units": "m",
                        "instances": sorted(meshes),
                        "left_out": left_out,
                    },
                    indent=1,
                )
            )
            print(f"{root.name}: canonical {base}, train {', '.join(n for n in rest if n != base)}")
        staging.rename(args.out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main())
