#!/usr/bin/env bash
# Tests the GPU roads on a machine without a GPU, in one build of burn with all three features
# (scripts/build-feature.sh prepares each): `vulkan` trains on lavapipe (Mesa's software Vulkan
# device, SPIR-V kernels) and `libtorch` on libtorch's CPU device, each against burn's CPU
# backend (trainer-core/tests/trainer.rs); `cuda` builds offline (NVRTC, the cubecl-llvm
# stand-in) and, with no NVIDIA driver here, refuses its device by the missing library's name
# (the backend unit tests, and a worker asked for `--device cuda`). Then a worker of that build
# trains a two-worker job with `workers.device: vulkan` (scripts/test-gpu-roads-job.sh), and the
# default worker is built back.
# Measured on 2 cores (2026-11-26): about 25 minutes the first time after the default build
# (PyTorch 2.9.0 is fetched, 2.5 minutes; burn is built a second way, 20 minutes), 4 after.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
roads_features=vulkan,libtorch,cuda
# One cargo command builds the tests and the worker (for worker's `cli` test), so both take
# one resolution of features and one build of burn: a separate `build -p worker` resolved
# other features and compiled burn's kernel crates a second time (15 minutes cold).
scripts/build-feature.sh "$roads_features" test --release -p trainer-core -p worker --lib \
    --test trainer --test cli -- backend trains_like_the_cpu_backend --nocapture
roads="$CARGO_TARGET_DIR/roads"
mkdir -p "$roads"
cp "$CARGO_TARGET_DIR/release/xfactor-worker" "$roads/xfactor-worker"
# The roads worker loads PyTorch 2.9.0's libtorch.
eval "$(scripts/setup-libtorch.sh)"
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
scripts/test-gpu-roads-job.sh "$roads/xfactor-worker"
