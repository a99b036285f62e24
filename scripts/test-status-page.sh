#!/usr/bin/env bash
# The coordinator's status page in a real browser (issue 53): a local job (coordinator and two
# workers as processes on loopback) trains while headless Chromium, from Debian's `chromium`
# package, loads the page: refused without the job token (the sign-in form, none of the job),
# then signed in (a local form posting the token, as a person would): the workers and the step
# are on it; after one worker is killed, the page shows it lost and the generation it ended.
# Screenshots of both go to --shots (docs/ keeps the README's). With `promtool` installed, the
# coordinator's /metrics is also checked by `promtool check metrics`. Exits 1 on any failure.
#
#   scripts/test-status-page.sh [--shots DIR] [--no-build]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
SHOTS="" BUILD=1
while [ $# -gt 0 ]; do
    case "$1" in
        --shots) SHOTS="$2"; shift ;;
        --no-build) BUILD=0 ;;
        *) echo "test-status-page: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
BROWSER=$(command -v chromium || command -v chromium-browser || true)
[ -n "$BROWSER" ] || { echo "test-status-page: no chromium (apt-get install chromium)" >&2; exit 1; }
if [ "$BUILD" = 1 ]; then
    cargo build --release -p coordinator -p worker --bins
fi
BIN="$CARGO_TARGET_DIR/release"
WORK=$(mktemp -d)
SHOTS=${SHOTS:-$WORK/shots}
mkdir -p "$SHOTS"
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
PORT=$(free_port) RPC_PORT=$(free_port)
TOKEN=local-harness-token
# The job as an operator runs one: the coordinator on the cluster YAML, the workers on their
# own (xfactor-local only writes the data and the YAML here, since it stops a job whose worker
# dies, and this test kills one).
"$BIN/xfactor-local" --dir "$WORK/run" --port "$RPC_PORT" --stage1-steps 5000 --stage2-steps 3 \
    --checkpoint-every 20 --no-evaluate --prepare-only >"$WORK/local.log" 2>&1
"$BIN/xfactor-coordinator" run --config "$WORK/run/cluster.yaml" --metrics-address "127.0.0.1:$PORT" \
    >"$WORK/coordinator.log" 2>&1 &
PIDS=($!)
for i in 0 1; do
    "$BIN/xfactor-worker" --coordinator "http://127.0.0.1:$RPC_PORT" --token "$TOKEN" --name "local-$i" \
        --scratch "$WORK/run/scratch" >"$WORK/worker-$i.log" 2>&1 &
    PIDS+=($!)
done
trap 'kill "${PIDS[@]}" 2>/dev/null; rm -rf "$WORK"' EXIT
fail() { echo "test-status-page: $*" >&2; tail -5 "$WORK"/*.log >&2; exit 1; }

# The page as Chromium shows it: its DOM on stdout, a screenshot in $2 when given. $1 is the
# address loaded; every load starts from a fresh profile, so no cookie survives between them.
browse() {
    local profile
    profile=$(mktemp -d -p "$WORK")
    local shot=()
    [ -n "${2:-}" ] && shot=(--screenshot="$2" --window-size=1280,1800)
    timeout 60 "$BROWSER" --headless --no-sandbox --disable-gpu --user-data-dir="$profile" \
        --virtual-time-budget=3000 "${shot[@]}" --dump-dom "$1" 2>/dev/null
}
# A local page that signs in with $1 as a person would: the form posted, the answer followed.
cat >"$WORK/sign-in.html" <<HTML
<form method="post" action="http://127.0.0.1:$PORT/login"><input name="token" value="__TOKEN__"></form>
<script>document.forms[0].submit()</script>
HTML
sign_in() { sed "s/__TOKEN__/$1/" "$WORK/sign-in.html" >"$WORK/sign-in-$2.html"; echo "file://$WORK/sign-in-$2.html"; }

api() { curl -s -H "Authorization: Bearer $TOKEN" "http://127.0.0.1:$PORT/api/status"; }
field() { python3 -c "import json, sys; s = json.load(sys.stdin); print($1)"; }
for _ in $(seq 600); do
    step=$(api 2>/dev/null | field 's["step"] if len(s["workers"]) == 2 else -1' 2>/dev/null || echo -1)
    [ "$step" -ge 5 ] && break
    kill -0 "${PIDS[0]}" 2>/dev/null || fail "the coordinator ended before the page could be seen"
    sleep 0.5
done
[ "$step" -ge 5 ] || fail "no step on /api/status"

refused=$(browse "http://127.0.0.1:$PORT/")
grep -q "Job token" <<<"$refused" || fail "the page without the token shows no sign-in form"
grep -q "local-0" <<<"$refused" && fail "the page without the token shows the workers"
wrong=$(browse "$(sign_in not-the-token wrong)")
grep -q "not this job's token" <<<"$wrong" || fail "a wrong token is not refused"

running=$(browse "$(sign_in "$TOKEN" running)" "$SHOTS/status-running.png")
for shown in local-0 local-1 "step " Generations Commits "<svg"; do
    grep -q "$shown" <<<"$running" || fail "the signed-in page lacks '$shown'"
done

if command -v promtool >/dev/null; then
    curl -s "http://127.0.0.1:$PORT/metrics" | promtool check metrics || fail "promtool check metrics"
    metrics_checked=yes
else
    metrics_checked=no_promtool
fi

kill -9 "${PIDS[2]}"
for _ in $(seq 300); do
    lost=$(api | field 'sum(w["state"] == "lost" for w in s["workers"])' 2>/dev/null || echo 0)
    [ "$lost" -ge 1 ] && break
    sleep 0.5
done
[ "$lost" -ge 1 ] || fail "the killed worker never shows as lost"
faulted=$(browse "$(sign_in "$TOKEN" faulted)" "$SHOTS/status-worker-killed.png")
grep -q ">lost<" <<<"$faulted" || fail "the page does not show the killed worker lost"
grep -q "ended at step" <<<"$faulted" || fail "the page does not show the generation that ended"
echo "bench=status_page refused=yes wrong_token_refused=yes workers_shown=2 killed_worker_shown=lost generation_end_shown=yes promtool_metrics=$metrics_checked shots=$SHOTS"
