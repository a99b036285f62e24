#!/usr/bin/env bash
# Runs a cargo command with one of the off-by-default GPU features of trainer-core, worker and
# evaluation (docs/gpus.md), preparing what that feature needs first:
#   vulkan    cubecl-spirv 0.11.3 with scripts/patches/cubecl-spirv-0.11.3-implicit-shared-memory.patch
#             applied, in a copy under the cache, given to cargo as a [patch] for this command only
#             (Cargo.lock is put back afterwards, so the default build keeps crates.io's crate)
#   libtorch  PyTorch 2.9.0 from PyPI in a virtual environment (scripts/setup-libtorch.sh)
#   cuda      vendor/cubecl-llvm-standin given to cargo as a [patch] for cubecl-llvm 0.11.3 (whose
#             build downloads LLVM; cubecl-cuda compiles kernels with NVRTC at run time instead),
#             and CUDARC_CUDA_VERSION (default 13000), so cudarc's build asks for no nvcc
# A [patch] changes Cargo.lock for this command only: it is put back afterwards.
# Usage: scripts/build-feature.sh FEATURE[,FEATURE] CARGO-SUBCOMMAND [ARGS...]
#   scripts/build-feature.sh vulkan build --release -p worker --bin xfactor-worker
#   scripts/build-feature.sh vulkan,libtorch test --release -p trainer-core --test trainer
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
features=${1:?usage: scripts/build-feature.sh vulkan|libtorch|cuda[,...] CARGO-SUBCOMMAND [ARGS...]}
shift
subcommand=${1:?usage: scripts/build-feature.sh FEATURE CARGO-SUBCOMMAND [ARGS...]}
shift
extra=()
# Puts Cargo.lock back after a command that patched crates, so the default build keeps
# crates.io's crates.
lock_saved=""
keep_lock() {
    [ -n "$lock_saved" ] && return
    lock_saved="$CARGO_TARGET_DIR/Cargo.lock.before-patch"
    mkdir -p "$CARGO_TARGET_DIR"
    cp Cargo.lock "$lock_saved"
    trap 'mv "$lock_saved" Cargo.lock' EXIT
}
for feature in ${features//,/ }; do
    case $feature in
    vulkan)
        version=0.11.3
        patch_file="$PWD/scripts/patches/cubecl-spirv-$version-implicit-shared-memory.patch"
        patched="$(dirname "$CARGO_TARGET_DIR")/patched/cubecl-spirv-$version"
        stamp="$patched/.xfactor-patch-$(sha256sum "$patch_file" | cut -c1-16)"
        if [ ! -e "$stamp" ]; then
            command -v patch >/dev/null || {
                echo "build-feature: the vulkan fix needs \`patch\` (scripts/setup.sh installs it)" >&2
                exit 1
            }
            cargo fetch --locked >/dev/null
            source_dir=$(ls -d "${CARGO_HOME:-$HOME/.cargo}"/registry/src/*/cubecl-spirv-$version | head -1)
            rm -rf "$patched"
            mkdir -p "$(dirname "$patched")"
            cp -r "$source_dir" "$patched"
            patch --quiet -p1 -d "$patched" <"$patch_file"
            touch "$stamp"
        fi
        extra+=(--config "patch.crates-io.cubecl-spirv.path=\"$patched\"")
        keep_lock
        ;;
    libtorch)
        eval "$(scripts/setup-libtorch.sh)"
        ;;
    cuda)
        extra+=(--config "patch.crates-io.cubecl-llvm.path=\"$PWD/vendor/cubecl-llvm-standin\"")
        export CUDARC_CUDA_VERSION="${CUDARC_CUDA_VERSION:-13000}"
        keep_lock
        ;;
    *)
        echo "build-feature: unknown feature $feature (expected vulkan, libtorch or cuda)" >&2
        exit 2
        ;;
    esac
done
cargo "$subcommand" --features "$features" "${extra[@]}" "$@"
