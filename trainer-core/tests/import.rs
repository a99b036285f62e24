//! Importing the release's clu checkpoint (`shared/fixtures/clu-checkpoint/`): the weights,
//! the optax state (resumed for one update) and the LPIPS weights it carries.

mod common;

use std::path::Path;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor};
use settings::commit::{CommitManifest, MANIFEST_NAME};
use settings::optim::{AdamWConfig, Schedule};
use trainer_core::flax::{FlaxTensors, HostTensor, flax_name, named_parameters};
use trainer_core::import::{LPIPS_FILE, MODEL_FILE, read_clu};
use trainer_core::lpips::Lpips;
use trainer_core::optim::AdamW;
use trainer_core::{XFactor, checkpoint};

/// The fixture's model is 32x32 (the JSON of `xfactor-tiny`); no weight records the size.
const IMAGE_SIZE: usize = 32;

fn expected() -> FlaxTensors {
    FlaxTensors::read(&common::shared_fixture(
        "clu-checkpoint/expected.safetensors",
    ))
    .unwrap()
}

fn assert_same(label: &str, ours: &HostTensor, theirs: &HostTensor) {
    assert_eq!(ours.shape, theirs.shape, "{label}");
    assert!(
        ours.values == theirs.values,
        "{label}: values differ (max {:e})",
        ours.values
            .iter()
            .zip(&theirs.values)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()))
    );
}

#[test]
fn import_recovers_every_tensor_of_the_latest_checkpoint() {
    let dir = common::shared_fixture("clu-checkpoint");
    let imported = read_clu(&dir, IMAGE_SIZE).unwrap();
    assert_eq!(
        imported.source.file_name().unwrap(),
        "ckpt-3.flax",
        "the `checkpoint` file names ckpt-3, not the other one"
    );
    let expected = expected();
    let out = tempfile::tempdir().unwrap();
    imported.write(out.path(), &Device::flex()).unwrap();

    // Weights, through our own checkpoint file.
    let (model, config) = checkpoint::load(&out.path().join(MODEL_FILE), &Device::flex()).unwrap();
    assert_eq!(config.image_size, IMAGE_SIZE);
    let ours = named_parameters(&model);
    let mut compared = 0;
    for name in expected.names_with_prefix("params.") {
        let key = name.trim_start_matches("params.");
        assert_same(name, &ours[key], expected.require(name).unwrap());
        compared += 1;
    }
    assert_eq!(compared, ours.len(), "every parameter of the model");

    // Moments and count, through the optimiser file.
    let moments = FlaxTensors::read(&out.path().join("optimizer.safetensors")).unwrap();
    for (theirs, mine) in [("opt.mu.", "first."), ("opt.nu.", "second.")] {
        for name in expected.names_with_prefix(theirs) {
            let ours = moments.require(&name.replacen(theirs, mine, 1)).unwrap();
            assert_same(name, ours, expected.require(name).unwrap());
        }
    }
    let count = expected.require("opt.count").unwrap().values[0] as u64;
    assert_eq!(imported.updates, count);
    println!(
        "imported {} from {}: {compared} parameters, {} moments, updates={} step={}",
        config.width,
        imported.source.display(),
        moments.names_with_prefix("").count(),
        imported.updates,
        imported.step
    );

    // The other checkpoint in the directory is an older state without the LPIPS weights:
    // importing it instead would lose them.
    let older = trainer_core::import::flax_state::FlaxState::parse(
        &std::fs::read(dir.join("checkpoints-0/ckpt-2.flax")).unwrap(),
    )
    .unwrap();
    assert_eq!(older.tensors_under("lpips_params.").count(), 0);
    assert_eq!(
        imported.lpips.len(),
        31,
        "13 convolutions x 2 + 5 linear heads"
    );
}

#[test]
fn imported_lpips_weights_reproduce_the_lpips_fixture() {
    let imported = read_clu(&common::shared_fixture("clu-checkpoint"), IMAGE_SIZE).unwrap();
    let out = tempfile::tempdir().unwrap();
    imported.write(out.path(), &Device::flex()).unwrap();
    let reference =
        FlaxTensors::read(&common::shared_fixture("lpips-vgg16-random.safetensors")).unwrap();
    let written = FlaxTensors::read(&out.path().join(LPIPS_FILE)).unwrap();
    let mapping: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(common::shared_fixture("clu-checkpoint/expected.json")).unwrap(),
    )
    .unwrap();
    for target in mapping["lpips_params"].as_object().unwrap().values() {
        let name = target.as_str().unwrap();
        assert_same(
            name,
            written.require(name).unwrap(),
            reference.require(name).unwrap(),
        );
    }
    let device = Device::flex();
    let lpips = Lpips::from_file(&out.path().join(LPIPS_FILE), &device).unwrap();
    let x: Tensor<4> = reference.require("input.x").unwrap().to_tensor(&device);
    let t: Tensor<4> = reference.require("input.t").unwrap().to_tensor(&device);
    let ours = HostTensor::from_tensor(lpips.distance(x, t));
    let theirs = reference.require("output.distance").unwrap();
    let worst = ours
        .values
        .iter()
        .zip(&theirs.values)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs() / b.abs()));
    println!(
        "imported LPIPS: distances={:?} reference={:?} rel_err={worst:.2e}",
        ours.values, theirs.values
    );
    assert!(worst <= 1e-4, "distance off by {worst:e}");
}

