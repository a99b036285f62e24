#!/usr/bin/env bash
# Opt-in set-up for the `libtorch` cargo feature (burn-tch): a virtual environment with
# PyTorch 2.9.0 from PyPI, the one version tch/torch-sys 0.22 accept, under
# ~/.cache/xfactor-dist/torch-env (about 4 GB with its CUDA libraries; the CPU device needs no
# GPU). Prints the variables a libtorch build and its binaries need; eval them:
#     eval "$(scripts/setup-libtorch.sh)"
#     cargo build --release -p worker --features libtorch
set -euo pipefail
torch_version="2.9.0"
env_dir="${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/torch-env"
installed() {
    "$env_dir/bin/python" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '$torch_version')" 2>/dev/null
}
if ! installed; then
    echo "installing torch==$torch_version into $env_dir" >&2
    python3 -m venv "$env_dir"
    "$env_dir/bin/pip" install --quiet "torch==$torch_version" "numpy<3" >&2
fi
torch_lib=$("$env_dir/bin/python" -c "import os, torch; print(os.path.join(os.path.dirname(torch.__file__), 'lib'))")
# torch-sys asks the active virtual environment's `python` where libtorch is
# (LIBTORCH_USE_PYTORCH); the binaries find its shared libraries through LD_LIBRARY_PATH.
echo "export LIBTORCH_USE_PYTORCH=1"
echo "export VIRTUAL_ENV='$env_dir'"
echo "export PATH='$env_dir/bin':\"\$PATH\""
echo "export LD_LIBRARY_PATH='$torch_lib'\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
