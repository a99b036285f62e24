//! Paths shared by the integration tests.

use std::path::PathBuf;

/// `shared/fixtures/` beside the checkout, or `$XFACTOR_SHARED/fixtures` when set.
#[allow(dead_code)] // each test binary compiles this module; not all of them need the helper
pub fn shared_fixture(name: &str) -> PathBuf {
    let shared = std::env::var_os("XFACTOR_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared"));
    shared.join("fixtures").join(name)
}

/// A `side x side` view of a smooth sinusoidal pattern shifted sideways by `offset` pixels: the
/// frames of a camera sliding past a textured wall, for tests that need real motion cheaply.
#[allow(dead_code)] // each test binary compiles this module; not all of them need the helper
pub fn sliding_frame(phases: &[f64], offset: f64, side: usize) -> data::Image {
    data::Image {
        height: side,
        width: side,
        pixels: (0..side * side * 3)
            .map(|i| {
                let (y, x, c) = ((i / 3) / side, (i / 3) % side, i % 3);
                let x = x as f64 + offset;
                (0.6 * (0.4 * x + phases[c]).sin() * (0.3 * y as f64 + phases[c + 3]).cos()) as f32
            })
            .collect(),
    }
}
