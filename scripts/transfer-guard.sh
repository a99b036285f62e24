#!/usr/bin/env bash
# CI's transfer guard (issue 52; docs/testing.md): the quick transfer recipe
# (scripts/transfer-quick.flags) cut to the first 4000 of the recipe's 12000 stage-1 steps, for
# seed 9 (`--stage1-schedule-steps 12000` keeps the recipe's cosine and window curriculum, so the
# weights are the full run's at step 4000, byte for byte), a short stage 2, then the first run's
# evaluation (16 held-out scenes, 128 transfers). Fails unless stage 1's TPS AUC@30 leads
# the oracle's unrelated-path calibration by 3 of their combined spreads, the recipe's target.
# The seed is named because seeds differ: seed 9 leads by 4.5 spreads at step 4000 on the
# recipe's machine and on an AMD EPYC (gemm's blocking no longer follows the L1 cache:
# vendor/gemm-common). On a CPU without AVX-512 a seed is another draw (docs/testing.md).
# About 9 to 11 minutes on 2 cores.
#
#   scripts/transfer-guard.sh [--no-build] [--out transfer-guard-run]
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=transfer-guard-run BUILD=()
while [ $# -gt 0 ]; do
    case "$1" in
        --no-build) BUILD=(--no-build) ;;
        --out) OUT="$2"; shift ;;
        *) echo "transfer-guard: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
bash scripts/transfer-recipe.sh --quick "${BUILD[@]}" --no-curve --seeds 9 --spreads 3 \
    --out "$OUT" -- --stage1-steps 4000
