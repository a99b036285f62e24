//! The project's folder in the user's cache, where `scripts/setup.sh` puts its Python
//! environments and processes keep what outlives them (compiled kernels): one rule for every
//! crate, so a tool and the script that installed it agree on the path.

use std::path::{Path, PathBuf};

/// `xfactor-dist` in the user's cache: `$XDG_CACHE_HOME` where set and not empty, else
/// `~/.cache`, else the system's temporary folder.
pub fn project_cache() -> PathBuf {
    let user_cache = std::env::var_os("XDG_CACHE_HOME")
        .filter(|value| !value.is_empty())
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|home| Path::new(&home).join(".cache")))
        .unwrap_or_else(std::env::temp_dir);
    user_cache.join("xfactor-dist")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_project_folder_is_named_in_the_user_cache() {
        assert!(project_cache().ends_with("xfactor-dist"));
        assert!(project_cache().is_absolute());
    }
}
