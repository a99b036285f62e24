#!/usr/bin/env bash
# Entry point of the packed GPU benchmark folder (made by scripts/bench-gpu.sh). Runs on the
# host it is copied to, without Rust or a network, and ends within DEADLINE_S (default 540 s,
# so one 15-minute GPU loan holds it with its start): first what the host offers, then our
# stage-1 step per compute path beside the JAX peer measured in the same run (on the host's
# best platform), most telling first (on a GPU the paper model at batch 8, then the benchmark
# model, the bf16 speed mode, the largest batch up to MAX_BATCH that fits; cuda, then wgpu and
# vulkan, then libtorch), a real two-worker job on the GPU, the release's half precisions last,
# and a summary table. Every figure is a `key=value` line; each step's time goes to
# steps.log as it ends; a path that cannot run says why and the rest go on.
#
# On an H200 (2026-11-27) the cuda road's first paper-model step had not ended after 270 s:
# cubecl's autotune compiled 447 candidate kernels with NVRTC, one after another on one core
# (262 s), while the GPU idled. Every run here therefore works in one folder whose cubecl.toml
# keeps compiled kernels (`[compilation] cache`) and autotune's choices in KERNEL_CACHE
# (default kernel-cache/ beside this script): a later run, or a later loan that carries the
# folder back, skips what was tuned and compiled. autotune.log lists every tuning.
#   ./run.sh      # STEPS=5 steps per measurement, DEADLINE_S=540, LIMIT_S=420 per run,
#                 # MAX_BATCH=64, JOB_STEPS=300, ROADS="cuda wgpu vulkan libtorch" (on a GPU),
#                 # KERNEL_CACHE; with OUT set, the cache and logs are copied there at the end
set -uo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
steps="${STEPS:-5}"
started=$(date +%s)
deadline="${DEADLINE_S:-540}"
results="$here/results.txt"
: >"$results"
steps_log="$here/steps.log"
: >"$steps_log"
# One working folder for every run: cubecl reads its cubecl.toml from the current folder.
work="$here/work"
kernel_cache="${KERNEL_CACHE:-$here/kernel-cache}"
mkdir -p "$work" "$kernel_cache"
cat >"$work/cubecl.toml" <<TOML
[compilation]
cache = true

[environment]
path = { directory = "$kernel_cache" }

