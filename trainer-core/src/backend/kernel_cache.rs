//! Where cubecl keeps the kernels it compiles and the kernels autotune chose, across processes.
//!
//! On an H200 the CUDA road's first paper-model step spent minutes compiling autotune's
//! candidates with NVRTC, one after another, with the GPU idle (docs/gpus.md). cubecl keeps
//! autotune's choices on disk by default, in a folder that depends on the working folder (a
//! checkout's `target/`, else the user's cache), and keeps compiled kernels only when asked.
//! A worker restarted after a fault, or in a fresh container, then pays the minutes again.
//! [`keep_kernels_in`] names one folder for both, so a host or a mounted volume pays once.

use std::path::{Path, PathBuf};

use burn::cubecl::config::cache::CacheConfig;
use burn::cubecl::config::{CubeClRuntimeConfig, RuntimeConfig};

/// The files cubecl reads its settings from, looked for in the working folder and its parents
/// (`burn.toml` under its `[cubecl]` section).
const CONFIG_FILES: [&str; 4] = ["cubecl.toml", "CubeCL.toml", "burn.toml", "Burn.toml"];

/// What [`keep_kernels_in`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum KernelCache {
    /// This build's cubecl keeps nothing on disk: its `persistence` feature comes with the
    /// `cuda` feature (cubecl-cuda's defaults), the road whose compiles cost minutes.
    NotInThisBuild,
    /// Compiled kernels and autotune's choices are kept in this folder.
    Kept(PathBuf),
    /// A cubecl settings file governs this process and was left to say where (its path).
    SettingsFile(PathBuf),
    /// cubecl's settings were already read or set in this process; nothing changed.
    AlreadySettled,
}

/// Why the kernel cache's folder cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("the kernel cache folder {dir} cannot be made")]
pub struct KernelCacheError {
    dir: PathBuf,
    #[source]
    source: std::io::Error,
}

/// Keeps cubecl's compiled kernels and autotune's choices in `dir` (made if missing) for the
/// rest of the process, unless a cubecl settings file governs it (found from the working
/// folder up) or cubecl's settings were already read. Call it before the first GPU work;
/// cubecl's environment variables (`CUBECL_AUTOTUNE_LEVEL`, ...) still apply.
pub fn keep_kernels_in(dir: &Path) -> Result<KernelCache, KernelCacheError> {
    if !cfg!(feature = "cuda") {
        return Ok(KernelCache::NotInThisBuild);
    }
    if let Some(file) = std::env::current_dir()
        .ok()
        .and_then(|folder| settings_file_above(&folder))
    {
        return Ok(KernelCache::SettingsFile(file));
    }
    std::fs::create_dir_all(dir).map_err(|source| KernelCacheError {
        dir: dir.to_path_buf(),
        source,
    })?;
    let mut config = CubeClRuntimeConfig::default().override_from_env();
    #[cfg(feature = "cuda")]
    {
        config.compilation.cache = true;
    }
    config.environment.path = CacheConfig::Directory(dir.to_path_buf());
    Ok(if CubeClRuntimeConfig::try_set(config) {
        KernelCache::Kept(dir.to_path_buf())
    } else {
        KernelCache::AlreadySettled
    })
}

/// The first cubecl settings file in `folder` or a folder above it, as cubecl looks for one.
fn settings_file_above(folder: &Path) -> Option<PathBuf> {
    folder.ancestors().find_map(|dir| {
        CONFIG_FILES
            .iter()
            .map(|name| dir.join(name))
            .find(|path| path.is_file())
    })
}

/// The folder a process keeps kernels in by default: `kernels` in the project's folder of the
/// user's cache ([`settings::cache::project_cache`]).
pub fn default_kernel_cache() -> PathBuf {
    settings::cache::project_cache().join("kernels")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_settings_file_is_found_in_the_folder_or_above() {
        let root = tempfile::tempdir().expect("a temporary folder");
        let nested = root.path().join("a/b");
        std::fs::create_dir_all(&nested).expect("nested folders");
        assert_eq!(settings_file_above(&nested), None);
        std::fs::write(root.path().join("burn.toml"), "").expect("a settings file");
        assert_eq!(
            settings_file_above(&nested),
            Some(root.path().join("burn.toml"))
        );
        std::fs::write(nested.join("cubecl.toml"), "").expect("a nearer settings file");
        assert_eq!(
            settings_file_above(&nested),
            Some(nested.join("cubecl.toml"))
        );
    }

    #[test]
    fn the_default_folder_is_in_the_user_cache() {
        assert!(default_kernel_cache().ends_with("xfactor-dist/kernels"));
    }
}
