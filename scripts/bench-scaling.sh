#!/usr/bin/env bash
# The data path's scaling benchmark (issue 40; docs/data-path.md). Needs root: every
# rank runs in a network namespace of its own, joined to a bridge by a veth whose egress is
# shaped with tc (netem rate and delay).
#
# A cell models N GPU hosts on links of L Gbit/s: each rank is `xfactor-worker path-bench`,
# the worker's real data path (flatten, local reduction, ring, AdamW update, checksum) on the
# paper model's parameter layout, with the forward and backward pass replaced by a wait of
# JAX's H200 step (0.47 s). The link is shaped to SIM_MBIT and the payload scaled down by
# the same factor (SIM_MBIT / L), so the ring takes as long as the real one would while two
# cores never saturate (each core's use is logged; a cell where one was busy above 90% is
# refused). Beside each cell's weak-scaling efficiency (compute / step) it prints an analytic
# ring without overlap: bus bandwidth 0.9 x link, 2 (N - 1) / N of the payload each way, and
# 2 (N - 1) hops of the shaped delay. N = 2 at 100 Gbit/s runs first, as the calibration.
# Every rank checks its parameters every step; `efficiency_auto` spreads that checksum over
# the paper model's default interval (`checksum_every: auto`), as a job runs, and the
# `rank0_*` keys split rank 0's step outside the compute and the ring.
#
# Unscaled and unshaped, the host path at the paper's size (1.22 GB of float32) between two
# ranks on loopback: copy, local reduction, ring, update, checksum, in seconds and GB/s; on
# one lane first (its copy, upload, update and checksum are what every cell then also counts:
# `full_size_host_s`, `efficiency_counting_host`), then the gRPC stream, bf16, and the ring
# over TLS with the test certificates, on one TLS lane (what a job with `tls:` runs) and on
# the gRPC stream. `scripts/bench-tls.sh` sets a TLS lane beside a plain one, ring only.
# Any failed, missing or refused cell fails the benchmark.
#
# Usage: sudo -E scripts/bench-scaling.sh [--smoke] [--no-build] [--ranks 2,4,8]
#            [--links 25,100,400] [--wires f32,bf16] [--steps N] [--skip-host-path]
# --smoke: one small cell (N = 2, 100 Gbit/s, float32, 2 steps) and no host path: CI's check.
# Every figure is one key=value line.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh

RANKS=2,4,8
LINKS=25,100,400
WIRES=f32,bf16
STEPS=8
BUILD=1
HOST_PATH=1
SIM_MBIT=100
DELAY_US=50
COMPUTE_S=0.47
PAPER_VALUES=305178624
while [ $# -gt 0 ]; do
    case "$1" in
        --smoke) RANKS=2 LINKS=100 WIRES=f32 STEPS=2 HOST_PATH=0 ;;
        --no-build) BUILD=0 ;;
        --ranks) RANKS="$2"; shift ;;
        --links) LINKS="$2"; shift ;;
        --wires) WIRES="$2"; shift ;;
        --steps) STEPS="$2"; shift ;;
        --skip-host-path) HOST_PATH=0 ;;
        *) echo "bench-scaling: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done

if [ "$(id -u)" != 0 ]; then
    echo "bench-scaling: needs root for network namespaces and tc; run: sudo -E $0 $*" >&2
    echo "bench=scaling refused=not_root"
    exit 1
fi
for tool in ip tc; do
    command -v "$tool" >/dev/null || { echo "bench-scaling: $tool is missing (iproute2)" >&2; exit 2; }
done
if [ "$BUILD" = 1 ]; then
    cargo build --release -p worker --bin xfactor-worker
fi
WORKER="$CARGO_TARGET_DIR/release/xfactor-worker"
SCRATCH="$(mktemp -d)"
LAYOUT="$SCRATCH/paper-layout.txt"
BRIDGE=xfbench0
MAX_RANKS=$(tr ',' '\n' <<<"$RANKS" | sort -n | tail -1)

cleanup() {
    for r in $(seq 0 $((MAX_RANKS - 1))); do ip netns del "xfb$r" 2>/dev/null || true; done
    ip link del "$BRIDGE" 2>/dev/null || true
    rm -rf "$SCRATCH"
}
trap cleanup EXIT

# The namespaces: rank r at 10.77.0.(r+1) behind veth xfbv<r>, all on one bridge.
setup_network() {
    ip link add "$BRIDGE" type bridge
    ip link set "$BRIDGE" up
    for r in $(seq 0 $((MAX_RANKS - 1))); do
        ip netns add "xfb$r"
        ip link add "xfbv$r" type veth peer name eth0 netns "xfb$r"
        ip link set "xfbv$r" master "$BRIDGE" up
        ip -n "xfb$r" addr add "10.77.0.$((r + 1))/24" dev eth0
        ip -n "xfb$r" link set eth0 up
        ip -n "xfb$r" link set lo up
    done
}

