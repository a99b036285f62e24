//! Parity with the authors' implementation on both backends.

mod common;

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use trainer_core::backend::BackendChoice;
use trainer_core::parity::{GRADIENT_TOLERANCE, OUTPUT_TOLERANCE, check_fixture};

/// Fixtures committed with this crate (made by `tools/reference`).
fn local_fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn assert_parity(fixture: &Path, device: &Device, label: &str) {
    let report = check_fixture(fixture, device)
        .unwrap_or_else(|e| panic!("{label}: cannot check {}: {e}", fixture.display()));
    let (worst_output, output_error) = report.worst_output();
    let (worst_gradient, gradient_error) = report.worst_gradient();
    println!(
        "{label}: outputs_max_abs_err={output_error:.3e} ({worst_output}) grads_max_rel_err={gradient_error:.3e} ({worst_gradient}) gradients={}",
        report.gradient_errors.len()
    );
    for (name, error) in &report.output_errors {
        assert!(
            *error <= OUTPUT_TOLERANCE,
            "{label}: output {name} off by {error:e}"
        );
    }
    for (name, error) in &report.gradient_errors {
        assert!(
            *error <= GRADIENT_TOLERANCE,
            "{label}: gradient {name} off by {error:e} (relative)"
        );
    }
    assert_eq!(
        report.reference_pose_max_abs, 0.0,
        "{label}: reference pose"
    );
    assert!(
        !report.gradient_errors.is_empty(),
        "{label}: no gradients compared"
    );
    assert!(report.passed());
}

#[test]
fn tiny_fixture_matches_on_cpu() {
    let fixture = common::shared_fixture("xfactor-tiny.safetensors");
    assert_parity(&fixture, &BackendChoice::Cpu.device(), "tiny/cpu");
}

#[test]
fn tiny_fixture_matches_on_wgpu() {
    let fixture = common::shared_fixture("xfactor-tiny.safetensors");
    assert_parity(&fixture, &BackendChoice::Wgpu.device(), "tiny/wgpu");
}

#[test]
fn other_sizes_match_on_cpu() {
    for name in ["xfactor-deep.safetensors", "xfactor-manyviews.safetensors"] {
        let fixture = local_fixture(name);
        assert_parity(&fixture, &BackendChoice::Cpu.device(), name);
    }
}
