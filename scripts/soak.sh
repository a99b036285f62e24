#!/usr/bin/env bash
# The soak under random faults (scripts/soak.py says what it injects and what it checks).
#
#   sudo -E scripts/soak.sh [--no-build] [--seed N] [--minutes M] [--stage1-steps N] [--stage2-steps N]
#                           [--instance I]   (0-9: its own subnet and names, to run beside others)
#                           [--keep]         (keep the logs and store of a soak that passed; one
#                                             that failed always keeps them)
#
# Needs root (network namespaces, tc, tcpdump). Installs tcpdump if missing; moto's S3 server
# comes from scripts/setup.sh. --minutes is the window in which faults start; the job must
# finish after it. Without step counts, the steps are sized so that the job outlasts the window
# a little: 11 steps of stage 1 and a quarter as many of stage 2 per second of window (the
# first 3-minute soak on this 2-core machine ran 2,500 steps in 203 s with four workers under
# its eight faults).
# Exits non-zero on any broken invariant, or when the job does not finish.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh

build=1 seed=1 minutes=20 stage1="" stage2="" instance=0 keep=0
while [ $# -gt 0 ]; do
    case "$1" in
        --no-build) build=0 ;;
        --seed) seed=$2; shift ;;
        --minutes) minutes=$2; shift ;;
        --stage1-steps) stage1=$2; shift ;;
        --stage2-steps) stage2=$2; shift ;;
        --instance) instance=$2; shift ;;
        --keep) keep=1 ;;
        *) echo "soak: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
if [ "$(id -u)" != 0 ]; then
    echo "soak: needs root for network namespaces, tc and tcpdump; run: sudo -E $0" >&2
    exit 1
fi
for tool in ip tc; do
    command -v "$tool" >/dev/null || { echo "soak: $tool is missing (iproute2)" >&2; exit 2; }
done
if ! command -v tcpdump >/dev/null; then
    apt-get install -y -qq tcpdump >/dev/null
fi
python="${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/s3-env/bin/python"
[ -x "$python" ] || bash scripts/setup.sh
if [ "$build" = 1 ]; then
    cargo build --release -p coordinator -p worker --bins
fi
stage1=${stage1:-$(awk -v m="$minutes" 'BEGIN { printf "%d", m * 60 * 11 }')}
stage2=${stage2:-$(( stage1 / 4 ))}
dir=$(mktemp -d /tmp/xfactor-soak.XXXXXX)
echo "soak: seed $seed, logs in $dir" >&2
status=0
"$python" scripts/soak.py --seed "$seed" --minutes "$minutes" --stage1-steps "$stage1" \
    --stage2-steps "$stage2" --dir "$dir" --binaries "$CARGO_TARGET_DIR/release" --instance "$instance" \
    || status=$?
# A passed soak's folder (logs, the S3 store, the capture) takes gigabytes: gone unless kept.
if [ "$status" = 0 ] && [ "$keep" = 0 ]; then
    rm -rf "$dir"
else
    echo "soak: logs kept in $dir" >&2
fi
exit "$status"