# Every rank's egress limited to $1 Mbit/s with $2 us of delay: netem where the kernel has it,
# else a token bucket (tbf) without the delay, and DELAY_US set to what was applied.
shape() {
    local shaper=netem
    tc -n xfb0 qdisc replace dev eth0 root netem delay "${2}us" rate "${1}mbit" limit 100000 2>/dev/null || shaper=tbf
    if [ "$shaper" = tbf ]; then
        DELAY_US=0
        echo "bench-scaling: this kernel has no netem; links shaped by tbf, without added delay" >&2
    fi
    for r in $(seq 0 $((MAX_RANKS - 1))); do
        if [ "$shaper" = netem ]; then
            tc -n "xfb$r" qdisc replace dev eth0 root netem delay "${2}us" rate "${1}mbit" limit 100000
        else
            tc -n "xfb$r" qdisc replace dev eth0 root tbf rate "${1}mbit" burst 64kb latency 100ms
        fi
    done
    SHAPER=$shaper
}

# Busy and total jiffies of every core, one "busy total" pair per line.
core_jiffies() {
    awk '/^cpu[0-9]/ { busy = $2 + $3 + $4 + $7 + $8; total = busy + $5 + $6; print busy, total }' /proc/stat
}

# The busiest core's share between two core_jiffies readings.
busiest_core() {
    paste -d' ' <(echo "$1") <(echo "$2") | awk '{ share = ($3 - $1) / (($4 - $2) + 1e-9); if (share > max) max = share } END { printf "%.3f", max }'
}

field() { tr ' ' '\n' <<<"$1" | sed -n "s/^$2=//p"; }

# Rank 0's split of its step outside the compute and the ring, as key=value pairs.
rank_phases() {
    local key out=""
    for key in copy_s local_reduce_s upload_s update_s checksum_s; do
        out="$out${out:+ }rank0_$key=$(field "$1" "$key")"
    done
    echo "$out"
}

# Fails the benchmark naming what went wrong.
fail() {
    echo "bench-scaling: $*" >&2
    exit 1
}

# Waits for every pid given; fails naming the rank output of the first that failed.
wait_ranks() {
    local label=$1 pid r=0
    shift
    for pid in "$@"; do
        wait "$pid" || fail "$label: rank $r exited with $?: $(tail -5 "$SCRATCH/$label-$r.out" "$SCRATCH/$label-$r.err" 2>/dev/null)"
        r=$((r + 1))
    done
}

# The data-path line of a rank's output; fails when it is missing or a figure is not a
# positive number.
rank_line() {
    local line key value
    line=$(grep '^bench=data_path' "$1") || fail "no bench=data_path line in $1"
    for key in step_s ring_s step_auto_s; do
        value=$(field "$line" "$key")
        awk -v v="$value" 'BEGIN { exit !(v + 0 > 0) }' || fail "$1: $key=$value is not a positive figure"
    done
    echo "$line"
}

# One cell: N ranks, link L Gbit/s, wire W. Prints the cell's line; fails when a rank fails
# or a figure is missing.
cell() {
    local n=$1 link=$2 wire=$3
    local scale chunk peers="" line before after busy
    scale=$(awk -v s="$SIM_MBIT" -v l="$link" 'BEGIN { printf "%.8f", s / (l * 1000) }')
    chunk=$(awk -v f="$scale" 'BEGIN { c = int(262144 * f); if (c < 1024) c = 1024; print c }')
    for r in $(seq 0 $((n - 1))); do peers="$peers${peers:+,}10.77.0.$((r + 1)):7100"; done
    before=$(core_jiffies)
    local pids=()
    for r in $(seq 0 $((n - 1))); do
        ip netns exec "xfb$r" "$WORKER" path-bench --rank "$r" --peers "$peers" \
            --scale "$scale" --compute-s "$COMPUTE_S" --steps "$STEPS" --wire "$wire" \
            --chunk-values "$chunk" --layout-file "$LAYOUT" >"$SCRATCH/rank-$r.out" 2>"$SCRATCH/rank-$r.err" &
        pids+=($!)
    done
    wait_ranks rank "${pids[@]}"
    after=$(core_jiffies)
    busy=$(busiest_core "$before" "$after")
    line=$(rank_line "$SCRATCH/rank-0.out") || exit 1
    awk -v line="$line" -v n="$n" -v link="$link" -v wire="$wire" -v busy="$busy" \
        -v sim="$SIM_MBIT" -v delay="$DELAY_US" -v compute="$COMPUTE_S" -v values="$PAPER_VALUES" \
        -v step="$(field "$line" step_s)" -v ring="$(field "$line" ring_s)" -v phases="$(rank_phases "$line")" \
        -v step_auto="$(field "$line" step_auto_s)" -v every="$(field "$line" checksum_every_auto)" \
        -v host="$FULL_HOST_S" -v update="$FULL_UPDATE_S" 'BEGIN {
        width = (wire == "bf16") ? 2 : 4
        bytes = values * width
        model_ring = 2 * (n - 1) / n * bytes / (0.9 * link * 1e9 / 8) + 2 * (n - 1) * delay * 1e-6
        model = compute / (compute + model_ring)
        measured = compute / step
        refused = (busy > 0.9) ? "core_saturated" : "no"
        printf "bench=scaling ranks=%d link_gbit=%d wire=%s shaped_mbit=%d delay_us=%d payload_real_gb=%.3f step_s=%.4f ring_s=%.4f efficiency=%.4f model_ring_s=%.4f model_efficiency=%.4f deviation=%.4f busiest_core=%s refused=%s checksum_every_auto=%d efficiency_auto=%.4f full_size_host_s=%.4f efficiency_counting_host=%.4f full_size_update_s=%.4f %s\n", n, link, wire, sim, delay, bytes / 1e9, step, ring, measured, model_ring, model, (measured - model) / model, busy, refused, every, compute / step_auto, host, compute / (step_auto + host), update, phases
        if (refused != "no") exit 3
    }'
}

