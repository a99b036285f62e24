//! cubecl's kernel cache named by `keep_kernels_in`: a test binary of its own, since cubecl's
//! settings are set once per process.

use trainer_core::backend::{KernelCache, keep_kernels_in};

/// Without the `cuda` feature cubecl keeps nothing on disk, and the call says so.
#[cfg(not(feature = "cuda"))]
#[test]
fn a_build_without_cuda_keeps_nothing() {
    let scratch = tempfile::tempdir().expect("a temporary folder");
    let kept = keep_kernels_in(&scratch.path().join("kernels")).expect("nothing to make");
    assert_eq!(kept, KernelCache::NotInThisBuild);
    assert!(!scratch.path().join("kernels").exists());
}

/// Builds with the `cuda` feature, whose cubecl keeps its cache on disk.
#[cfg(feature = "cuda")]
mod kept {
    use std::path::Path;
    use std::time::{Duration, Instant};

    use burn::cubecl::config::{CubeClRuntimeConfig, RuntimeConfig};
    use burn::tensor::{Distribution, Tensor};
    use trainer_core::backend::{Backend, BackendDevices};

    use super::*;

    /// Whether `dir` holds a non-empty cubecl database, waiting up to `patience` for it.
    fn holds_a_database(dir: &Path, patience: Duration) -> bool {
        let started = Instant::now();
        loop {
            let found = std::fs::read_dir(dir)
                .into_iter()
                .flatten()
                .flatten()
                .any(|entry| {
                    entry.file_name().to_string_lossy().ends_with(".db")
                        && entry.metadata().is_ok_and(|meta| meta.len() > 0)
                });
            if found || started.elapsed() > patience {
                return found;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Autotune's choice for a matmul on the Cube backend (lavapipe where there is no GPU)
    /// lands in the folder named, with compiled kernels kept; a second call changes nothing.
    #[test]
    fn autotune_choices_land_in_the_folder_named() {
        let scratch = tempfile::tempdir().expect("a temporary folder");
        let folder = scratch.path().join("kernels");
        let kept = keep_kernels_in(&folder).expect("the folder can be made");
        assert_eq!(kept, KernelCache::Kept(folder.clone()));
        assert!(folder.is_dir());
        assert_eq!(
            keep_kernels_in(&scratch.path().join("elsewhere")).expect("no folder needed"),
            KernelCache::AlreadySettled
        );
        assert!(CubeClRuntimeConfig::get().compilation.cache);

        let device = Backend::Wgpu
            .device()
            .expect("a wgpu adapter (lavapipe where there is no GPU)");
        let x = Tensor::<2>::random([256, 256], Distribution::Default, &device);
        let total: f32 = x.clone().matmul(x).sum().into_scalar();
        assert!(total.is_finite());
        assert!(
            holds_a_database(&folder, Duration::from_secs(10)),
            "no cubecl database in {}",
            folder.display()
        );
    }

    /// A folder that cannot be made is an error naming it.
    #[test]
    fn a_folder_that_cannot_be_made_is_named() {
        let scratch = tempfile::tempdir().expect("a temporary folder");
        let file = scratch.path().join("a-file");
        std::fs::write(&file, "").expect("a file");
        let error = keep_kernels_in(&file.join("kernels")).expect_err("a file is in the way");
        assert!(error.to_string().contains("a-file/kernels"), "{error}");
    }
}
