//! Paths shared by the integration tests.

use std::path::PathBuf;

/// `shared/fixtures/` beside the checkout, or `$XFACTOR_SHARED/fixtures` when set.
pub fn shared_fixture(name: &str) -> PathBuf {
    let shared = std::env::var_os("XFACTOR_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared"));
    shared.join("fixtures").join(name)
}
