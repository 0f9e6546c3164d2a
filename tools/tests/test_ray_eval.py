"""tools/ray_eval.py on a local Ray (2 CPUs): 4 shards of a small generated set merge into
the tables of the unsharded run (the wall times aside), and a failing task is retried and
reported; 2 shards of eval-frames on rendered BOP frames merge into its unsharded tables. Needs Ray (`pip install "ray[default]"`) and the vkdr binary
(target/release/vkdr, or VKDR_BIN); skipped without Ray, not run by CI (Ray is large):

    python3 -m pytest tools/tests/test_ray_eval.py
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("ray")

ROOT = Path(__file__).resolve().parents[2]
VKDR = Path(os.environ.get("VKDR_BIN", ROOT / "target" / "release" / "vkdr"))


def without_times(value):
    if isinstance(value, dict):
        return {k: without_times(v) for k, v in value.items() if k != "ms" and not k.endswith("_ms")}
    if isinstance(value, list):
        return [without_times(v) for v in value]
    return value


def run(*args, ok=True):
    done = subprocess.run([str(a) for a in args], capture_output=True, text=True)
    assert (done.returncode == 0) == ok, f"{args}: {done.stderr[-2000:]}"
    return done


def test_ray_shards_merge_into_the_unsharded_tables(tmp_path):
    if not VKDR.exists():
        pytest.fail(f"no vkdr binary at {VKDR}: cargo build --release, or set VKDR_BIN")
    data = tmp_path / "data"
    run(VKDR, "gen-dataset", "--train", "4", "--test", "2", "--out", data)
    flags = ["--dataset", data, "--categories", "bottle,mug", "--trials", "2", "--known-iterations", "4",
             "--noise-iterations", "4", "--align", "2", "--starts", "2", "--spaces", tmp_path / "spaces"]
    run(VKDR, "eval", *flags, "--out", tmp_path / "full")
    ray_eval = [sys.executable, ROOT / "tools" / "ray_eval.py", "--address", "local", "--num-cpus", "2",
                "--gpus-per-task", "0", "--vkdr", VKDR]
    done = run(*ray_eval, "--shards", "4", "--out", tmp_path / "ray", "--", *flags)
    assert "[4/4]" in done.stderr
    for name in ["table.json"]:
        full = json.loads((tmp_path / "full" / name).read_text())
        merged = json.loads((tmp_path / "ray" / name).read_text())
        assert without_times(merged) == without_times(full)
    assert (tmp_path / "ray" / "trials.csv").read_bytes() == (tmp_path / "full" / "trials.csv").read_bytes()

    # Every task fails (no such category): each is retried twice, reported, and no merge runs.
    bad = [str(f) for f in flags]
    bad[bad.index("bottle,mug")] = "nosuch"
    done = run(*ray_eval, "--shards", "2", "--retries", "2", "--out", tmp_path / "bad", "--", *bad, ok=False)
    assert "failed after 2 retries" in done.stderr and "no category" in done.stderr
    assert "no merge" in done.stderr


def test_ray_eval_frames_shards_merge_into_the_unsharded_tables(tmp_path):
    if not VKDR.exists():
        pytest.fail(f"no vkdr binary at {VKDR}: cargo build --release, or set VKDR_BIN")
    data, frames = tmp_path / "data", tmp_path / "frames"
    run(VKDR, "gen-dataset", "--train", "4", "--test", "2", "--out", data)
    run(VKDR, "gen-frames", "--dataset", data, "--categories", "bottle", "--occluder", "--out", frames)
    flags = [frames, "--categories", frames / "map.json", "--trials", "2", "--spaces", tmp_path / "spaces"]
    run(VKDR, "eval-frames", *flags, "--out", tmp_path / "full")
    done = run(sys.executable, ROOT / "tools" / "ray_eval.py", "--command", "eval-frames", "--address", "local",
               "--num-cpus", "2", "--gpus-per-task", "0", "--vkdr", VKDR, "--shards", "2", "--out", tmp_path / "ray",
               "--", *flags)
    assert "[2/2]" in done.stderr
    full = json.loads((tmp_path / "full" / "table.json").read_text())
    merged = json.loads((tmp_path / "ray" / "table.json").read_text())
    assert len(full) == 2 and without_times(merged) == without_times(full)
    assert (tmp_path / "ray" / "trials.csv").read_bytes() == (tmp_path / "full" / "trials.csv").read_bytes()
