//! The single-process trainer: exact resume, accumulation equivalence, refusal without LPIPS.

mod common;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor};
use data::Image;
use data::rng::Stream;
use data::{BatchSource, SampleError, Samples};
use settings::objective::{Stage1Config, Stage2Config};
use settings::optim::{AdamWConfig, Schedule};
use settings::train::{StageObjective, TrainConfig};
use trainer_core::trainer::{TrainError, Trainer};
use trainer_core::{XFactor, XFactorConfig};

const SIDE: usize = 16;

fn frame(phases: &[f64], offset: f64) -> Image {
    common::sliding_frame(phases, offset, SIDE)
}

/// Sliding-camera samples that depend only on `(step, sample)`.
struct SlidingCamera {
    views: Option<usize>,
}

impl BatchSource for SlidingCamera {
    fn samples(&self, step: u64, first: u64, count: usize) -> Result<Samples, SampleError> {
        let scene = |sample: u64| {
            let mut stream = Stream::new(&[step, sample]);
            let phases: Vec<f64> = (0..6).map(|_| stream.uniform_in(0.0, 6.0)).collect();
            let speed = stream.uniform_in(-0.6, 0.6);
            (phases, speed)
        };
        let samples = first..first + count as u64;
        Ok(match self.views {
            None => Samples::Pairs(
                samples
                    .map(|s| {
                        let (phases, speed) = scene(s);
                        (frame(&phases, 0.0), frame(&phases, 4.0 * speed))
                    })
                    .collect(),
            ),
            Some(views) => Samples::Views(
                samples
                    .map(|s| {
                        let (phases, speed) = scene(s);
                        (0..views as u64)
                            .map(|f| (f * 2, frame(&phases, f as f64 * speed)))
                            .collect()
                    })
                    .collect(),
            ),
        })
    }
}

fn model_config() -> XFactorConfig {
    XFactorConfig::tiny(SIDE)
}

fn train_config(objective: StageObjective, global: usize, micro: usize) -> TrainConfig {
    TrainConfig {
        seed: 9,
        objective,
        global_batch: global,
        micro_batch: micro,
        shards: 2,
        schedule: Schedule {
            initial_lr: 1e-4,
            peak_lr: 2e-3,
            final_lr: 1e-3,
            warmup_steps: 2,
            total_steps: 20,
        },
        optimizer: AdamWConfig::default(),
    }
}

fn stage1() -> StageObjective {
    StageObjective::Stage1(Stage1Config {
        lpips_weight: 0.0,
        ..Stage1Config::default()
    })
}

fn parameters(model: &XFactor) -> Vec<Vec<f32>> {
    parameters_of(model)
}

fn parameters_of<M: Module>(model: &M) -> Vec<Vec<f32>> {
    struct Collect(Vec<Vec<f32>>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.push(param.val().try_into_vec_as::<f32>().unwrap());
        }
    }
    let mut collect = Collect(Vec::new());
    model.visit(&mut collect);
    collect.0
}

fn fresh_trainer(config: TrainConfig, device: &Device) -> Trainer {
    let model = XFactor::new(&model_config(), 1, device).unwrap();
    Trainer::new(config, model_config(), model, None, device).unwrap()
}

#[test]
fn resume_continues_bitwise_exactly() {
    let device = Device::flex().autodiff();
    let source = SlidingCamera { views: None };
    let config = train_config(stage1(), 4, 2);

    let mut straight = fresh_trainer(config.clone(), &device);
    for _ in 0..6 {
        straight.train_step(&source).unwrap();
    }

    let dir = tempfile::tempdir().unwrap();
    let mut first_half = fresh_trainer(config.clone(), &device);
    for _ in 0..3 {
        first_half.train_step(&source).unwrap();
    }
    first_half.save_checkpoint(dir.path()).unwrap();
    drop(first_half);
    let mut resumed = Trainer::resume(config, dir.path(), None, &device).unwrap();
    assert_eq!(resumed.step(), 3);
    for _ in 0..3 {
        resumed.train_step(&source).unwrap();
    }
    assert_eq!(parameters(straight.model()), parameters(resumed.model()));
}