/// Gradients registered under the model's parameter ids from tensors named by flax name.
fn gradients_from(model: &XFactor, tensors: &FlaxTensors, prefix: &str) -> GradientsParams {
    struct Register<'a> {
        tensors: &'a FlaxTensors,
        prefix: &'a str,
        path: Vec<String>,
        grads: GradientsParams,
    }
    impl ModuleVisitor for Register<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let name = format!("{}{}", self.prefix, flax_name(&self.path));
            let grad = self.tensors.require(&name).unwrap();
            let device = param.val().device();
            self.grads
                .register::<D>(param.id, grad.to_tensor::<D>(&device));
        }
    }
    let mut register = Register {
        tensors,
        prefix,
        path: Vec::new(),
        grads: GradientsParams::new(),
    };
    model.visit(&mut register);
    register.grads
}

#[test]
fn one_update_from_the_imported_optimiser_state_matches_optax() {
    let imported = read_clu(&common::shared_fixture("clu-checkpoint"), IMAGE_SIZE).unwrap();
    let out = tempfile::tempdir().unwrap();
    let device = Device::flex();
    imported.write(out.path(), &device).unwrap();
    // A committed checkpoint: a job's `init_weights:` downloads and verifies it.
    let manifest: CommitManifest =
        serde_json::from_slice(&std::fs::read(out.path().join(MANIFEST_NAME)).unwrap()).unwrap();
    let mut listed: Vec<&str> = manifest.files.iter().map(|f| f.name.as_str()).collect();
    listed.sort_unstable();
    assert_eq!(
        listed,
        [
            "lpips.safetensors",
            "model.json",
            MODEL_FILE,
            "optimizer.safetensors",
            "state.json"
        ]
    );
    for file in &manifest.files {
        let bytes = std::fs::read(out.path().join(&file.name)).unwrap();
        assert_eq!(Some(crc32fast::hash(&bytes)), file.crc32, "{}", file.name);
    }
    let (model, _) = checkpoint::load(&out.path().join(MODEL_FILE), &device).unwrap();
    let state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("state.json")).unwrap())
            .unwrap();
    let (step, updates) = (
        state["step"].as_u64().unwrap(),
        state["updates"].as_u64().unwrap(),
    );
    let mut optimizer = AdamW::new(AdamWConfig::default());
    let moments = FlaxTensors::read(&out.path().join("optimizer.safetensors")).unwrap();
    optimizer.import_moments(&model, &moments, updates).unwrap();
    let expected = expected();
    let before = named_parameters(&model);
    let grads = gradients_from(&model, &expected, "step3.grad.");
    let lr = Schedule::default().learning_rate(step);
    let (model, report) = optimizer.step(model, &grads, lr);
    assert!(report.applied);
    let after = named_parameters(&model);
    // Relative to each tensor's largest value: on the small biases the update is a tenth of
    // the weight, so a skipped, mis-scaled or differently-rounded update (a learning rate off
    // by 4e-5, say) fails here, while float32's rounding of `p + u` stays far below.
    let (mut worst, mut worst_name, mut moved) = (0.0f32, String::new(), 0);
    for (name, ours) in &after {
        let theirs = expected.require(&format!("step3.params.{name}")).unwrap();
        let error = ours
            .values
            .iter()
            .zip(&theirs.values)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()))
            / theirs.max_abs().max(f32::MIN_POSITIVE);
        if error > worst {
            (worst, worst_name) = (error, name.clone());
        }
        if theirs.values != before[name].values {
            moved += 1;
        }
    }
    println!(
        "resumed update at step {step} (updates {updates}, lr {lr:e}): worst_rel_err={worst:.2e} ({worst_name}) over {} tensors, {moved} moved",
        after.len()
    );
    assert_eq!(moved, after.len(), "optax moved every tensor");
    assert!(
        worst <= 1e-6,
        "{worst_name}: off by {worst:e} of its largest value"
    );
}

#[test]
fn a_missing_entry_is_named() {
    let source = common::shared_fixture("clu-checkpoint/checkpoints-0");
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(source.join("ckpt-2.flax")).unwrap();
    // Rename every key `global_embed` (same length, so the msgpack stays valid).
    let needle = b"global_embed";
    let mut patched = bytes.clone();
    let mut renamed = 0;
    while let Some(at) = patched.windows(needle.len()).position(|w| w == needle) {
        patched[at..at + needle.len()].copy_from_slice(b"global_embex");
        renamed += 1;
    }
    assert!(renamed > 0, "the state names global_embed");
    std::fs::write(dir.path().join("ckpt-2.flax"), patched).unwrap();
    std::fs::write(
        dir.path().join("checkpoint"),
        "model_checkpoint_path: \"ckpt-2\"\n",
    )
    .unwrap();
    let error = read_clu(dir.path(), IMAGE_SIZE).unwrap_err();
    assert!(
        error.to_string().contains("params.PoseEnc.global_embed"),
        "{error}"
    );
    assert!(read_clu(Path::new("/nonexistent"), IMAGE_SIZE).is_err());
}
