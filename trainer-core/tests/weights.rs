//! Importing flax-named weights, the project's checkpoint format and the check command.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use burn::tensor::{Device, Tensor, TensorData};
use data::rng::Stream;
use safetensors::SafeTensors;
use safetensors::tensor::TensorView;
use trainer_core::flax::{FlaxTensors, PARAMS_PREFIX, load_flax};
use trainer_core::{XFactor, XFactorConfig, checkpoint};

/// Two Render layers, unlike PoseEnc's one, so mismatched layer counts are exercised.
fn tiny_config() -> XFactorConfig {
    XFactorConfig {
        render_layers: 2,
        ..XFactorConfig::tiny(16)
    }
}

/// Copies the tiny fixture (and its JSON) into `dir`, dropping `remove` and giving `reshape`
/// a transposed shape.
fn corrupted_fixture(dir: &Path, remove: &str, reshape: &str) -> PathBuf {
    let source = common::shared_fixture("xfactor-tiny.safetensors");
    let bytes = std::fs::read(&source).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let mut views = Vec::new();
    for (name, view) in file.tensors() {
        if name == remove {
            continue;
        }
        let mut shape = view.shape().to_vec();
        if name == reshape {
            shape.reverse();
        }
        views.push((
            name,
            TensorView::new(view.dtype(), shape, view.data()).unwrap(),
        ));
    }
    let target = dir.join("corrupt.safetensors");
    std::fs::write(&target, safetensors::serialize(views, None).unwrap()).unwrap();
    std::fs::copy(source.with_extension("json"), target.with_extension("json")).unwrap();
    target
}

#[test]
fn wrong_and_missing_tensors_are_named_with_both_shapes() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = corrupted_fixture(
        dir.path(),
        "params.Render.MLP3_0.Dense_2.bias",
        "params.PoseEnc.Dense_0.kernel",
    );
    let tensors = FlaxTensors::read(&fixture).unwrap();
    let config = XFactorConfig {
        image_size: 32,
        patch_size: 4,
        width: 64,
        num_heads: 4,
        pose_layers: 2,
        render_layers: 2,
        pose_dim: 16,
        global_tokens: 8,
        round_qkv_bf16: false,
        pose_conditioning: settings::model::PoseConditioning::Latent,
        precision: settings::model::Precision::F32,
        compute: settings::model::Precision::F32,
    };
    let model = XFactor::new(&config, 0, &Device::flex()).unwrap();
    let message = load_flax(model, &tensors, PARAMS_PREFIX)
        .unwrap_err()
        .to_string();
    assert!(
        message.contains("`params.Render.MLP3_0.Dense_2.bias` is missing")
            && message.contains("[48]"),
        "{message}"
    );
    assert!(
        message.contains("`params.PoseEnc.Dense_0.kernel` has shape [64, 48]")
            && message.contains("expects [48, 64]"),
        "{message}"
    );
}

#[test]
fn weights_of_another_architecture_are_refused() {
    let tensors = FlaxTensors::read(&common::shared_fixture("xfactor-tiny.safetensors")).unwrap();
    let mut config = tiny_config();
    config.pose_layers = 3;
    let model = XFactor::new(&config, 0, &Device::flex()).unwrap();
    let message = load_flax(model, &tensors, PARAMS_PREFIX)
        .unwrap_err()
        .to_string();
    assert!(message.contains("params.PoseEnc.layers_2."), "{message}");
}

fn render_once(model: &XFactor, device: &Device) -> Vec<f32> {
    let config = tiny_config();
    let side = config.image_size;
    let mut stream = Stream::new(&[99]);
    let values: Vec<f32> = (0..2 * side * side * 3)
        .map(|_| stream.uniform_in(-1.0, 1.0) as f32)
        .collect();
    let pair = Tensor::<5>::from_data(TensorData::new(values, [1, 2, side, side, 3]), device);
    model.render_pair(pair).try_into_vec_as::<f32>().unwrap()
}

#[test]
fn checkpoint_round_trip_is_exact_and_self_describing() {
    let device = Device::flex();
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("model.safetensors");
    let config = tiny_config();
    let model = XFactor::new(&config, 7, &device).unwrap();
    checkpoint::save(&model, &config, &weights).unwrap();
    let (loaded, loaded_config) = checkpoint::load(&weights, &device).unwrap();
    assert_eq!(loaded_config, config);
    assert_eq!(render_once(&model, &device), render_once(&loaded, &device));
}

#[test]
fn checkpoint_with_a_mismatched_config_names_the_tensors() {
    let device = Device::flex();
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("model.safetensors");
    let config = tiny_config();
    checkpoint::save(
        &XFactor::new(&config, 1, &device).unwrap(),
        &config,
        &weights,
    )
    .unwrap();
    let mut wider = config.clone();
    wider.pose_dim = 12;
    std::fs::write(
        checkpoint::config_path(&weights),
        serde_json::to_string(&wider).unwrap(),
    )
    .unwrap();
    let message = checkpoint::load(&weights, &device).unwrap_err().to_string();
    assert!(message.contains("pose_head"), "{message}");
}

#[test]
fn same_seed_same_model() {
    let device = Device::flex();
    let a = XFactor::new(&tiny_config(), 3, &device).unwrap();
    let b = XFactor::new(&tiny_config(), 3, &device).unwrap();
    let c = XFactor::new(&tiny_config(), 4, &device).unwrap();
    let kernel = |m: &XFactor| {
        m.render
            .pixel_head
            .dense_0
            .kernel
            .val()
            .try_into_vec_as::<f32>()
            .unwrap()
    };
    assert_eq!(kernel(&a), kernel(&b));
    assert_ne!(kernel(&a), kernel(&c));
}

#[test]
fn check_command_passes_on_the_tiny_fixture_and_names_broken_tensors() {
    let binary = env!("CARGO_BIN_EXE_xfactor-check");
    let ok = Command::new(binary)
        .arg(common::shared_fixture("xfactor-tiny.safetensors"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&ok.stdout);
    assert!(
        ok.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert!(stdout.contains("result=pass"), "{stdout}");
    assert!(stdout.contains("output render_mv"), "{stdout}");

    let dir = tempfile::tempdir().unwrap();
    let fixture = corrupted_fixture(
        dir.path(),
        "params.PoseEnc.global_embed",
        "params.Render.layers_1.RMSNorm_2.alpha",
    );
    let broken = Command::new(binary).arg(&fixture).output().unwrap();
    let stderr = String::from_utf8_lossy(&broken.stderr);
    assert_eq!(broken.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("params.PoseEnc.global_embed"), "{stderr}");
    assert!(
        stderr.contains("params.Render.layers_1.RMSNorm_2.alpha"),
        "{stderr}"
    );
}
