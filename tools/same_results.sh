#!/usr/bin/env bash
# Whether two builds of vkdr compute the same results: the commit BASE against the working
# tree, for a change that should move no number (a refactor, a rename, a new front end).
#
#   tools/same_results.sh BASE [OUT]        (OUT: target/same-results by default)
#
# Builds BASE's `vkdr` in a git worktree (its own target folder), then runs with each
# build:
#   - `vkdr demo` (a generated dataset, a bottle's shape space, a registration from pose
#     noise with depth, the registered mesh's G-buffer);
#   - `vkdr eval` on the demo's bottles (2 trials, depth, 2 mm depth noise, the box in
#     front, gravity known);
#   - `vkdr eval-frames` on one real frame (../shared/real/ycbv-dev, where it is), the
#     defaults with 2 trials;
# and compares every file they write: byte for byte (.npy, .npz, .obj, pose.json, the
# shape spaces' descriptions), the CSV and JSON tables and logs without their times
# (fields and columns "ms", "noise_ms", "ms_per_iteration", "seconds", ...), and skips
# pictures and markdown (the tables' times and the plots' time axes differ from run to
# run). Exits 1 naming each file that differs.
set -euo pipefail

base=${1:?usage: tools/same_results.sh BASE [OUT]}
root=$(git rev-parse --show-toplevel)
out=$(realpath -m "${2:-$root/target/same-results}")
cd "$root"
commit=$(git rev-parse --verify "$base^{commit}")
mkdir -p "$out"

echo "== building $base ($commit) and the working tree"
rm -rf "$out/base-src"
git worktree prune
git worktree add --force --detach "$out/base-src" "$commit" >/dev/null
trap 'git worktree remove --force "$out/base-src"' EXIT
# The base's build reads ../shared and the shaders as the working tree's does.
CARGO_TARGET_DIR="$out/base-target" cargo build --release -q -p vkdr-cli --manifest-path "$out/base-src/Cargo.toml"
cargo build --release -q -p vkdr-cli
bins=("$out/base-target/release/vkdr" "$root/target/release/vkdr")
frames="$root/../shared/real/ycbv-dev/bop"

for k in 0 1; do
    side=$([ "$k" = 0 ] && echo base || echo head)
    vkdr=${bins[$k]}
    dir="$out/$side"
    rm -rf "$dir"
    mkdir -p "$dir"
    echo "== $side: demo, eval, eval-frames"
    "$vkdr" demo --out "$dir/demo" >"$dir/demo.log" 2>&1
    "$vkdr" eval --dataset "$dir/demo/dataset" --categories bottle --trials 2 --depth \
        --depth-noise 0.002 --occluder --gravity known --out "$dir/eval" >"$dir/eval.log" 2>&1
    if [ -d "$frames" ]; then
        "$vkdr" eval-frames "$frames" --images 000000/1 --trials 2 --out "$dir/frames" \
            >"$dir/frames.log" 2>&1
    fi
done

echo "== comparing"
python3 - "$out/base" "$out/head" <<'EOF'
import json
import sys
from pathlib import Path

base, head = Path(sys.argv[1]), Path(sys.argv[2])
def is_time(name):
    """A field or column that holds a time: ms, noise_ms, ms_per_iteration, seconds, ..."""
    return name in ("ms", "milliseconds", "seconds") or name.startswith("ms_") or name.endswith("_ms")


def without_times(value):
    if isinstance(value, dict):
        return {k: without_times(v) for k, v in value.items() if not is_time(k)}
    if isinstance(value, list):
        return [without_times(v) for v in value]
    return value


def csv_without_times(text):
    rows = [line.split(",") for line in text.splitlines()]
    keep = [i for i, name in enumerate(rows[0]) if not is_time(name)] if rows else []
    return [[row[i] for i in keep if i < len(row)] for row in rows]


compared, different = 0, []
files = sorted(p.relative_to(base) for p in base.rglob("*") if p.is_file())
for name in files:
    if name.suffix in (".png", ".md", ".log", ".txt"):
        continue
    theirs, ours = base / name, head / name
    if not ours.is_file():
        different.append(f"{name}: missing from the working tree's run")
        continue
    compared += 1
    if name.suffix == ".json" and name.name not in ("pose.json",) and not name.name.endswith(".npz.json"):
        if without_times(json.loads(theirs.read_text())) != without_times(json.loads(ours.read_text())):
            different.append(f"{name}: differs (times left out)")
    elif name.suffix == ".csv":
        if csv_without_times(theirs.read_text()) != csv_without_times(ours.read_text()):
            different.append(f"{name}: differs (times left out)")
    elif theirs.read_bytes() != ours.read_bytes():
        different.append(f"{name}: differs")
extra = sorted(str(p.relative_to(head)) for p in head.rglob("*") if p.is_file() and not (base / p.relative_to(head)).exists())
print(f"compared {compared} files ({len(files)} written by the base run; pictures, markdown and logs left out)")
for line in different:
    print(f"  {line}")
if extra:
    print(f"  only the working tree's run wrote: {', '.join(extra)}")
sys.exit(1 if different else 0)
EOF
echo "== the same results"
