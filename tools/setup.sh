#!/usr/bin/env bash
# Installs what vkdr needs and is missing: the Vulkan loader, Mesa's lavapipe (a CPU
# Vulkan driver, so that everything runs without a GPU), the validation layers, shaderc
# and glslang for compiling shaders, and the Rust toolchain's cargo. Does nothing when
# all of it is there. Debian and Ubuntu (apt-get); other systems: install the same
# packages by hand.
set -euo pipefail

packages=(
    libvulkan1 libvulkan-dev mesa-vulkan-drivers vulkan-validationlayers vulkan-tools
    libshaderc-dev glslang-dev spirv-tools pkg-config
)

missing=()
for p in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

if [ ${#missing[@]} -gt 0 ]; then
    if ! command -v apt-get >/dev/null; then
        echo "tools/setup.sh: missing ${missing[*]} and no apt-get here; install them by hand" >&2
        exit 1
    fi
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    echo "tools/setup.sh: installing ${missing[*]}"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if ! command -v cargo >/dev/null; then
    echo "tools/setup.sh: cargo not found; install Rust from https://rustup.rs" >&2
    exit 1
fi