/// Every parameter's gradient, flattened, in the model's visiting order.
fn gradient_values(model: &XFactor, grads: &GradientsParams) -> Vec<f32> {
    struct Collect<'a>(&'a GradientsParams, Vec<f32>);
    impl ModuleVisitor for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let grad = self
                .0
                .get::<D>(param.id)
                .expect("every parameter has a gradient");
            self.1.extend(grad.try_into_vec_as::<f32>().unwrap());
        }
    }
    let mut collect = Collect(grads, Vec::new());
    model.visit(&mut collect);
    collect.1
}

#[test]
fn accumulating_two_micro_batches_equals_one_batch() {
    let device = Device::flex().autodiff();
    let source = SlidingCamera { views: None };
    let accumulated = fresh_trainer(train_config(stage1(), 8, 4), &device);
    let whole = fresh_trainer(train_config(stage1(), 8, 8), &device);
    let (loss_a, grads_a) = accumulated.batch_gradients(&source).unwrap();
    let (loss_b, grads_b) = whole.batch_gradients(&source).unwrap();
    assert!((loss_a - loss_b).abs() < 1e-6, "{loss_a} vs {loss_b}");
    let a = gradient_values(accumulated.model(), &grads_a);
    let b = gradient_values(whole.model(), &grads_b);
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let worst = a
        .iter()
        .zip(&b)
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
    assert!(
        scale > 0.0 && worst <= 1e-5 * scale,
        "gradients differ by {worst} of {scale}"
    );
}

#[test]
fn stage2_trains_from_multi_view_samples() {
    let device = Device::flex().autodiff();
    let objective = StageObjective::Stage2(Stage2Config {
        lpips_weight: 0.0,
        ..Stage2Config::default()
    });
    let mut trainer = fresh_trainer(train_config(objective, 2, 2), &device);
    let metrics = trainer
        .train_step(&SlidingCamera { views: Some(6) })
        .unwrap();
    assert!(metrics.loss.is_finite() && metrics.applied);
    let wrong = trainer
        .train_step(&SlidingCamera { views: None })
        .unwrap_err();
    assert!(matches!(wrong, TrainError::WrongSamples { .. }), "{wrong}");
}

#[test]
fn a_positive_lpips_weight_without_weights_is_refused() {
    let device = Device::flex().autodiff();
    let model = XFactor::new(&model_config(), 1, &device).unwrap();
    let config = train_config(StageObjective::Stage1(Stage1Config::default()), 4, 2);
    let error = Trainer::new(config, model_config(), model, None, &device)
        .err()
        .expect("refused");
    assert!(
        error.to_string().contains("convert_lpips_weights"),
        "{error}"
    );
}