# Unscaled and unshaped: two ranks on loopback with the paper's 1.22 GB and no compute, one
# I/O thread each (the worker daemon's), with wire $1 on $2 lanes (0: the gRPC stream, as
# the peer), and with $3 = tls the ring over TLS (the test certificates of
# proto/testdata/tls; on one lane, what a job with `tls:` runs by default).
host_path() {
    local peers="127.0.0.1:7201,127.0.0.1:7202" pids=() tls=()
    if [ "${3:-}" = tls ]; then tls=(--tls-dir proto/testdata/tls); fi
    for r in 0 1; do
        "$WORKER" path-bench --rank "$r" --peers "$peers" --compute-s 0 --steps 3 \
            --wire "$1" --lanes "$2" "${tls[@]}" --layout-file "$LAYOUT" >"$SCRATCH/host-$r.out" 2>"$SCRATCH/host-$r.err" &
        pids+=($!)
    done
    wait_ranks host "${pids[@]}"
    rank_line "$SCRATCH/host-0.out" | sed 's/^bench=data_path/bench=host_path/'
}

# What the scaled cells leave out: at full size a rank's gradient copy, upload and checksum
# (spread over the default interval) cost a good part of a second, not the milliseconds of a
# scaled cell. The float32 host path on one lane measures them first; each cell then also
# prints them (`full_size_host_s`) and its efficiency once they are counted
# (`efficiency_counting_host`). The optimizer's update is left out of that sum and printed
# beside it (`full_size_update_s`): here the CPU is the device, so it is AdamW on the CPU,
# where a GPU host runs it on the GPU.
FULL_HOST_S=0 FULL_UPDATE_S=0
if [ "$HOST_PATH" = 1 ]; then
    FIRST_HOST=$(host_path f32 1)
    echo "$FIRST_HOST"
    FULL_HOST_S=$(awk -v line="$FIRST_HOST" 'BEGIN {
        n = split(line, pairs, " ")
        for (i = 1; i <= n; i++) { split(pairs[i], kv, "="); v[kv[1]] = kv[2] }
        printf "%.4f %.4f", v["copy_s"] + v["upload_s"] + v["checksum_s"] / v["checksum_every_auto"], v["update_s"]
    }')
    read -r FULL_HOST_S FULL_UPDATE_S <<<"$FULL_HOST_S"
fi

setup_network
shape "$SIM_MBIT" "$DELAY_US"
echo "bench=scaling_config ranks=$RANKS links_gbit=$LINKS wires=$WIRES steps=$STEPS shaper=$SHAPER shaped_mbit=$SIM_MBIT delay_us=$DELAY_US compute_s=$COMPUTE_S cores=$(nproc)"
# The calibration cell first: N = 2 at 100 Gbit/s in float32.
CELL=$(cell 2 100 f32) || fail "the calibration cell failed or was refused: $CELL"
echo "calibration: $CELL"
for n in ${RANKS//,/ }; do
    for link in ${LINKS//,/ }; do
        for wire in ${WIRES//,/ }; do
            if [ "$n" = 2 ] && [ "$link" = 100 ] && [ "$wire" = f32 ]; then continue; fi
            CELL=$(cell "$n" "$link" "$wire") || fail "cell ranks=$n link_gbit=$link wire=$wire failed or was refused: $CELL"
            echo "$CELL"
        done
    done
done

if [ "$HOST_PATH" = 1 ]; then
    host_path f32 0
    host_path bf16 0
    host_path bf16 1
    host_path f32 1 tls
    host_path f32 0 tls
fi
