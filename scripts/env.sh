# Sourced by the other scripts: one cargo profile (release) and one persistent target directory
# outside the checkout, so tests, runs, benchmarks and CI reruns share a single build.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/xfactor-dist/target}"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
# Reads the words of a flags file (scripts/transfer-recipe.flags) into the array named by $1,
# `#` comments and blank lines dropped; fails, naming the file, when it is unreadable or holds
# no flag (a process substitution alone would hide that and run with xfactor-local's defaults).
read_flags_file() {
    local -n into="$1"
    [ -r "$2" ] || { echo "$2: cannot read the recipe's flags" >&2; return 1; }
    mapfile -t into < <(sed -e 's/#.*//' "$2" | tr -s ' \t' '\n\n' | sed '/^$/d')
    [ "${#into[@]}" -gt 0 ] || { echo "$2: holds no flag" >&2; return 1; }
}
