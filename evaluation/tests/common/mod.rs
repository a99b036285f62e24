//! Paths and models shared by the integration tests.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use trainer_core::{XFactor, XFactorConfig, checkpoint};

/// `shared/fixtures/` beside the checkout, or `$XFACTOR_SHARED/fixtures` when set.
#[allow(dead_code)] // each test binary compiles this module; not all of them need the helper
pub fn shared_fixture(name: &str) -> PathBuf {
    let shared = std::env::var_os("XFACTOR_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared"));
    shared.join("fixtures").join(name)
}

/// Saves a freshly initialised model of `config` as `dir/model.safetensors` (+ `.json`).
#[allow(dead_code)] // each test binary compiles this module; not all of them need the helper
pub fn untrained_checkpoint(config: &XFactorConfig, seed: u64, dir: &Path) -> PathBuf {
    let model = XFactor::new(config, seed, &Device::flex()).unwrap();
    let path = dir.join("model.safetensors");
    checkpoint::save(&model, config, &path).unwrap();
    path
}
