#!/usr/bin/env bash
# The transfer recipe (issue 52), one run per seed: xfactor-local trains the `small` model on
# generated scenes through both stages and evaluates both on held-out scenes, then
# `xfactor curve` evaluates every stage-1 commit the same way (TPS AUC@30 against steps). One
# key=value line per seed, then the spread over the seeds and whether every seed's stage-1
# transfers lead the oracle's unrelated-path calibration by --spreads of their combined
# spreads (exit 1 when one does not; --no-check: report only, as the ablations of
# scripts/table3-miniature.sh need). The recipe's flags are scripts/transfer-recipe.flags
# (about 55 minutes a seed on 2 cores; `scripts/run.sh --transfer` runs it once); --quick reads
# scripts/transfer-quick.flags instead (the recipe's first 8000 steps, the first run's
# evaluation). Extra arguments go to xfactor-local (they override the recipe's flags; with
# --stage1-only, stage 2's figures read n/a).
#
#   scripts/transfer-recipe.sh [--quick] [--seeds 7,8,9] [--out transfer-runs] [--spreads 3]
#                              [--no-build] [--no-curve] [--no-check] [-- XFACTOR_LOCAL_FLAGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
SEEDS=7,8,9 OUT=transfer-runs SPREADS=3 BUILD=1 CURVE=1 CHECK=1
FLAGS_FILE=scripts/transfer-recipe.flags
while [ $# -gt 0 ]; do
    case "$1" in
        --seeds) SEEDS="$2"; shift ;;
        --out) OUT="$2"; shift ;;
        --spreads) SPREADS="$2"; shift ;;
        --no-build) BUILD=0 ;;
        --no-curve) CURVE=0 ;;
        --no-check) CHECK=0 ;;
        --quick) FLAGS_FILE=scripts/transfer-quick.flags ;;
        --) shift; break ;;
        *) echo "transfer-recipe: unknown argument $1 (xfactor-local's flags go after --)" >&2; exit 2 ;;
    esac
    shift
done
read_flags_file RECIPE "$FLAGS_FILE"
if [ "$BUILD" = 1 ]; then
    cargo build --release -p coordinator -p worker -p evaluation --bins
fi
BIN="$CARGO_TARGET_DIR/release"
mkdir -p "$OUT"
field() { grep -o "$1=[^ ]*" <<<"$2" | head -1 | cut -d= -f2; }

LINES=()
for seed in ${SEEDS//,/ }; do
    run="$OUT/seed-$seed"
    "$BIN/xfactor-local" --dir "$run" --seed "$seed" "${RECIPE[@]}" "$@" >"$run.log" 2>&1 \
        || { echo "transfer-recipe: seed $seed failed, see $run.log" >&2; exit 1; }
    figures=$(grep '^outcome=' "$run.log")
    # Stage 1's transfers and the unrelated-path calibration at full precision from the report
    # (the figures line rounds them), so the lead agrees with `xfactor compare`'s.
    transfers=$(python3 - "$run" <<'PY'
import glob, json, sys
report = json.load(open(glob.glob(sys.argv[1] + "/checkpoints/evaluation/*/report.json")[0]))
stage1 = next(s for s in report["stages"] if s["checkpoint"]["label"] == "stage1")
tps = stage1["trained"]["tps"]
for metrics in (tps["model"], tps["unrelated_trajectory"]):
    auc = next(t["auc"] for t in metrics["thresholds"] if t["threshold"] == 30)
    print(f"{auc:.6f} {metrics['spread']['auc30']:.6f}", end=" ")
PY
)
    read -r tps tps_spread calibration calibration_spread <<<"$transfers"
    line=$(awk -v seed="$seed" -v tps="$tps" -v ts="$tps_spread" -v cal="$calibration" -v cs="$calibration_spread" \
        -v s2="$(field stage2_tps_auc30 "$figures")" -v s2s="$(field stage2_tps_auc30_spread "$figures")" \
        -v probe="$(field stage1_probe_auc30 "$figures")" -v untrained="$(field stage1_untrained_probe_auc30 "$figures")" \
        -v psnr="$(field stage1_psnr "$figures")" -v seconds="$(field seconds "$figures")" '
        function shown(x) { return x == "" ? "n/a" : sprintf("%.3f", x) }
        BEGIN {
        lead = (tps - cal) / sqrt(ts * ts + cs * cs)
        printf "bench=transfer_recipe seed=%s stage1_tps_auc30=%.3f stage1_tps_auc30_spread=%.3f unrelated_auc30=%.3f unrelated_auc30_spread=%.3f lead_in_spreads=%.2f stage2_tps_auc30=%s stage2_tps_auc30_spread=%s stage1_probe_auc30=%s stage1_untrained_probe_auc30=%s stage1_psnr=%.2f seconds=%s\n", seed, tps, ts, cal, cs, lead, shown(s2), shown(s2s), shown(probe), shown(untrained), psnr, seconds
    }')
    echo "$line"
    LINES+=("$line")
    if [ "$CURVE" = 1 ]; then
        "$BIN/xfactor" curve --run "$run" >"$run.curve" 2>"$run.curve.log" \
            || { echo "transfer-recipe: the curve of seed $seed failed, see $run.curve.log" >&2; exit 1; }
        sed "s/^/seed=$seed /" "$run.curve"
    fi
done
printf '%s\n' "${LINES[@]}" | awk -v need="$SPREADS" -v check="$CHECK" -v flags="${RECIPE[*]} $*" '
    function value(key,    i, kv) { for (i = 1; i <= NF; i++) { split($i, kv, "="); if (kv[1] == key) return kv[2] } }
    { n++; tps[n] = value("stage1_tps_auc30"); lead = value("lead_in_spreads") + 0
      worst = (n == 1 || lead < worst) ? lead : worst; sum += tps[n] }
    END {
        mean = sum / n
        for (i = 1; i <= n; i++) var += (tps[i] - mean) ^ 2
        sd = n > 1 ? sqrt(var / (n - 1)) : 0
        printf "bench=transfer_recipe_summary seeds=%d flags=\"%s\" stage1_tps_auc30_mean=%.3f stage1_tps_auc30_sd_over_seeds=%.3f worst_lead_in_spreads=%.2f needed=%s met=%s\n", n, flags, mean, sd, worst, need, (worst >= need ? "yes" : "no")
        exit check && !(worst >= need)
    }'
