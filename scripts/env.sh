# Sourced by the other scripts: one cargo profile (release) and one persistent target directory
# outside the checkout, so tests, runs, benchmarks and CI reruns share a single build.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/target}"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
# The words of a flags file (scripts/transfer-recipe.flags), `#` comments and blank lines
# dropped, one per line for `mapfile`.
recipe_flags() {
    sed -e 's/#.*//' "$1" | tr -s ' \t' '\n\n' | sed '/^$/d'
}