#[test]
fn run_checkpoints_every_n_steps_and_stage2_starts_from_stage1_pose_enc() {
    let device = Device::flex().autodiff();
    let dir = tempfile::tempdir().unwrap();
    let mut stage1_trainer = fresh_trainer(train_config(stage1(), 2, 2), &device);
    let mut seen = Vec::new();
    let mut saved_at = Vec::new();
    stage1_trainer
        .run(
            &SlidingCamera { views: None },
            5,
            Some((dir.path(), 2)),
            |m| {
                seen.push(m.step);
                let state = std::fs::read_to_string(dir.path().join("state.json")).ok();
                saved_at.push(state);
            },
        )
        .unwrap();
    assert_eq!(seen, vec![0, 1, 2, 3, 4]);
    let state = std::fs::read_to_string(dir.path().join("state.json")).unwrap();
    assert!(state.contains("\"step\": 5"), "{state}");
    // A checkpoint existed after step 2 (written when 2 steps were done).
    assert!(
        saved_at[2]
            .as_deref()
            .is_some_and(|s| s.contains("\"step\": 2"))
    );

    // The release's start: PoseEnc from stage 1, Render freshly initialised from the seed.
    let stage2 = StageObjective::Stage2(Stage2Config {
        lpips_weight: 0.0,
        ..Stage2Config::default()
    });
    let stage2_trainer =
        Trainer::from_weights(train_config(stage2, 2, 2), dir.path(), None, &device).unwrap();
    assert_eq!(stage2_trainer.step(), 0);
    let fresh = XFactor::new(&model_config(), train_config(stage1(), 2, 2).seed, &device).unwrap();
    assert_eq!(
        parameters_of(&stage2_trainer.model().pose_enc),
        parameters_of(&stage1_trainer.model().pose_enc)
    );
    assert_eq!(
        parameters_of(&stage2_trainer.model().render),
        parameters_of(&fresh.render)
    );
    assert_ne!(
        parameters_of(&stage2_trainer.model().render),
        parameters_of(&stage1_trainer.model().render)
    );

    // The paper's text: both networks continue from stage 1.
    let stage2 = StageObjective::Stage2(Stage2Config {
        lpips_weight: 0.0,
        render_from_stage1: true,
        ..Stage2Config::default()
    });
    let stage2_trainer =
        Trainer::from_weights(train_config(stage2, 2, 2), dir.path(), None, &device).unwrap();
    assert_eq!(
        parameters(stage2_trainer.model()),
        parameters(stage1_trainer.model())
    );
}

/// Losses of `steps` stage-1 steps of the tiny model at `precision`, from the same weights.
fn losses_at(precision: settings::model::Precision, steps: usize) -> Vec<f32> {
    losses_on(Device::flex().autodiff(), precision, steps)
}

/// [`losses_at`] on `device`.
fn losses_on(device: Device, precision: settings::model::Precision, steps: usize) -> Vec<f32> {
    let config = XFactorConfig {
        precision,
        ..model_config()
    };
    trained(device, config, steps).1
}

/// A trainer of the tiny model `config` after `steps` stage-1 steps, and their losses.
fn trained(device: Device, config: XFactorConfig, steps: usize) -> (Trainer, Vec<f32>) {
    let model = XFactor::new(&config, 1, &device).unwrap();
    let mut trainer =
        Trainer::new(train_config(stage1(), 4, 2), config, model, None, &device).unwrap();
    let source = SlidingCamera { views: None };
    let losses = (0..steps)
        .map(|_| trainer.train_step(&source).unwrap().loss)
        .collect();
    (trainer, losses)
}

/// The largest relative difference between two runs' losses, step by step.
fn worst_relative_difference(losses: &[f32], reference: &[f32]) -> f32 {
    losses
        .iter()
        .zip(reference)
        .map(|(h, f)| ((h - f) / f).abs())
        .fold(0.0f32, f32::max)
}

/// `model.compute: bf16` (torch's autocast): products and attention in bf16, weights, their
/// updates and AdamW's state in float32. The losses follow float32's within 2% at each of 8
/// steps (and differ: the products did run in bf16), and every parameter is still float32
/// afterwards.
#[test]
fn bf16_compute_trains_like_float32_and_keeps_float32_weights() {
    use settings::model::Precision;
    let steps = 8;
    let reference = losses_at(Precision::F32, steps);
    let config = XFactorConfig {
        compute: Precision::Bf16,
        ..model_config()
    };
    let (trainer, losses) = trained(Device::flex().autodiff(), config, steps);
    let worst = worst_relative_difference(&losses, &reference);
    println!(
        "compute=bf16 steps={steps} worst_relative_loss_difference={worst:.2e} f32_last={:.4} bf16_last={:.4}",
        reference[steps - 1],
        losses[steps - 1]
    );
    assert!(worst > 0.0, "compute bf16 changed nothing");
    assert!(worst < 0.02, "compute bf16: the loss strays by {worst:e}");
    let dtypes = parameter_dtypes(trainer.model());
    assert!(
        dtypes
            .iter()
            .all(|dtype| *dtype == burn::tensor::DType::F32),
        "compute bf16: parameters in {dtypes:?}"
    );
}

