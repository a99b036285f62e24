#!/usr/bin/env bash
# Installs what the project needs beyond a Rust toolchain:
# - a Vulkan loader and Mesa's lavapipe software device, so burn-wgpu runs (on the CPU) on
#   machines without a GPU;
# - patch, for the vulkan feature's fix to cubecl-spirv (scripts/build-feature.sh);
# - ffmpeg (and ffprobe), which `xfactor transfer` uses to decode video files and to write the
#   MP4, and which its test uses to make and measure videos;
# - Pillow and NumPy for the system python3, which the decode benchmark's PIL peer
#   (trainer-core/benches/pil_decode.py) runs on;
# - moto's S3 server (PyPI `moto[server]`, pinned) in a virtual environment in the persistent
#   cache, which the S3 integration tests start on loopback. Those tests fail, not skip, when
#   it is missing, so this step fails loudly too;
# - TensorBoard (PyPI `tensorboard`, pinned; no TensorFlow) in another virtual environment,
#   whose EventAccumulator the TensorBoard test reads the coordinator's event files with, and
#   whose `tensorboard --logdir` shows them.
set -euo pipefail

sudo_cmd=""
if [ "$(id -u)" != 0 ]; then sudo_cmd="sudo"; fi
apt_packages=()

if ! { ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 && ldconfig -p | grep -q libvulkan.so.1; }; then
    apt_packages+=(mesa-vulkan-drivers libvulkan1)
fi
# scripts/build-feature.sh applies the vulkan feature's fix to cubecl-spirv with it.
if ! command -v patch >/dev/null; then
    apt_packages+=(patch)
fi
# The GPU benchmark's folder is xz-compressed (scripts/bench-gpu.sh).
if ! command -v xz >/dev/null; then
    apt_packages+=(xz-utils)
fi
if ! command -v ffmpeg >/dev/null || ! command -v ffprobe >/dev/null; then
    apt_packages+=(ffmpeg)
fi
# apt installs them for the system interpreter, which the benchmark runs even where a version
# manager (pyenv) puts another python3 first on PATH.
system_python=/usr/bin/python3
[ -x "$system_python" ] || system_python=python3
if ! "$system_python" -c "import PIL, numpy" 2>/dev/null; then
    apt_packages+=(python3-pil python3-numpy)
fi
if [ "${#apt_packages[@]}" -gt 0 ]; then
    echo "setup: installing ${apt_packages[*]}" >&2
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends \
        "${apt_packages[@]}" >/dev/null
fi

# A virtual environment at $1 (made once; Debian's python3 has venv in a separate package).
make_venv() {
    if [ -x "$1/bin/pip" ]; then return; fi
    if ! python3 -m venv "$1" >/dev/null 2>&1; then
        $sudo_cmd apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends \
            python3-venv >/dev/null
        rm -rf "$1"
        python3 -m venv "$1"
    fi
}

moto_version="5.2.1"
s3_env="${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/s3-env"
if ! "$s3_env/bin/python" -c "import moto, sys; sys.exit(moto.__version__ != '$moto_version')" 2>/dev/null; then
    echo "setup: installing moto[server]==$moto_version into $s3_env" >&2
    make_venv "$s3_env"
    "$s3_env/bin/pip" install --quiet --disable-pip-version-check "moto[server]==$moto_version"
fi

tensorboard_version="2.20.0"
tensorboard_env="${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/tensorboard-env"
if ! "$tensorboard_env/bin/python" -c "import tensorboard, sys; sys.exit(tensorboard.__version__ != '$tensorboard_version')" 2>/dev/null; then
    echo "setup: installing tensorboard==$tensorboard_version into $tensorboard_env" >&2
    make_venv "$tensorboard_env"
    "$tensorboard_env/bin/pip" install --quiet --disable-pip-version-check "tensorboard==$tensorboard_version"
fi
