#!/usr/bin/env bash
# Opt-in set-up for the JAX peer of the step benchmark (trainer-core/benches/model_step.rs):
# a virtual environment with CPU JAX, pinned, under ~/.cache/xfactor-dist/jax-env. On a GPU
# host the bench can use that host's own JAX instead (XFACTOR_JAX_PYTHON=python3).
set -euo pipefail
env_dir="${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/jax-env"
if ! "$env_dir/bin/python" -c "import jax, safetensors" 2>/dev/null; then
    python3 -m venv "$env_dir"
    "$env_dir/bin/pip" install --quiet "jax==0.10.2" "numpy<3" "safetensors==0.8.0"
fi
"$env_dir/bin/python" -c "import jax; print('jax', jax.__version__, 'in', '$env_dir')"
