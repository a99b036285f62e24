//! LPIPS against the authors' JAX implementation (random weights of the pretrained layout).

mod common;

use burn::tensor::{Device, Tensor};
use trainer_core::backend::{Backend, BackendDevices};
use trainer_core::flax::{FlaxTensors, HostTensor};
use trainer_core::lpips::Lpips;

fn check(device: &Device, label: &str) {
    let tensors =
        FlaxTensors::read(&common::shared_fixture("lpips-vgg16-random.safetensors")).unwrap();
    let device = device.clone().autodiff();
    let lpips = Lpips::from_tensors(&tensors, &device).unwrap();
    let x: Tensor<4> = tensors.require("input.x").unwrap().to_tensor(&device);
    let x = x.require_grad();
    let t: Tensor<4> = tensors.require("input.t").unwrap().to_tensor(&device);
    let distance = lpips.distance(x.clone(), t);
    let ours = HostTensor::from_tensor(distance.clone());
    let reference = tensors.require("output.distance").unwrap();
    let grads = distance.mean().backward();
    let grad = HostTensor::from_tensor(x.grad(&grads).expect("gradient wrt x"));
    let reference_grad = tensors.require("output.grad_x").unwrap();

    let distance_error = ours
        .values
        .iter()
        .zip(&reference.values)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs() / b.abs()));
    let grad_error = grad
        .values
        .iter()
        .zip(&reference_grad.values)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()))
        / reference_grad.max_abs();
    println!(
        "{label}: distances={:?} reference={:?} distance_rel_err={distance_error:.3e} grad_rel_err={grad_error:.3e}",
        ours.values, reference.values
    );
    assert_eq!(ours.values.len(), reference.values.len());
    assert!(
        distance_error <= 1e-4,
        "{label}: distance off by {distance_error:e}"
    );
    assert!(
        grad_error <= 1e-3,
        "{label}: gradient off by {grad_error:e}"
    );
}

#[test]
fn lpips_matches_the_authors_on_cpu() {
    check(&Backend::Cpu.device().unwrap(), "lpips/cpu");
}

#[test]
fn lpips_matches_the_authors_on_wgpu() {
    check(&Backend::Wgpu.device().unwrap(), "lpips/wgpu");
}

#[test]
fn a_missing_lpips_tensor_is_named() {
    let tensors = FlaxTensors::default();
    let message = Lpips::from_tensors(&tensors, &Device::flex())
        .unwrap_err()
        .to_string();
    assert!(message.contains("vgg.conv1_1.weight"), "{message}");
}
