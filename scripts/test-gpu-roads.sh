#!/usr/bin/env bash
# Tests the GPU roads that build on a machine without a GPU, in one build with both features
# (scripts/build-feature.sh prepares each): `vulkan` trains on lavapipe (Mesa's software Vulkan
# device, SPIR-V kernels) and `libtorch` on libtorch's CPU device, each against burn's CPU
# backend (trainer-core/tests/trainer.rs); the backend unit tests see the features built.
# About 15 minutes the first time (PyTorch 2.9.0 is fetched, burn is built a second way);
# seconds after.
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
scripts/build-feature.sh vulkan,libtorch test --release -p trainer-core --lib --test trainer \
    -- backend trains_like_the_cpu_backend --nocapture
