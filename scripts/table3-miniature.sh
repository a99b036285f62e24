#!/usr/bin/env bash
# The paper's Table 3 in miniature (issue 52): each ablation trained at the transfer recipe's
# stage-1 budget (scripts/transfer-recipe.sh: the small model, 64 generated scenes, 12000
# stage-1 steps, evaluated on 64 held-out scenes with the paper's probe; `--stage1-only`, as
# Table 3 compares stage 1), for every seed, then laid side by side by `xfactor compare`: one
# row per variant with its mean and standard deviation over seeds, one line per run with its
# bootstrap spreads and its transfers' lead over the unrelated path. A run whose folder already
# holds an evaluation is not trained again, so the table can be completed over several
# sessions; its latest evaluation is the one compared. About 30 minutes a run on 2 cores (the
# extra-view models: 35, measured with the machine to themselves).
#
#   scripts/table3-miniature.sh [--seeds 8,9] [--variants xfactor,unconstrained,...]
#                               [--out table3-runs] [--no-build]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
SEEDS=8,9 OUT=table3-runs BUILD=1
VARIANTS=xfactor,unconstrained,bottleneck,se3-plucker,extra-view-decoder,extra-view-encoder-decoder
while [ $# -gt 0 ]; do
    case "$1" in
        --seeds) SEEDS="$2"; shift ;;
        --variants) VARIANTS="$2"; shift ;;
        --out) OUT="$2"; shift ;;
        --no-build) BUILD=0 ;;
        *) echo "table3-miniature: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
# Table 3's columns as xfactor-local flags. The bottleneck autoencodes through a pose latent a
# quarter of the small preset's 16 (the paper's: 16 of 256).
flags_of() {
    case "$1" in
        xfactor) echo "--variant transfer" ;;
        unconstrained) echo "--variant autoencode" ;;
        bottleneck) echo "--variant autoencode --pose-dim 4" ;;
        se3-plucker) echo "--variant se3_plucker" ;;
        extra-view-decoder) echo "--variant extra_view_decoder" ;;
        extra-view-encoder-decoder) echo "--variant extra_view_encoder_decoder" ;;
        *) echo "table3-miniature: unknown variant $1" >&2; return 1 ;;
    esac
}
# The newest evaluation report of a run folder (none: empty).
latest_report() {
    ls -t "$1"/checkpoints/evaluation/*/report.json 2>/dev/null | head -1
}
if [ "$BUILD" = 1 ]; then
    cargo build --release -p coordinator -p worker -p evaluation --bins
fi
REPORTS=() LABELS=()
for variant in ${VARIANTS//,/ }; do
    flags=$(flags_of "$variant")
    for seed in ${SEEDS//,/ }; do
        run="$OUT/$variant/seed-$seed"
        if [ -z "$(latest_report "$run")" ]; then
            # shellcheck disable=SC2086 # the variant's flags are words
            scripts/transfer-recipe.sh --no-build --no-curve --no-check --seeds "$seed" \
                --out "$OUT/$variant" -- $flags --stage1-only
        fi
        REPORTS+=("$(latest_report "$run")")
        LABELS+=(--label "$variant")
    done
done
"$CARGO_TARGET_DIR/release/xfactor" compare "${REPORTS[@]}" "${LABELS[@]}" --stage 1 \
    --threshold 30 --out "$OUT/compare"
