#!/usr/bin/env bash
# A TLS lane beside a plain one (issue 51): two worker processes on loopback all-reduce the
# paper model's 1.22 GB of float32 gradients on one lane, plain and over TLS (the test
# certificates of proto/testdata/tls, as a job with `tls:` runs), in alternating pairs so that
# both see the same machine. Each run's figure is the median of --repeats all-reduces; the last
# line gives the medians over the pairs, the ratio of throughputs (plain time / TLS time) per
# pair, its median and range, and exits 1 when the median ratio is under --target.
#
#   scripts/bench-tls.sh [--pairs 5] [--repeats 5] [--size-mb 1220] [--target 0.5] [--no-build]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
PAIRS=5 REPEATS=5 SIZE_MB=1220 TARGET=0.5 BUILD=1
while [ $# -gt 0 ]; do
    case "$1" in
        --pairs) PAIRS="$2"; shift ;;
        --repeats) REPEATS="$2"; shift ;;
        --size-mb) SIZE_MB="$2"; shift ;;
        --target) TARGET="$2"; shift ;;
        --no-build) BUILD=0 ;;
        *) echo "bench-tls: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
if [ "$BUILD" = 1 ]; then
    cargo build --release -p worker --bin xfactor-worker
fi
WORKER="$CARGO_TARGET_DIR/release/xfactor-worker"
SCRATCH="$(mktemp -d)"
trap 'rm -rf "$SCRATCH"' EXIT

free_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# One all-reduce run on one lane, $1 = plain or tls: prints its median seconds.
run() {
    local peers pids=() tls=()
    peers="127.0.0.1:$(free_port),127.0.0.1:$(free_port)"
    if [ "$1" = tls ]; then tls=(--tls-dir proto/testdata/tls); fi
    for r in 0 1; do
        "$WORKER" allreduce-bench --rank "$r" --peers "$peers" --lanes 1 "${tls[@]}" \
            --sizes-mb "$SIZE_MB" --repeats "$REPEATS" >"$SCRATCH/rank-$r.out" 2>"$SCRATCH/rank-$r.err" &
        pids+=($!)
    done
    for pid in "${pids[@]}"; do
        wait "$pid" || { echo "bench-tls: a $1 rank failed:" >&2; cat "$SCRATCH"/rank-*.err >&2; exit 1; }
    done
    local seconds
    seconds=$(grep -o 'seconds=[0-9.]*' "$SCRATCH/rank-0.out" | cut -d= -f2)
    [ -n "$seconds" ] || { echo "bench-tls: no figure from the $1 run" >&2; exit 1; }
    echo "$seconds"
}

PLAIN=() TLS=()
for pair in $(seq 1 "$PAIRS"); do
    plain=$(run plain)
    tls=$(run tls)
    PLAIN+=("$plain") TLS+=("$tls")
    awk -v p="$pair" -v a="$plain" -v b="$tls" -v mb="$SIZE_MB" 'BEGIN {
        printf "bench=tls_lane_pair pair=%d size_mb=%s plain_s=%.4f tls_s=%.4f plain_gbs=%.3f tls_gbs=%.3f ratio=%.3f\n", p, mb, a, b, mb / 1000 / a, mb / 1000 / b, a / b
    }'
done
printf '%s\n' "${PLAIN[@]}" >"$SCRATCH/plain"
printf '%s\n' "${TLS[@]}" >"$SCRATCH/tls"
paste "$SCRATCH/plain" "$SCRATCH/tls" | awk -v mb="$SIZE_MB" -v target="$TARGET" -v repeats="$REPEATS" -v cores="$(nproc)" '
    function median(v, n,    i, j, t) {
        for (i = 1; i <= n; i++) for (j = i + 1; j <= n; j++) if (v[j] < v[i]) { t = v[i]; v[i] = v[j]; v[j] = t }
        return n % 2 ? v[(n + 1) / 2] : (v[n / 2] + v[n / 2 + 1]) / 2
    }
    { n++; plain[n] = $1; tls[n] = $2; ratio[n] = $1 / $2
      low = (n == 1 || ratio[n] < low) ? ratio[n] : low
      high = (n == 1 || ratio[n] > high) ? ratio[n] : high }
    END {
        r = median(ratio, n)
        printf "bench=tls_lane size_mb=%s pairs=%d repeats=%d cores=%d plain_s_median=%.4f tls_s_median=%.4f ratio_median=%.3f ratio_min=%.3f ratio_max=%.3f target=%s met=%s\n", mb, n, repeats, cores, median(plain, n), median(tls, n), r, low, high, target, (r >= target ? "yes" : "no")
        exit !(r >= target)
    }'
