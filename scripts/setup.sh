#!/usr/bin/env bash
# Installs what the project needs beyond a Rust toolchain: a Vulkan loader and Mesa's lavapipe
# software device, so burn-wgpu runs (on the CPU) on machines without a GPU.
set -euo pipefail

have_lavapipe() {
    ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 && ldconfig -p | grep -q libvulkan.so.1
}

if ! have_lavapipe; then
    sudo_cmd=""
    if [ "$(id -u)" != 0 ]; then sudo_cmd="sudo"; fi
    echo "setup: installing mesa-vulkan-drivers (lavapipe) and libvulkan1" >&2
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends \
        mesa-vulkan-drivers libvulkan1 >/dev/null
fi
