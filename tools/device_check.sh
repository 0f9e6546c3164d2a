#!/usr/bin/env bash
# vkdr's figures on one device, in one command: the device, the rasterizer's bench, the
# registration's bench, CPD, the Python binding's overhead and the real YCB-Video frames,
# each step's JSON under OUT and one markdown table (tools/device_report.py) with each
# figure's lavapipe counterpart where a JSON of an earlier run is given.
#
#   tools/device_check.sh [--quick] [--out DIR] [--work DIR] [--bin VKDR]
#                         [--frames BOP_DIR] [--wheels DIR] [--baseline FILE]
#
# --quick runs every step at tiny sizes (CI runs it on lavapipe so that it never rots);
# the full form is sized for an NVIDIA GPU (about 6 minutes on an H100, docs/device.md).
# OUT gets three files: device_check.md, device_check.json and steps.tar.gz (every step's
# log and output, from the work folder, OUT/steps by default).
# Defaults: OUT=$OUT or device-check/, the binary target/release/vkdr (or .device/vkdr),
# the frames ../shared/real/ycbv-dev/bop (or .device/ycbv-dev/bop), the module from the
# wheels in .device/wheels where `import vkdr` fails, no baseline (FILE: an earlier run's
# device_check.json).
#
# Where `ldconfig -p` has no Vulkan loader and .gl/*.deb exist (the device README's
# recipe), they are unpacked first; the NVIDIA ICD is used where it is installed.
#
# Every step must succeed: the first that fails ends the run non-zero, naming itself, and
# no table is written (a partial table is never reported as whole).
set -euo pipefail

quick=0
out="${OUT:-device-check}"
work=""
bin=""
frames=""
wheels=".device/wheels"
baseline=""
while [ $# -gt 0 ]; do
    case "$1" in
        --quick) quick=1 ;;
        --out) out="$2"; shift ;;
        --work) work="$2"; shift ;;
        --bin) bin="$2"; shift ;;
        --frames) frames="$2"; shift ;;
        --wheels) wheels="$2"; shift ;;
        --baseline) baseline="$2"; shift ;;
        -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
        *) echo "device_check: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done

first_of() {
    for candidate in "$@"; do
        if [ -e "$candidate" ]; then echo "$candidate"; return; fi
    done
}
bin="${bin:-$(first_of target/release/vkdr .device/vkdr)}"
frames="${frames:-$(first_of ../shared/real/ycbv-dev/bop .device/ycbv-dev/bop)}"
[ -n "$bin" ] && [ -x "$bin" ] || { echo "device_check: no vkdr binary (cargo build --release, or --bin)" >&2; exit 2; }
[ -n "$frames" ] && [ -d "$frames" ] || { echo "device_check: no BOP frames (--frames DIR)" >&2; exit 2; }
work="${work:-$out/steps}"
mkdir -p "$out" "$work"
started=$(date +%s)

# Runs one step: its name, then the command; its output goes to WORK/NAME.log (and the
# terminal). A failure ends the run, naming the step.
step() {
    local name="$1"; shift
    local t0=$(date +%s)
    echo "== $name: $*"
    if ! "$@" > >(tee "$work/$name.log") 2>&1; then
        echo "device_check: step '$name' failed (its log: $work/$name.log)" >&2
        tar czf "$out/steps.tar.gz" -C "$work" .
        exit 1
    fi
    echo "== $name: $(( $(date +%s) - t0 )) s"
}

# The loader and the driver.
if ! ldconfig -p 2>/dev/null | grep -q libvulkan.so.1; then
    if compgen -G ".gl/*.deb" >/dev/null; then
        for f in .gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
    fi
fi
nvidia_icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
if [ -z "${VK_DRIVER_FILES:-}" ] && [ -f "$nvidia_icd" ]; then
    export VK_DRIVER_FILES="$nvidia_icd"
fi

# The Python module: the one installed, or the carried wheel into a private folder.
python=python3
if ! "$python" -c "import vkdr" 2>/dev/null; then
    if compgen -G "$wheels/*.whl" >/dev/null; then
        "$python" -m pip install -q --no-index --no-deps --no-compile --target /tmp/vkdr-site "$wheels"/*.whl
        export PYTHONPATH="/tmp/vkdr-site${PYTHONPATH:+:$PYTHONPATH}"
    else
        echo "device_check: no vkdr Python module and no wheel in $wheels" >&2
        exit 2
    fi
fi

if [ "$quick" = 1 ]; then
    sizes_bench=("64" "80x60"); bench_max=2000; repeats=2
    register_size=96x72; subdivide=0; register_repeats=1; batches=(2)
    cpd_sizes=300; overhead=(--vertices 2000 --size 64 --runs 3)
    frame_args=(--images 000000/1 --trials 2)
else
    sizes_bench=("1024" "320x240"); bench_max=1000000; repeats=10
    register_size=640x480; subdivide=3; register_repeats=5; batches=(1 4 16 64)
    cpd_sizes=2000,5000,100000; overhead=(--vertices 100000 --size 1024 --runs 15)
    frame_args=()
fi

step info "$bin" info
for size in "${sizes_bench[@]}"; do
    step "bench_$size" "$bin" bench --size "$size" --max-vertices "$bench_max" \
        --repeats "$repeats" --out "$work/bench_$size" --force
done
for observed in mask depth; do
    extra=(); [ "$observed" = depth ] && extra=(--depth)
    for batch in "${batches[@]}"; do
        step "register_${observed}_batch$batch" "$bin" bench-register --subdivide "$subdivide" \
            --size "$register_size" --repeats "$register_repeats" --batch "$batch" "${extra[@]}" \
            --out "$work/register_${observed}_batch$batch" --force
    done
done
step cpd "$python" tools/peers/cpd_peers.py --sizes "$cpd_sizes" --skip-pycpd-above 0 \
    --vkdr "$bin" --out "$work/cpd"
step overhead "$python" bindings/python/benches/overhead.py "${overhead[@]}" --json "$work/overhead.json"
step frames "$bin" eval-frames "$frames" "${frame_args[@]}" --out "$work/frames" --force

report=(--steps "$work" --out "$out" --seconds $(( $(date +%s) - started )))
[ -n "$baseline" ] && report+=(--baseline "$baseline")
step report "$python" tools/device_report.py "${report[@]}"
tar czf "$out/steps.tar.gz" --exclude '*.npy' -C "$work" .
