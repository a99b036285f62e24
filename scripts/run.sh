#!/usr/bin/env bash
# The main command. Today: checks the model against the authors' fixture on both backends and
# prints the stage-1 step benchmark. It grows into the local coordinator + two workers run.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
source scripts/env.sh
fixture="${XFACTOR_SHARED:-../shared}/fixtures/xfactor-tiny.safetensors"
cargo build --release -p trainer-core --bins
for backend in cpu wgpu; do
    "$CARGO_TARGET_DIR/release/xfactor-check" "$fixture" --backend "$backend"
done
cargo bench -p trainer-core --bench model_step -- --backend cpu "$@"
