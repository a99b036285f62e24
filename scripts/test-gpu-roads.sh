#!/usr/bin/env bash
# Tests the GPU roads that build on a machine without a GPU, in one build with both features
# (scripts/build-feature.sh prepares each): `vulkan` trains on lavapipe (Mesa's software Vulkan
# device, SPIR-V kernels) and `libtorch` on libtorch's CPU device, each against burn's CPU
# backend (trainer-core/tests/trainer.rs); the backend unit tests see the features built.
# Then a worker of that build trains a two-worker job with `workers.device: vulkan`
# (scripts/test-gpu-roads-job.sh), and the default worker is built back.
# About 20 minutes the first time (PyTorch 2.9.0 is fetched, burn is built a second way);
# a minute or two after.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
scripts/build-feature.sh vulkan,libtorch test --release -p trainer-core --lib --test trainer \
    -- backend trains_like_the_cpu_backend --nocapture
scripts/build-feature.sh vulkan,libtorch build --release -p worker --bin xfactor-worker
roads="$CARGO_TARGET_DIR/roads"
mkdir -p "$roads"
cp "$CARGO_TARGET_DIR/release/xfactor-worker" "$roads/xfactor-worker"
cargo build --release -p worker --bin xfactor-worker
eval "$(scripts/setup-libtorch.sh)"
scripts/test-gpu-roads-job.sh "$roads/xfactor-worker"
