//! Parity with the authors' implementation on both backends.

mod common;

use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor};
use trainer_core::XFactor;
use trainer_core::backend::{Backend, BackendDevices};
use trainer_core::flax::{FlaxTensors, PARAMS_PREFIX, load_flax};
use trainer_core::parity::{
    GRADIENT_TOLERANCE, OUTPUT_TOLERANCE, check_fixture, read_fixture_config,
};

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
    assert_parity(&fixture, &Backend::Cpu.device().unwrap(), "tiny/cpu");
}

#[test]
fn tiny_fixture_matches_on_wgpu() {
    let fixture = common::shared_fixture("xfactor-tiny.safetensors");
    assert_parity(&fixture, &Backend::Wgpu.device().unwrap(), "tiny/wgpu");
}

#[test]
fn other_sizes_match_on_both_backends() {
    for name in ["xfactor-deep.safetensors", "xfactor-manyviews.safetensors"] {
        let fixture = local_fixture(name);
        for backend in [Backend::Cpu, Backend::Wgpu] {
            assert_parity(
                &fixture,
                &backend.device().unwrap(),
                &format!("{name}/{}", backend.name()),
            );
        }
    }
}

#[test]
fn bfloat16_rounding_of_qkv_is_an_option_that_stays_close() {
    let fixture = common::shared_fixture("xfactor-tiny.safetensors");
    let mut config = read_fixture_config(&fixture)
        .unwrap()
        .model_config()
        .unwrap();
    let tensors = FlaxTensors::read(&fixture).unwrap();
    let device = Device::flex();
    let mut render = |round: bool| {
        config.round_qkv_bf16 = round;
        let model = load_flax(
            XFactor::new(&config, 0, &device).unwrap(),
            &tensors,
            PARAMS_PREFIX,
        )
        .unwrap();
        let pair: Tensor<5> = tensors.require("input.pair").unwrap().to_tensor(&device);
        model.render_pair(pair).try_into_vec_as::<f32>().unwrap()
    };
    let exact = render(false);
    let rounded = render(true);
    let difference = exact
        .iter()
        .zip(&rounded)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(difference > 0.0, "rounding had no effect");
    assert!(
        difference < 2e-2,
        "rounding moved the render by {difference}"
    );
}
