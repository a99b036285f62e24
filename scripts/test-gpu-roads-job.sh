#!/usr/bin/env bash
# A real job on a GPU road chosen at run time: the coordinator and two worker processes on
# loopback train both stages with `workers.device: vulkan` (SPIR-V on lavapipe here), using a
# worker built with the vulkan feature. Passes when the job finishes and the
# coordinator's `status` showed both workers on vulkan. Called by scripts/test-gpu-roads.sh.
#   scripts/test-gpu-roads-job.sh WORKER-BINARY
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
worker=${1:?usage: scripts/test-gpu-roads-job.sh WORKER-BINARY}
bin="$CARGO_TARGET_DIR/release"
dir=$(mktemp -d)
trap 'pkill -P $$ 2>/dev/null || true; rm -rf "$dir"' EXIT
"$bin/xfactor-local" --dir "$dir" --workers 2 --stage1-steps 12 --stage2-steps 2 \
    --checkpoint-every 6 --no-evaluate --prepare-only >/dev/null 2>&1
sed -i 's/^  device: cpu$/  device: vulkan/' "$dir/cluster.yaml"
grep -q '^  device: vulkan$' "$dir/cluster.yaml"
address="http://$(sed -n 's/^listen: //p' "$dir/cluster.yaml")"
token=$(sed -n 's/^  token: //p' "$dir/cluster.yaml")
"$bin/xfactor-coordinator" run --config "$dir/cluster.yaml" --report "$dir/report.json" \
    >"$dir/coordinator.log" 2>&1 &
coordinator=$!
for rank in 0 1; do
    XFACTOR_TOKEN="$token" "$worker" --coordinator "$address" --no-slurm --name "roads-$rank" \
        >"$dir/worker-$rank.log" 2>&1 &
done
on_vulkan=0
while kill -0 "$coordinator" 2>/dev/null; do
    status=$("$bin/xfactor-coordinator" status --address "$address" --token "$token" 2>/dev/null || true)
    if [ "$(grep -c 'backend=vulkan' <<<"$status")" = 2 ]; then
        on_vulkan=1
        grep '^worker=' <<<"$status"
    fi
    [ "$on_vulkan" = 1 ] && break
    sleep 0.5
done
if ! wait "$coordinator"; then
    tail -20 "$dir"/*.log >&2
    echo "roads-job: the coordinator failed" >&2
    exit 1
fi
outcome=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["outcome"])' "$dir/report.json")
losses=$(python3 -c 'import json,sys; s=json.load(open(sys.argv[1]))["steps"]; print("%.4f->%.4f" % (s[0]["loss"], s[11]["loss"]))' "$dir/report.json")
echo "roads-job: device=vulkan workers=2 outcome=$outcome stage1_loss=$losses status_showed_vulkan=$on_vulkan"
[ "$outcome" = finished ] && [ "$on_vulkan" = 1 ]
