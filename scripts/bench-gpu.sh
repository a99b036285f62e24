#!/usr/bin/env bash
# Packs the GPU benchmark into one folder of at most 64 MiB, to carry to a GPU host that has
# no Rust and no network, then runs its run.sh here unless --pack-only. Stripped x86-64
# binaries, xz-compressed (gzip left the `gpu` folder at 81 MB; xz at 50):
#   default  the step benchmark of the default build (burn's CPU backend, and wgpu: WGSL
#            through the host's Vulkan driver), xfactor-local, xfactor-coordinator and the
#            default xfactor-worker
#   gpu      the step benchmark and xfactor-worker built with `vulkan,cuda` (SPIR-V, and CUDA
#            with kernels compiled by NVRTC at run time; no libtorch, so it loads on any host),
#            with xfactor-local and xfactor-coordinator (no tensor library: the same either way);
#            its worker replaces the default one in the folder (and in the target folder: it
#            loads on any host, and is the build CI tests: XFACTOR_FEATURES=vulkan,cuda)
#   roads    on request: the step benchmark of the `vulkan,libtorch,cuda` build CI tests
#            (scripts/test-gpu-roads.sh); it loads PyTorch 2.9.0's libtorch
# then the JAX reference and run.sh. A path that does not build is written to not-built.txt.
# xfactor-local runs the workers beside it, so the folder's job trains on the gpu worker.
#   scripts/bench-gpu.sh [--pack-only] [--out DIR] [--paths default,gpu[,roads]]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
out="$(dirname "$CARGO_TARGET_DIR")/bench-gpu"
run=1
paths=default,gpu
while [ $# -gt 0 ]; do
    case $1 in
    --pack-only) run=0 ;;
    --out) out=$2; shift ;;
    --paths) paths=$2; shift ;;
    *) echo "bench-gpu: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done

# The executables that `$@` (a cargo command line that builds) writes, one path a line.
built_executables() {
    "$@" --message-format=json 2>"$out/build.log" |
        python3 -c 'import json,sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable"):
        print(m["target"]["name"], m["executable"])'
}

# Strips and compresses one executable into the folder as NAME.xz.
pack() { # name binary
    cp "$2" "$out/$1"
    strip "$out/$1"
    xz -9 -T0 -f "$out/$1"
}

# Builds and packs the step benchmark of one road's build (and, with `worker`, its worker).
pack_road() { # path feature-command... ; the bench is named model_step-PATH
    local path=$1 name executable packed=0
    shift
    while read -r name executable; do
        case $name in
        model_step) pack "model_step-$path" "$executable"; packed=1 ;;
        xfactor-worker | xfactor-local | xfactor-coordinator) pack "$name" "$executable" ;;
        esac
    done < <(built_executables "$@")
    [ "$packed" = 1 ]
}

rm -rf "$out"
mkdir -p "$out"
: >"$out/not-built.txt"
for path in ${paths//,/ }; do
    case $path in
    default) command=(cargo build --release -p trainer-core --bench model_step
        -p coordinator --bin xfactor-local --bin xfactor-coordinator -p worker --bin xfactor-worker) ;;
    # evaluation is selected too, so it takes the features it takes in CI's `--workspace`
    # build (worker links it) and that build's worker is reused, not compiled again.
    gpu) command=(scripts/build-feature.sh vulkan,cuda build --release -p trainer-core
        --bench model_step -p worker --bin xfactor-worker -p evaluation
        -p coordinator --bin xfactor-local --bin xfactor-coordinator) ;;
    roads) command=(scripts/build-feature.sh vulkan,libtorch,cuda build --release
        -p trainer-core --bench model_step) ;;
    *) echo "bench-gpu: unknown build $path (expected default, gpu, roads)" >&2; exit 2 ;;
    esac
    echo "bench-gpu: building $path" >&2
    if ! pack_road "$path" "${command[@]}"; then
        echo "path=$path status=not-built reason=\"$(grep -m1 -E '^error' "$out/build.log" || tail -1 "$out/build.log")\"" >>"$out/not-built.txt"
    fi
done
rm -f "$out/build.log"
# The gpu build's benchmark runs cpu and wgpu too: one benchmark keeps the folder under 64 MiB.
if [ -e "$out/model_step-gpu.xz" ]; then
    rm -f "$out/model_step-default.xz"
fi
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
