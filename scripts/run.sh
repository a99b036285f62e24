#!/usr/bin/env bash
# The main command: a coordinator and two CPU worker processes on loopback train XFactor through
# stage 1 and stage 2 on a small generated RE10K-layout dataset (in ./xfactor-local-run), then
# print the job's figures. `--transfer`, given first, runs the transfer recipe instead
# (scripts/transfer-recipe.flags, in ./xfactor-transfer-run: about 55 minutes on 2 cores);
# `--transfer-quick` its first 8000 stage-1 steps with the first run's evaluation
# (scripts/transfer-quick.flags, in ./xfactor-transfer-quick-run: about 20 minutes).
# Extra arguments go to xfactor-local (e.g. --stage1-steps 40).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
source scripts/env.sh
FLAGS=()
case "${1:-}" in
    --transfer)
        shift
        read_flags_file FLAGS scripts/transfer-recipe.flags
        FLAGS+=(--dir xfactor-transfer-run) ;;
    --transfer-quick)
        shift
        read_flags_file FLAGS scripts/transfer-quick.flags
        FLAGS+=(--dir xfactor-transfer-quick-run) ;;
esac
cargo build --release -p coordinator -p worker -p evaluation --bins
"$CARGO_TARGET_DIR/release/xfactor-local" "${FLAGS[@]}" "$@"
