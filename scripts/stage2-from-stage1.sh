#!/usr/bin/env bash
# Stage 2 again from a finished local run's stage-1 final commit, with other stage-2 settings
# (issue 52: does stage 2 keep the transfer?). Copies the run's final stage-1 checkpoint into
# OUT, writes the job record the coordinator resumes from (stage 2, nothing of it done yet) and
# the run's cluster YAML with stage 2's steps, peak learning rate (and micro-batch, warm-up and
# its starting rate, commit interval) changed and no
# evaluation (and without a --stage1-only run's `stop_after`), then runs a coordinator and two
# CPU workers on loopback until stage 2 commits.
# Evaluate the result with `xfactor evaluate --context-views 1|2`.
#
#   scripts/stage2-from-stage1.sh RUN_DIR OUT_DIR [--steps 150] [--peak-lr 0.001] [--micro-batch N]
#                                 [--warmup-steps N] [--initial-lr LR] [--checkpoint-every N]
#
# --micro-batch changes only how each worker splits its share of a step (the same samples, the
# same mean gradient, summed in another order): a probe of how much stage 2 depends on the
# order of float additions.
set -euo pipefail
RUN="${1:?usage: stage2-from-stage1.sh RUN_DIR OUT_DIR [--steps N] [--peak-lr LR] [--micro-batch N] [--warmup-steps N] [--initial-lr LR] [--checkpoint-every N]}"
OUT="${2:?usage: stage2-from-stage1.sh RUN_DIR OUT_DIR [--steps N] [--peak-lr LR] [--micro-batch N] [--warmup-steps N] [--initial-lr LR] [--checkpoint-every N]}"
shift 2
# Both paths are the caller's: resolved before the script moves to the repository root.
RUN=$(cd "$RUN" && pwd)
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
case "$RUN/" in
    "$OUT"/*) echo "stage2-from-stage1: OUT_DIR $OUT holds the run $RUN, and is emptied first" >&2; exit 2 ;;
esac
cd "$(dirname "$0")/.."
source scripts/env.sh
STEPS=150 LR=0.001 MICRO= WARMUP= INITIAL= EVERY=
while [ $# -gt 0 ]; do
    case "$1" in
        --steps) STEPS="$2"; shift ;;
        --peak-lr) LR="$2"; shift ;;
        --micro-batch) MICRO="$2"; shift ;;
        --warmup-steps) WARMUP="$2"; shift ;;
        --initial-lr) INITIAL="$2"; shift ;;
        --checkpoint-every) EVERY="$2"; shift ;;
        *) echo "stage2-from-stage1: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
BIN="$CARGO_TARGET_DIR/release"
FINAL=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["stage1_final"])' \
    "$RUN/checkpoints/job.json")
[ -f "$FINAL/COMMIT.json" ] || { echo "stage2-from-stage1: $FINAL is no committed checkpoint" >&2; exit 1; }
# Says which stage 1 it builds on, with that run's own stage-1 TPS where it evaluated one: a
# stage 2 started from the wrong run's commit scores that run's stage 1, not the one meant.
python3 - "$RUN" "$FINAL" <<'PY' >&2
import glob, sys
run, final = sys.argv[1:]
tps = "not evaluated"
for path in glob.glob(run + "/checkpoints/evaluation/*/report.md"):
    header, found = None, []
    for line in open(path):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if "SE3_Auc@30" in cells:
            header = cells.index("SE3_Auc@30")
        elif header is not None and cells[1:3] == ["trained", "TPS"]:
            found.append(f"{cells[0]}: {cells[header]}")
    if found:
        tps = "; ".join(found)
print(f"stage2-from-stage1: from {final} (the run's own evaluation, TPS AUC@30: {tps})")
PY
rm -rf "$OUT"
mkdir -p "$OUT/checkpoints/stage1"
cp -r "$FINAL" "$OUT/checkpoints/stage1/"
STAGE1="$OUT/checkpoints/stage1/$(basename "$FINAL")"
PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
python3 - "$RUN/cluster.yaml" "$OUT" "$LR" "$STEPS" "$PORT" "$STAGE1" "$MICRO" "$WARMUP" "$INITIAL" "$EVERY" <<'PY'
import json, re, sys
source, out, lr, steps, port, stage1, micro, warmup, initial, every = sys.argv[1:]
yaml = open(source).read()
yaml = re.sub(r"listen: .*", f"listen: 127.0.0.1:{port}", yaml)
yaml = re.sub(r"(checkpoint:\n  uri: ).*", lambda m: m.group(1) + out + "/checkpoints", yaml)
if every:
    yaml = re.sub(r"(checkpoint:\n  uri: .*\n  every: )\d+", lambda m: m.group(1) + every, yaml)
stage2 = re.search(r"stage2:\n(  .*\n)+", yaml).group(0)
# Word-bounded, so the warm-up's `warmup_steps` keeps its value.
changed = re.sub(r"\b(curriculum_steps|total_steps|steps): \d+", lambda m: f"{m.group(1)}: {steps}", stage2)
changed = re.sub(r"peak_lr: [0-9.e-]+", f"peak_lr: {lr}", changed)
if micro:
    changed = re.sub(r"micro_batch: \d+", f"micro_batch: {micro}", changed)
if warmup:
    changed = re.sub(r"warmup_steps: \d+", f"warmup_steps: {warmup}", changed)
if initial:
    changed = re.sub(r"initial_lr: [0-9.e+-]+", f"initial_lr: {initial}", changed)
yaml = re.sub(r"\nevaluate:\n(  .*\n)+", "\n", yaml.replace(stage2, changed))
# A run made with `xfactor-local --stage1-only` says to stop after stage 1; this one trains stage 2.
yaml = re.sub(r"^stop_after: .*\n", "", yaml, flags=re.M)
open(out + "/cluster.yaml", "w").write(yaml)
record = {"job": "local-demo", "stage": 2, "earlier_commits": [], "stage1_final": stage1,
          "last_commit": {"stage": 1, "step": int(re.search(r"step-0*(\d+)", stage1).group(1)),
                          "location": stage1}}
json.dump(record, open(out + "/checkpoints/job.json", "w"))
PY
TOKEN=$(sed -n 's/^  token: //p' "$OUT/cluster.yaml" | head -1)
"$BIN/xfactor-coordinator" run --config "$OUT/cluster.yaml" >"$OUT/coordinator.log" 2>&1 &
COORDINATOR=$!
# `|| true` on both: errexit holds inside the trap, and a coordinator that already ended would
# otherwise turn a finished stage 2 into a failure.
trap 'kill $COORDINATOR 2>/dev/null || true; pkill -f "scratch $OUT/scratch" 2>/dev/null || true' EXIT
sleep 2
for i in 0 1; do
    "$BIN/xfactor-worker" --coordinator "http://127.0.0.1:$PORT" --token "$TOKEN" \
        --name "local-$i" --scratch "$OUT/scratch" >"$OUT/worker-$i.log" 2>&1 &
done
wait "$COORDINATOR"
ls -d "$OUT"/checkpoints/stage2/step-*
