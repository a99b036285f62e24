#!/usr/bin/env bash
# Packs the GPU benchmark into one folder of at most 64 MiB, to carry to a GPU host that has
# no Rust and no network: the stripped x86-64 step benchmark of every GPU path this machine
# can build, gzipped: `default` (burn's CPU backend and wgpu, which takes WGSL through the
# host's Vulkan driver), `roads` (the vulkan and libtorch features together, the build
# scripts/test-gpu-roads.sh makes, so the two share artifacts; it loads PyTorch 2.9.0's
# libtorch), and on request `vulkan` alone (SPIR-V, for a host without that PyTorch; another
# full build of burn); then the JAX reference and run.sh. Then runs that run.sh here, unless
# --pack-only. A path that does not build is written to not-built.txt with why.
#   scripts/bench-gpu.sh [--pack-only] [--out DIR] [--paths default,roads[,vulkan]]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
out="$(dirname "$CARGO_TARGET_DIR")/bench-gpu"
run=1
paths=default,roads
while [ $# -gt 0 ]; do
    case $1 in
    --pack-only) run=0 ;;
    --out) out=$2; shift ;;
    --paths) paths=$2; shift ;;
    *) echo "bench-gpu: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done

# The executable of the model_step bench that `$@` (a cargo command line) builds.
bench_binary() {
    "$@" --bench model_step --no-run --message-format=json 2>"$out/build.log" |
        python3 -c 'import json,sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "model_step" and m.get("executable"):
        print(m["executable"])'
}

# Strips and gzips one build's benchmark into the folder as model_step-NAME.gz.
pack() { # name binary
    cp "$2" "$out/model_step-$1"
    strip "$out/model_step-$1"
    gzip -9 -f "$out/model_step-$1"
}

rm -rf "$out"
mkdir -p "$out"
: >"$out/not-built.txt"
for path in ${paths//,/ }; do
    case $path in
    default) command=(cargo bench -p trainer-core) ;;
    vulkan) command=(scripts/build-feature.sh vulkan bench -p trainer-core) ;;
    roads) command=(scripts/build-feature.sh vulkan,libtorch bench -p trainer-core) ;;
    *) echo "bench-gpu: unknown build $path (expected default, roads, vulkan)" >&2; exit 2 ;;
    esac
    echo "bench-gpu: building $path" >&2
    if binary=$(bench_binary "${command[@]}") && [ -n "$binary" ]; then
        pack "$path" "$binary"
    else
        echo "path=$path status=not-built reason=\"$(grep -m1 -E '^error' "$out/build.log" || tail -1 "$out/build.log")\"" >>"$out/not-built.txt"
    fi
done
echo "path=cuda status=not-built reason=\"burn's cuda feature downloads LLVM 23 at build time; our builders reach only package registries\"" >>"$out/not-built.txt"
rm -f "$out/build.log"
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
