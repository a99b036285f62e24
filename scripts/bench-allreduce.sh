#!/usr/bin/env bash
# The all-reduce benchmark (issue 5): builds the coordinator and worker binaries it starts, then
# prints one key=value line (algbw_gbs_1mb_lane= ... algbw_gbs_100mb_stream=: one TCP lane, then the gRPC stream, and step_s_1worker= /
# step_s_2workers= / comm_share_2workers= for the benchmark model). Extra arguments go to the
# benchmark (e.g. --repeats 9 --model-steps 10).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
cargo build --release -p coordinator -p worker -p evaluation --bins
cargo bench -p worker --bench allreduce -- "$@"