[autotune.logger]
level = "minimal"
file = "$here/autotune.log"
append = true
TOML
mkdir -p "$here/bin"
# xz where the host has it, else Python's lzma module.
unpack() { # packed binary
    if command -v xz >/dev/null; then
        xz -dc "$1" >"$2"
    else
        python3 -c 'import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], "wb"))' "$1" "$2"
    fi
}
for packed in "$here"/*.xz; do
    [ -e "$packed" ] || continue
    binary="$here/bin/$(basename "$packed" .xz)"
    [ -x "$binary" ] || { unpack "$packed" "$binary" && chmod +x "$binary"; }
done

# Seconds left before the deadline.
left() { echo $((deadline - ($(date +%s) - started))); }

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
# The NVIDIA Vulkan ICD where the driver ships it outside the loader's default folders, and
# the CUDA toolkit's NVRTC, which compiles the cuda road's kernels at run time.
for icd in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json; do
    [ -e "$icd" ] && export VK_DRIVER_FILES="${VK_DRIVER_FILES:-$icd}"
done
for cuda in "${CUDA_PATH:-}" /usr/local/cuda; do
    if [ -n "$cuda" ] && [ -d "$cuda/lib64" ]; then
        export LD_LIBRARY_PATH="$cuda/lib64${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
        break
    fi
done
loader=no
ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1' && loader=yes
nvrtc=no
first_lib="${LD_LIBRARY_PATH:-}"
{ ldconfig -p 2>/dev/null | grep -q libnvrtc.so || ls "${first_lib%%:*}"/libnvrtc.so* >/dev/null 2>&1; } && nvrtc=yes
echo "vulkan icd=${VK_DRIVER_FILES:-default} libvulkan=$loader nvrtc=$nvrtc"
torch=$(python3 -c 'import torch; print(torch.__version__)' 2>/dev/null || echo none)
echo "python $(python3 --version 2>&1 | tr ' ' '=') torch=$torch"

# JAX beside our process on one GPU: it allocates as it goes instead of taking 75% at start.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
jax_python=""
for candidate in "${XFACTOR_JAX_PYTHON:-}" python3 "$HOME/.cache/xfactor-dist/jax-env/bin/python"; do
    if [ -n "$candidate" ] && "$candidate" -c 'import jax' >/dev/null 2>&1; then
        jax_python="$candidate"
        break
    fi
done
if [ -n "$jax_python" ]; then
    echo "jax $("$jax_python" -c 'import jax; d = jax.devices()[0]; print("version=" + jax.__version__, "platform=" + d.platform, "device=\"" + d.device_kind + "\"")')"
    export XFACTOR_JAX_PYTHON="$jax_python"
else
    echo "jax none (no Python here imports jax)"
fi
cat "$here/not-built.txt"

# The libtorch road links PyTorch 2.9.0's shared libraries: this host's torch, or the
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

# The packed benchmark that runs `path`: cpu and wgpu from the default build; vulkan and cuda
# from the `gpu` build (no libtorch), else the `roads` build, which libtorch needs.
binary_for() { # path
    local binary
    case $1 in
    cpu | wgpu) binary="$here/bin/model_step-default"
        [ -x "$binary" ] || binary="$here/bin/model_step-gpu" ;;
    vulkan | cuda) binary="$here/bin/model_step-gpu"
        [ -x "$binary" ] || binary="$here/bin/model_step-roads" ;;
    libtorch) binary="$here/bin/model_step-roads" ;;
    esac
    [ -x "$binary" ] || return 1
    if [ "$binary" = "$here/bin/model_step-roads" ] && [ "$libtorch_ready" != yes ]; then
        echo "path=$1 status=cannot-run reason=\"the roads build loads libtorch: ${libtorch_why:-no Python here imports torch 2.9.0}\"" >&2
        return 1
    fi
    echo "$binary"
}

# The first line of the last failed run's stderr that says what went wrong.
why_failed() {
    # A graphics library's XDG_RUNTIME_DIR complaint on a headless host is noise, not the cause.
    grep -v 'XDG_RUNTIME_DIR' "$here/last-error.log" >"$here/last-error.kept" || true
    { grep -m1 -iE 'error|panicked|unavailable|out of memory' "$here/last-error.kept" || tail -1 "$here/last-error.kept"; } |
        tr -d '"' | cut -c1-300
}

# One measurement: our step (with the JAX peer when asked), as the bench's key=value line,
# kept for the summary. Fails when it cannot run, runs out of memory or out of time.
measure() { # backend model batch precision jax [compute]
    local bench limit args=(--backend "$1" --model "$2" --batch "$3" --precision "$4"
        --compute "${6:-f32}" --steps "$steps" --skip-paper --reference "$here/xfactor_reference.py")
    bench=$(binary_for "$1" 2>/dev/null) || return 1
    [ "$1" = cpu ] || args+=(--shards 1)
    [ "$5" = jax ] || args+=(--skip-jax)
    limit=$(left)
    [ "$limit" -gt "${LIMIT_S:-420}" ] && limit="${LIMIT_S:-420}"
    [ "$limit" -ge 20 ] || { echo "out of time" >"$here/last-error.log"; return 1; }
    echo "run backend=$1 model=$2 batch=$3 precision=$4 compute=${6:-f32} limit_s=$limit" >>"$steps_log"
    (cd "$work" && timeout "$limit" "$bench" "${args[@]}" 2>"$here/last-error.log") | grep '^backend=' | tee -a "$results"
    local status=${PIPESTATUS[0]}
    grep '^progress' "$here/last-error.log" >>"$steps_log"
    [ "$status" = 0 ]
}

# The JAX peer alone, for a model whose run of ours ended before its peer ran: the reference's
# own line, under `backend=jax`.
jax_alone() { # model batch
    local dims=(--height 64 --width 64 --patch-size 8 --features 256 --num-heads 8 --num-layers 4
        --pose-dim 64 --global-tokens 8)
    [ "$1" = paper ] && dims=(--height 256 --width 256 --patch-size 16 --features 1024
        --num-heads 16 --num-layers 8 --pose-dim 256 --global-tokens 32)
    [ -n "${XFACTOR_JAX_PYTHON:-}" ] && [ "$(left)" -ge 60 ] || return 0
    timeout 90 "$XFACTOR_JAX_PYTHON" "$here/xfactor_reference.py" bench --batch "$2" --steps "$steps" \
        "${dims[@]}" 2>>"$here/last-error.log" | grep '^jax_' | sed "s/^/backend=jax model=$1 batch=$2 /"
}

# Batch 8, then doubling while it fits, up to MAX_BATCH (each batch in its own process, so
# running out of memory ends only that run); prints the largest that fitted.
largest_batch() { # backend model
    local batch=16 fits=8
    while [ "$batch" -le "${MAX_BATCH:-64}" ] && measure "$1" "$2" "$batch" f32 no >/dev/null; do
        fits=$batch
        batch=$((batch * 2))
    done
    echo "backend=$1 model=$2 largest_batch=$fits tried_up_to=${MAX_BATCH:-64}"
}

paths=()
candidates=(cpu wgpu vulkan libtorch cuda)
[ "$gpu" = 1 ] && candidates=(cuda wgpu vulkan libtorch)
# ROADS="cuda wgpu" measures only those.
[ -n "${ROADS:-}" ] && read -r -a candidates <<<"$ROADS"
for path in "${candidates[@]}"; do
    binary_for "$path" >/dev/null && paths+=("$path")
done
if [ "$gpu" = 1 ]; then
    # Most telling first: the paper model's first run on a road tunes its kernels for minutes.
    for path in "${paths[@]}"; do
        if ! measure "$path" paper 8 f32 jax; then
            echo "backend=$path model=paper batch=8 status=failed reason=\"$(why_failed)\""
            jax_alone paper 8
        fi
        measure "$path" benchmark 8 f32 jax ||
            echo "backend=$path model=benchmark batch=8 status=failed reason=\"$(why_failed)\""
        # The bf16 speed mode (`model.compute: bf16`: products and attention in bf16 on tensor
        # cores, float32 weights and AdamW state).
        measure "$path" paper 8 f32 no bf16 >/dev/null ||
            echo "backend=$path model=paper batch=8 compute=bf16 status=failed reason=\"$(why_failed)\""
        largest_batch "$path" paper | tee -a "$results"
    done
else
    echo "model=paper status=skipped reason=\"no GPU: one step of the 305M model at 256x256 takes minutes on a CPU\""
    for path in "${paths[@]}"; do
        measure "$path" benchmark 8 f32 jax ||
            echo "backend=$path model=benchmark batch=8 status=failed reason=\"$(why_failed)\""
    done
fi

# The system, not only a step: a coordinator and two workers on the GPU for a few hundred steps.
job_device=cpu
[ "$gpu" = 1 ] && job_device=cuda
if [ -x "$here/bin/xfactor-local" ] && [ "$(left)" -gt 90 ]; then
    job_dir=$(mktemp -d)
    # From the working folder, whose cubecl.toml the workers read too.
    cd "$work" && timeout $(($(left) - 30)) "$here/bin/xfactor-local" --dir "$job_dir" --device "$job_device" \
        --workers 2 --stage1-steps "${JOB_STEPS:-300}" --stage2-steps 20 --no-evaluate \
        2>"$here/last-error.log" | grep '^outcome=' | sed 's/^/job /' | tee -a "$results" ||
        echo "job device=$job_device status=failed reason=\"$(why_failed)\""
fi

for path in "${paths[@]}"; do
    for half in bf16 f16; do
        measure "$path" benchmark 8 "$half" no >/dev/null ||
            echo "backend=$path model=benchmark batch=8 precision=$half status=failed reason=\"$(why_failed)\""
    done
done

echo "summary (seconds=$(( $(date +%s) - started )); ours beside JAX in the same run):"
python3 - "$results" <<'EOF'
import sys
rows = []
for line in open(sys.argv[1]):
    fields = dict(part.split("=", 1) for part in line.split() if "=" in part)
    if "step_s" in fields:
        rows.append([fields.get(k, "-") for k in (
            "backend", "model", "precision", "compute", "batch", "step_s", "pairs_per_s", "jax_step_s",
            "vs_jax", "memory_pool_reserved_bytes", "memory_driver_process_used_bytes",
            "jax_peak_bytes_in_use")])
    elif "largest_batch" in fields:
        print(f"  largest batch: {fields['backend']} {fields['model']} {fields['largest_batch']}"
              f" (tried up to {fields['tried_up_to']})")
    elif line.startswith("job "):
        print("  " + line.strip())
head = ["backend", "model", "prec", "compute", "batch", "step_s", "pairs/s", "jax_s", "ours/jax",
        "pool_bytes", "driver_bytes", "jax_peak_bytes"]
widths = [max(len(str(row[i])) for row in [head] + rows) for i in range(len(head))]
for row in [head] + rows:
    print("  " + "  ".join(str(cell).ljust(width) for cell, width in zip(row, widths)))
EOF

# What a later loan carries back to skip tuning and compiling (KERNEL_CACHE), and the logs.
echo "kernel_cache bytes=$(du -sb "$kernel_cache" | cut -f1) path=$kernel_cache"
if [ -n "${OUT:-}" ] && [ -d "$OUT" ]; then
    cp "$results" "$steps_log" "$OUT/"
    [ -e "$here/autotune.log" ] && xz -c "$here/autotune.log" >"$OUT/autotune.log.xz"
    tar -C "$kernel_cache" -cJf "$OUT/kernel-cache.tar.xz" .
fi
