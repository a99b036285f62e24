#!/usr/bin/env bash
# The test command: installs system packages if missing, then runs every test of the workspace
# in the release profile (the wgpu parity test runs on lavapipe when no GPU is present).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
source scripts/env.sh
cargo test --release --workspace "$@"
