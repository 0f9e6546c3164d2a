#!/usr/bin/env bash
# Prepares what tools/device_check.sh needs on a bare GPU machine, in .device/ and .gl/
# (both ignored by git, carried by the `device` tool): the release binary (stripped), the
# Python module's wheel, a copy of the real frames (../shared does not travel), the Vulkan
# loader's .debs, and, with --baseline, this machine's own full run as the lavapipe column.
#
#   bash tools/device_prepare.sh [--baseline]
#
# Then, with the `device` tool (docs/device.md):
#   run(command="bash tools/device_check.sh --out $OUT --work /tmp/dc --baseline .device/baseline/device_check.json",
#       carry=[".device", ".gl"], timeout_s=480)
set -euo pipefail
cd "$(dirname "$0")/.."
baseline=0
[ "${1:-}" = "--baseline" ] && baseline=1

for ignored in /.device/ /.gl/; do
    grep -qxF "$ignored" .git/info/exclude 2>/dev/null || echo "$ignored" >>.git/info/exclude
done
mkdir -p .device/wheels .gl

cargo build --release
strip -o .device/vkdr target/release/vkdr
rm -f .device/wheels/*.whl
python3 -m pip wheel --no-deps -w .device/wheels ./bindings/python
rm -rf .device/ycbv-dev
cp -r ../shared/real/ycbv-dev .device/ycbv-dev

if ! compgen -G ".gl/*.deb" >/dev/null; then
    o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
    mkdir -p /tmp/amd64/partial
    # shellcheck disable=SC2086
    apt-get $o update
    # shellcheck disable=SC2086
    (cd .gl && apt-get $o download libvulkan1)
fi

if [ "$baseline" = 1 ]; then
    bash tools/device_check.sh --out .device/baseline --bin .device/vkdr --frames .device/ycbv-dev/bop
fi
du -sh .device .gl
