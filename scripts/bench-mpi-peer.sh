#!/usr/bin/env bash
# The peer of the all-reduce benchmark on this machine: OpenMPI's MPI_Allreduce between 2
# ranks over TCP loopback (shared memory disabled), same sizes and timing rule as
# scripts/bench-allreduce.sh. Installs openmpi-bin and libopenmpi-dev when missing.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v mpicc >/dev/null || ! command -v mpirun >/dev/null; then
    sudo_cmd=""
    if [ "$(id -u)" != 0 ]; then sudo_cmd="sudo"; fi
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends \
        openmpi-bin libopenmpi-dev >/dev/null
fi
out="${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/mpi-allreduce"
mkdir -p "$(dirname "$out")"
mpicc -O2 -o "$out" tools/mpi-peer/allreduce.c
mpirun --allow-run-as-root --oversubscribe -np 2 --mca btl self,tcp --mca pml ob1 \
    --mca btl_tcp_if_include lo "$out" "$@"
