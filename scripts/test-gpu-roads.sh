#!/usr/bin/env bash
# Tests the GPU roads on a machine without a GPU: `vulkan` trains on lavapipe (Mesa's software
# Vulkan device, SPIR-V kernels) against burn's CPU backend (trainer-core/tests/trainer.rs);
# `cuda` builds offline (NVRTC, the cubecl-llvm stand-in) and, with no NVIDIA driver here,
# refuses its device by the missing library's name (the backend unit tests, and a worker asked
# for `--device cuda`). Then a worker of that build trains a two-worker job with
# `workers.device: vulkan` (scripts/test-gpu-roads-job.sh).
#
# `vulkan,cuda` is the roads' shared build: CI builds the whole suite with it
# (`XFACTOR_FEATURES=vulkan,cuda scripts/test.sh`), which has already run the vulkan and cuda
# tests, so they are skipped here then and cargo finds the worker built.
#
# --libtorch adds the `libtorch` road (burn-tch, which burn deprecates for its cubecl backends)
# on libtorch's CPU device. CI leaves it out: torch-sys's dependencies turn on other features of
# crates burn's kernel crates share (half, digest, getrandom), so that build compiles all of
# them a second time (20 minutes on 2 cores), and CI must end within 75 minutes from cold.
#   scripts/test-gpu-roads.sh [--libtorch]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
shared=vulkan,cuda
if [ "${XFACTOR_FEATURES:-}" = "$shared" ]; then
    echo "gpu-roads: the suite ran the vulkan and cuda tests in the $shared build"
else
    # One cargo command builds the tests and the worker (for worker's `cli` test), so both take
    # one resolution of features and one build of burn.
    scripts/build-feature.sh "$shared" test --release -p trainer-core -p worker --lib \
        --test trainer --test cli -- backend trains_like_the_cpu_backend --nocapture
fi
worker="$CARGO_TARGET_DIR/release/xfactor-worker"
# --device cuda without a driver: refused before joining, naming the library, exit 1, no panic.
set +e
refusal=$("$worker" --device cuda --coordinator http://127.0.0.1:9 --token t --no-slurm 2>&1)
code=$?
set -e
if [ "$code" != 1 ] || ! grep -q 'libcuda.so\|libnvrtc.so' <<<"$refusal" || grep -q panicked <<<"$refusal"; then
    echo "gpu-roads: --device cuda without a driver should exit 1 naming libcuda/libnvrtc (exit $code):" >&2
    echo "$refusal" >&2
    exit 1
fi
echo "gpu-roads: --device cuda without a driver refused: $(grep -o -- '--device cuda: .*' <<<"$refusal" | head -1)"
scripts/test-gpu-roads-job.sh "$worker"
if [ "${1:-}" = --libtorch ]; then
    # Last: this build leaves the worker above in place (it builds trainer-core's tests only).
    scripts/build-feature.sh "$shared,libtorch" test --release -p trainer-core --test trainer \
        -- libtorch_trains_like_the_cpu_backend --nocapture
fi
