#!/usr/bin/env bash
# Entry point of the packed GPU benchmark folder (made by scripts/bench-gpu.sh). Runs on the
# host it is copied to, without Rust or a network: first what the host offers, then, in one
# run, our stage-1 step per compute path (cpu and wgpu from the default build, vulkan and
# libtorch from the feature builds) for the benchmark and paper models at batch 8 and at the
# largest batch that fits, in f32 (beside the JAX peer's) and in the release's mixed precision
# (bf16, f16). Every figure is a `key=value` line; a path that cannot run says why and the
# rest go on.
#   ./run.sh                 # STEPS=5 steps per measurement by default
set -uo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
steps="${STEPS:-5}"
mkdir -p "$here/bin"
for packed in "$here"/model_step-*.gz; do
    [ -e "$packed" ] || continue
    binary="$here/bin/$(basename "$packed" .gz)"
    [ -x "$binary" ] || { gunzip -c "$packed" >"$binary" && chmod +x "$binary"; }
done

echo "host date=$(date -u +%F) kernel=$(uname -r) cores=$(nproc)"
gpu=0
if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    gpu=1
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader |
        while IFS=, read -r name driver memory; do
            echo "gpu name=\"${name}\" driver=${driver# } memory=\"${memory# }\""
        done
    echo "cuda version=$(nvidia-smi | sed -n 's/.*CUDA Version: *\([0-9.]*\).*/\1/p' | head -1)"
else
    echo "gpu none (no nvidia-smi, or it lists no GPU)"
fi
icd=no
for file in /usr/share/vulkan/icd.d/nvidia_icd*.json /etc/vulkan/icd.d/nvidia_icd*.json; do
    [ -e "$file" ] && icd="$file"
done
loader=no
ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1' && loader=yes
echo "vulkan nvidia_icd=$icd libvulkan=$loader"
torch=$(python3 -c 'import torch; print(torch.__version__)' 2>/dev/null || echo none)
echo "python $(python3 --version 2>&1 | tr ' ' '=') torch=$torch"

jax_python=""
for candidate in "${XFACTOR_JAX_PYTHON:-}" python3 "$HOME/.cache/xfactor-dist/jax-env/bin/python"; do
    if [ -n "$candidate" ] && "$candidate" -c 'import jax' >/dev/null 2>&1; then
        jax_python="$candidate"
        break
    fi
done
if [ -n "$jax_python" ]; then
    echo "jax $("$jax_python" -c 'import jax; print("version=" + jax.__version__, "devices=" + ",".join(d.platform for d in jax.devices()))')"
    export XFACTOR_JAX_PYTHON="$jax_python"
else
    echo "jax none (no Python here imports jax)"
fi

cat "$here/not-built.txt"

# The libtorch build links PyTorch 2.9.0's shared libraries: this host's torch, or the
# project's opt-in environment (scripts/setup-libtorch.sh) on a builder.
libtorch_ready=no
for candidate in "${XFACTOR_TORCH_PYTHON:-}" python3 "$HOME/.cache/xfactor-dist/torch-env/bin/python"; do
    [ -n "$candidate" ] || continue
    version=$("$candidate" -c 'import torch; print(torch.__version__.split("+")[0])' 2>/dev/null) || continue
    if [ "$version" = 2.9.0 ]; then
        lib=$("$candidate" -c 'import os, torch; print(os.path.join(os.path.dirname(torch.__file__), "lib"))' 2>/dev/null)
        export LD_LIBRARY_PATH="$lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
        libtorch_ready=yes
        break
    fi
    libtorch_why="the libtorch build links PyTorch 2.9.0; $candidate has torch $version"
done

# The packed binary that runs `path` (the vulkan-only build where packed, else the roads
# build, which needs libtorch), or nothing (and why on stderr) when it cannot run here.
binary_for() { # path
    local binary="$here/bin/model_step-roads"
    case $1 in
    cpu | wgpu) binary="$here/bin/model_step-default" ;;
    vulkan) [ -x "$here/bin/model_step-vulkan" ] && binary="$here/bin/model_step-vulkan" ;;
    esac
    if [ ! -x "$binary" ]; then
        return 1
    fi
    if [ "$binary" = "$here/bin/model_step-roads" ] && [ "$libtorch_ready" != yes ]; then
        echo "path=$1 status=cannot-run reason=\"the roads build loads libtorch: ${libtorch_why:-no Python here imports torch 2.9.0}\"" >&2
        return 1
    fi
    echo "$binary"
}

# The first line of the last failed measurement's stderr that says what went wrong.
why_failed() {
    { grep -m1 -iE 'error|panicked|unavailable' "$here/last-error.log" || tail -1 "$here/last-error.log"; } |
        tr -d '"' | cut -c1-300
}

# One measurement: our step (with the JAX peer when asked), as the bench's key=value line.
measure() { # backend model batch precision jax
    local bench args=(--backend "$1" --model "$2" --batch "$3" --precision "$4" --steps "$steps"
        --skip-paper --reference "$here/xfactor_reference.py")
    bench=$(binary_for "$1" 2>/dev/null) || return 1
    [ "$5" = jax ] || args+=(--skip-jax)
    timeout "${LIMIT_S:-900}" "$bench" "${args[@]}" 2>"$here/last-error.log" | grep '^backend='
}

# The largest batch that fits: doubles from 8 while a run succeeds (each in its own process,
# so running out of memory ends only that run).
largest_batch() { # backend model
    local batch=8 fits=0
    while [ "$batch" -le "${MAX_BATCH:-1024}" ] && measure "$1" "$2" "$batch" f32 no >/dev/null; do
        fits=$batch
        batch=$((batch * 2))
    done
    echo "$fits"
}

paths=()
candidates=(cpu wgpu vulkan libtorch)
[ "$gpu" = 1 ] && candidates=(wgpu vulkan libtorch)
for path in "${candidates[@]}"; do
    binary_for "$path" >/dev/null && paths+=("$path")
done
models=(benchmark)
if [ "$gpu" = 1 ]; then
    models=(benchmark paper)
else
    echo "model=paper status=skipped reason=\"no GPU: one step of the 305M model at 256x256 takes minutes on a CPU\""
fi
for model in "${models[@]}"; do
    for path in "${paths[@]}"; do
        batches=(8)
        if [ "$gpu" = 1 ]; then
            max=$(largest_batch "$path" "$model")
            echo "backend=$path model=$model largest_batch=$max"
            [ "$max" -gt 8 ] && batches+=("$max")
        fi
        for batch in "${batches[@]}"; do
            measure "$path" "$model" "$batch" f32 jax ||
                echo "backend=$path model=$model batch=$batch status=failed reason=\"$(why_failed)\""
            for half in bf16 f16; do
                measure "$path" "$model" "$batch" "$half" no ||
                    echo "backend=$path model=$model batch=$batch precision=$half status=failed reason=\"$(why_failed)\""
            done
        done
    done
done
