#!/usr/bin/env bash
# Tests the GPU roads on a machine without a GPU, in one build of burn with all three features
# (scripts/build-feature.sh prepares each): `vulkan` trains on lavapipe (Mesa's software Vulkan
# device, SPIR-V kernels) and `libtorch` on libtorch's CPU device, each against burn's CPU
# backend (trainer-core/tests/trainer.rs); `cuda` builds offline (NVRTC, the cubecl-llvm
# stand-in) and, with no NVIDIA driver here, refuses its device by the missing library's name
# (the backend unit tests, and a worker asked for `--device cuda`). Then a worker of that build
# trains a two-worker job with `workers.device: vulkan` (scripts/test-gpu-roads-job.sh), and the
# default worker is built back.
# About 20 minutes the first time (PyTorch 2.9.0 is fetched, burn is built a second way);
# a minute or two after.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
roads_features=vulkan,libtorch,cuda
scripts/build-feature.sh "$roads_features" test --release -p trainer-core --lib --test trainer \
    -- backend trains_like_the_cpu_backend --nocapture
scripts/build-feature.sh "$roads_features" build --release -p worker --bin xfactor-worker
roads="$CARGO_TARGET_DIR/roads"
mkdir -p "$roads"
cp "$CARGO_TARGET_DIR/release/xfactor-worker" "$roads/xfactor-worker"
# --device cuda without a driver: refused before joining, naming the library, exit 1, no panic.
set +e
refusal=$("$roads/xfactor-worker" --device cuda --coordinator http://127.0.0.1:9 --token t --no-slurm 2>&1)
code=$?
set -e
if [ "$code" != 1 ] || ! grep -q 'libcuda.so\|libnvrtc.so' <<<"$refusal" || grep -q panicked <<<"$refusal"; then
    echo "gpu-roads: --device cuda without a driver should exit 1 naming libcuda/libnvrtc (exit $code):" >&2
    echo "$refusal" >&2
    exit 1
fi
echo "gpu-roads: --device cuda without a driver refused: $(grep -o -- '--device cuda: .*' <<<"$refusal" | head -1)"
cargo build --release -p worker --bin xfactor-worker
eval "$(scripts/setup-libtorch.sh)"
scripts/test-gpu-roads-job.sh "$roads/xfactor-worker"