/// The float type of every parameter of `model`.
fn parameter_dtypes<M: Module>(model: &M) -> Vec<burn::tensor::DType> {
    struct Collect(Vec<burn::tensor::DType>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.push(param.val().dtype());
        }
    }
    let mut collect = Collect(Vec::new());
    model.visit(&mut collect);
    collect.0
}

#[test]
fn half_precision_trains_like_float32_within_a_percent_of_the_loss() {
    use settings::model::Precision;
    let steps = 8;
    let reference = losses_at(Precision::F32, steps);
    for half in [Precision::Bf16, Precision::F16] {
        let losses = losses_at(half, steps);
        let worst = worst_relative_difference(&losses, &reference);
        println!(
            "precision={} steps={steps} worst_relative_loss_difference={worst:.2e} f32_first={:.4} f32_last={:.4} half_last={:.4}",
            half.name(),
            reference[0],
            reference[steps - 1],
            losses[steps - 1]
        );
        assert!(worst > 0.0, "{} rounded nothing", half.name());
        assert!(
            worst < 0.01,
            "{}: the loss strays by {worst:e}",
            half.name()
        );
    }
}

#[test]
fn activation_checkpointing_recomputes_to_the_same_losses() {
    let precision = settings::model::Precision::F32;
    let plain = losses_on(Device::flex().autodiff(), precision, 4);
    let checkpointed = losses_on(
        Device::flex().autodiff().gradient_checkpointing(),
        precision,
        4,
    );
    for (a, b) in plain.iter().zip(&checkpointed) {
        assert!((a - b).abs() <= 1e-6 * a.abs().max(1.0), "{a} vs {b}");
    }
}

/// Trains the tiny model for six steps on `backend` and on burn's CPU backend from the same
/// weights and batches; the losses agree to `1e-3` relative (float32 sums in another order).
#[cfg(any(feature = "vulkan", feature = "libtorch"))]
fn trains_like_the_cpu_backend(backend: trainer_core::backend::Backend) {
    use trainer_core::backend::BackendDevices;
    let precision = settings::model::Precision::F32;
    let steps = 6;
    let reference = losses_on(Device::flex().autodiff(), precision, steps);
    let device = backend.device().unwrap().autodiff();
    let losses = losses_on(device, precision, steps);
    let worst = losses
        .iter()
        .zip(&reference)
        .map(|(b, c)| ((b - c) / c).abs())
        .fold(0.0f32, f32::max);
    println!(
        "backend={backend} steps={steps} worst_relative_loss_difference={worst:.2e} cpu_first={:.5} cpu_last={:.5} {backend}_last={:.5}",
        reference[0],
        reference[steps - 1],
        losses[steps - 1]
    );
    assert!(
        reference[steps - 1] < reference[0],
        "the CPU run learned nothing: {reference:?}"
    );
    assert!(worst < 1e-3, "{backend}: {losses:?} vs cpu {reference:?}");
}

/// libtorch's CPU device here; on a GPU host the same build trains on libtorch's CUDA.
#[cfg(feature = "libtorch")]
#[test]
fn libtorch_trains_like_the_cpu_backend() {
    trains_like_the_cpu_backend(trainer_core::backend::Backend::Libtorch);
}

/// SPIR-V kernels on the first Vulkan adapter: lavapipe on this machine, under the validation
/// layer where `VK_INSTANCE_LAYERS` asks for it.
#[cfg(feature = "vulkan")]
#[test]
fn vulkan_trains_like_the_cpu_backend() {
    trains_like_the_cpu_backend(trainer_core::backend::Backend::Vulkan);
}
