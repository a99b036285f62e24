#!/usr/bin/env bash
# Checks that every command builds from one set of artifacts: for each package selection the
# scripts and a developer use (`-p X` for every member, and run.sh's), every dependency must be
# resolved with the same features as in the whole workspace's build. Otherwise cargo compiles a
# second copy (burn's kernel crates: 11 minutes on 2 cores). The workspace-hack crate, written
# by `cargo hakari generate`, is what makes them equal; this fails when it is stale.
# Reads metadata only (`cargo tree`): a few seconds, no compilation.
set -euo pipefail
cd "$(dirname "$0")/.."
features() {
    cargo tree "$@" -f '{p} {f}' --prefix none 2>/dev/null | sed 's/ (\*)$//' | sort -u
}
workspace=$(mktemp)
trap 'rm -f "$workspace"' EXIT
features --workspace -e normal,build,dev >"$workspace"
failed=0
selections=("-p coordinator -p worker -p evaluation")
for member in settings data proto telemetry trainer-core worker coordinator evaluation; do
    selections+=("-p $member")
done
for selection in "${selections[@]}"; do
    # shellcheck disable=SC2086
    differing=$(comm -13 "$workspace" <(features $selection -e normal,build) || true)
    if [ -n "$differing" ]; then
        echo "one-build: \`cargo build $selection\` resolves other features than the workspace:"
        echo "$differing" | sed 's/^/  /'
        failed=1
    fi
done
if [ "$failed" = 1 ]; then
    echo "one-build: regenerate the workspace-hack: cargo hakari generate && cargo hakari manage-deps --yes"
    exit 1
fi
echo "one-build: ${#selections[@]} package selections resolve the workspace's features"
