#!/usr/bin/env bash
# Packs the GPU benchmark into one folder of at most 64 MiB, to carry to a GPU host that has
# no Rust and no network: the stripped x86-64 step benchmark of every GPU path this machine
# can build (the default build's: burn's CPU backend and wgpu, which takes WGSL through the
# host's Vulkan driver), the JAX reference, and run.sh. Then runs that run.sh here, unless
# --pack-only.
#   scripts/bench-gpu.sh [--pack-only] [--out DIR]     # default DIR: target-dir/../bench-gpu
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
out="$(dirname "$CARGO_TARGET_DIR")/bench-gpu"
run=1
while [ $# -gt 0 ]; do
    case $1 in
    --pack-only) run=0 ;;
    --out) out=$2; shift ;;
    *) echo "bench-gpu: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
binary=$(cargo bench -p trainer-core --bench model_step --no-run --message-format=json 2>/dev/null |
    python3 -c 'import json,sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "model_step" and m.get("executable"):
        print(m["executable"])')
rm -rf "$out"
mkdir -p "$out"
cp "$binary" "$out/model_step"
strip "$out/model_step"
cp tools/reference/xfactor_reference.py scripts/bench-gpu/run.sh "$out/"
bytes=$(du -sb "$out" | cut -f1)
limit=$((64 * 1024 * 1024))
echo "bench-gpu: packed $out ($bytes bytes; the limit is $limit)"
if [ "$bytes" -gt "$limit" ]; then
    echo "bench-gpu: the folder is over 64 MiB" >&2
    exit 1
fi
if [ "$run" = 1 ]; then
    bash "$out/run.sh"
fi
