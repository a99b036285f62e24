#!/usr/bin/env bash
# The test command: installs system packages if missing, then runs every test of the workspace
# in the release profile (the wgpu parity test runs on lavapipe when no GPU is present).
# XFACTOR_FEATURES=vulkan,cuda (CI) builds the suite with those GPU roads through
# scripts/build-feature.sh, so the roads' tests, their workers and the GPU pack reuse this one
# build of burn instead of compiling burn's kernel crates a second time (20 minutes cold).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
source scripts/env.sh
if [ -n "${XFACTOR_FEATURES:-}" ]; then
    scripts/build-feature.sh "$XFACTOR_FEATURES" test --release --workspace "$@"
else
    cargo test --release --workspace "$@"
fi
