# Sourced by the other scripts: one cargo profile (release) and one persistent target directory
# outside the checkout, so tests, runs, benchmarks and CI reruns share a single build.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/target}"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
