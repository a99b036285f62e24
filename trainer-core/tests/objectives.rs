//! Both objectives with the model and the optimiser: the stage-1 loss falls on a toy problem,
//! stage 1 through the shared path equals the direct computation, stage 2 reaches every
//! parameter; the autoencoding, extra-view and SE(3)-and-Plücker variants equal their hand
//! computations and learn.

mod common;

use burn::module::Module;
use burn::tensor::Device;
use burn::tensor::{Tensor, TensorData};
use data::Image;
use data::rng::Stream;
use settings::model::{CAMERA_VECTOR_VALUES, PoseConditioning};
use settings::objective::{ObjectiveVariant, Stage1Config, Stage2Config};
use settings::optim::{AdamWConfig, Schedule};
use trainer_core::lpips::Lpips;
use trainer_core::model::PoseLatents;
use trainer_core::objective::{Stage1Objective, Stage2Objective, objective_loss, swap_slots};
use trainer_core::optim::AdamW;
use trainer_core::sharded::sharded_gradients;
use trainer_core::{XFactor, XFactorConfig};

const SIDE: usize = 16;

/// A smooth random pattern seen through a window shifted by `shift` pixels: a pair of frames
/// from a camera that slides sideways.
fn sliding_pair(stream: &mut Stream) -> (Image, Image) {
    let phases: Vec<f64> = (0..6)
        .map(|_| stream.uniform_in(0.0, std::f64::consts::TAU))
        .collect();
    let shift = stream.uniform_in(-3.0, 3.0);
    let frame = |offset: f64| common::sliding_frame(&phases, offset, SIDE);
    (frame(0.0), frame(shift))
}

/// The same slide as [`sliding_pair`] with a frame halfway: reference, extra view, target.
fn sliding_triple(stream: &mut Stream) -> Vec<(u64, Image)> {
    let phases: Vec<f64> = (0..6)
        .map(|_| stream.uniform_in(0.0, std::f64::consts::TAU))
        .collect();
    let shift = stream.uniform_in(-3.0, 3.0);
    [0.0, 0.5, 1.0]
        .into_iter()
        .enumerate()
        .map(|(i, share)| {
            (
                i as u64,
                common::sliding_frame(&phases, shift * share, SIDE),
            )
        })
        .collect()
}

/// `mean |second - prediction|` over the second frames of `pairs`: the L1 loss by hand.
fn mean_error_to_second_frames(pairs: &[(Image, Image)], prediction: Tensor<4>) -> f32 {
    let seconds: Vec<f32> = pairs
        .iter()
        .flat_map(|(_, second)| second.pixels.iter().copied())
        .collect();
    let shape = [pairs.len(), SIDE, SIDE, 3];
    let targets = Tensor::<4>::from_data(TensorData::new(seconds, shape), &prediction.device());
    (targets - prediction).abs().mean().into_scalar::<f32>()
}

fn tiny_config() -> XFactorConfig {
    XFactorConfig::tiny(SIDE)
}

/// The tiny model as a job training `variant` builds it: `se3_plucker` reads camera vectors
/// and conditions Render on their Plücker rays.
fn tiny_config_for(variant: ObjectiveVariant) -> XFactorConfig {
    let mut config = tiny_config();
    config.pose_conditioning = variant.pose_conditioning();
    if config.pose_conditioning == PoseConditioning::PluckerRays {
        config.pose_dim = CAMERA_VECTOR_VALUES;
    }
    config
}

/// Trains the tiny model with `variant` for `steps` AdamW steps on eight sliding pairs (or,
/// for the extra-view variants, triples; two shards of four) and returns the mean loss of the first five and of the last five steps.
fn train_tiny(variant: ObjectiveVariant, pairs_seed: u64, steps: u64) -> (f32, f32) {
    let device = Device::flex().autodiff();
    let config = tiny_config_for(variant);
    let mut model = XFactor::new(&config, 0, &device).unwrap();
    let objective = Stage1Config {
        lpips_weight: 0.0,
        variant,
        ..Stage1Config::default()
    };
    let schedule = Schedule {
        initial_lr: 1e-4,
        peak_lr: 3e-3,
        final_lr: 1e-3,
        warmup_steps: 5,
        total_steps: steps,
    };
    let mut optimizer = AdamW::new(AdamWConfig::default());
    let mut stream = Stream::new(&[pairs_seed]);
    let pairs: Vec<_> = (0..8).map(|_| sliding_pair(&mut stream)).collect();
    let triples: Vec<_> = (0..8).map(|_| sliding_triple(&mut stream)).collect();
    let mut losses = Vec::new();
    for step in 0..steps {
        let (loss, grads) = sharded_gradients(&model, 2, |copy, shard| {
            let (first, patch) = (shard * 4, config.patch_size);
            let batch = if variant.stage1_frames() == 3 {
                let shard_triples = &triples[first..first + 4];
                objective.batch_with_extra_view(
                    shard_triples,
                    0,
                    step,
                    first as u64,
                    patch,
                    &device,
                )
            } else {
                objective.batch(
                    &pairs[first..first + 4],
                    0,
                    step,
                    first as u64,
                    patch,
                    &device,
                )
            };
            objective_loss(copy, None, 0.0, &batch).total * 0.5
        });
        let (updated, report) = optimizer.step(model, &grads, schedule.learning_rate(step));
        assert!(report.applied && report.grad_norm.is_finite());
        model = updated;
        losses.push(loss);
    }
    let mean = |window: &[f32]| window.iter().sum::<f32>() / window.len() as f32;
    (mean(&losses[..5]), mean(&losses[losses.len() - 5..]))
}

#[test]
fn stage1_loss_falls_with_adamw() {
    let (start, end) = train_tiny(ObjectiveVariant::Transfer, 42, 300);
    println!("stage-1 L1: first five steps {start:.4}, last five {end:.4}");
    assert!(end < 0.7 * start, "loss went from {start} to {end}");
}

#[test]
fn lpips_term_enters_the_loss() {
    let device = Device::flex().autodiff();
    let config = tiny_config();
    let model = XFactor::new(&config, 0, &device).unwrap();
    let lpips = Lpips::from_file(
        &common::shared_fixture("lpips-vgg16-random.safetensors"),
        &device,
    )
    .unwrap();
    let objective = Stage1Config::default();
    let pairs: Vec<_> = (0..2)
        .map(|_| sliding_pair(&mut Stream::new(&[1])))
        .collect();
    let batch = objective.batch(&pairs, 0, 0, 0, config.patch_size, &device);
    let loss = objective_loss(&model, Some(&lpips), 0.5, &batch);
    let l1 = loss.l1.into_scalar::<f32>();
    let distance = loss.lpips.expect("LPIPS given").into_scalar::<f32>();
    let total = loss.total.into_scalar::<f32>();
    assert!(distance > 0.0 && distance.is_finite());
    assert!((total - (l1 + 0.5 * distance)).abs() < 1e-6);
}

#[test]
fn shared_path_equals_the_direct_stage1_computation() {
    let device = Device::flex();
    let config = tiny_config();
    let model = XFactor::new(&config, 3, &device).unwrap();
    let objective = Stage1Config::default();
    let mut stream = Stream::new(&[5]);
    let pairs: Vec<_> = (0..4).map(|_| sliding_pair(&mut stream)).collect();
    // A sample whose draw marks two quadrants, so the mask and the swap both matter.
    let sample = (0..100)
        .find(|&s| !objective.draw(0, 0, s).mask.is_empty())
        .unwrap();
    let batch = objective.batch(&pairs[..1], 0, 0, sample, config.patch_size, &device);
    let shared = objective_loss(&model, None, 0.0, &batch)
        .l1
        .into_scalar::<f32>();
    let latents = model
        .pose_enc
        .forward_masked(batch.encoder_pairs.clone(), batch.mask.clone());
    let prediction = model.render.forward(
        batch.context.clone(),
        PoseLatents::PerSegment(swap_slots(latents)),
        Some(batch.mask.clone()),
    );
    let direct = (batch.target.clone() - prediction)
        .abs()
        .mean()
        .into_scalar::<f32>();
    assert!((shared - direct).abs() <= 1e-7, "{shared} vs {direct}");
}

#[test]
fn stage2_loss_reaches_every_parameter() {
    let device = Device::flex().autodiff();
    let config = tiny_config();
    let model = XFactor::new(&config, 4, &device).unwrap();
    let objective = Stage2Config {
        lpips_weight: 0.0,
        ..Stage2Config::default()
    };
    let mut stream = Stream::new(&[8]);
    let samples: Vec<Vec<(u64, Image)>> = (0..2)
        .map(|_| {
            (0..6u64)
                .map(|frame| (frame * 3, sliding_pair(&mut stream).1))
                .collect()
        })
        .collect();
    let batch = objective.batch(&samples, 0, 1, 0, config.patch_size, &device);
    assert_eq!(batch.context.dims(), [2, 5, SIDE, SIDE, 3]);
    assert_eq!(batch.encoder_pairs.dims(), [10, 2, SIDE, SIDE, 3]);
    let loss = objective_loss(&model, None, 0.0, &batch).total;
    assert!(loss.clone().into_scalar::<f32>().is_finite());
    let grads = loss.backward();
    let mut missing = 0;
    struct Count<'a>(&'a burn::tensor::Gradients, &'a mut usize);
    impl burn::module::ModuleVisitor for Count<'_> {
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            if param.val().grad(self.0).is_none() {
                *self.1 += 1;
            }
        }
    }
    model.visit(&mut Count(&grads, &mut missing));
    assert_eq!(missing, 0, "parameters without a gradient");
}

#[test]
fn autoencode_renders_the_other_frame_from_its_whole_image_latent() {
    let device = Device::flex();
    let config = tiny_config();
    let model = XFactor::new(&config, 3, &device).unwrap();
    let objective = Stage1Config {
        variant: ObjectiveVariant::Autoencode,
        ..Stage1Config::default()
    };
    let mut stream = Stream::new(&[9]);
    let pairs: Vec<_> = (0..4).map(|_| sliding_pair(&mut stream)).collect();
    // Over many draws: never a mask, never the context as target.
    for sample in 0..200 {
        let draw = objective.draw(0, 0, sample);
        assert!(draw.mask.is_empty() && !draw.self_decode, "sample {sample}");
    }
    let batch = objective.batch(&pairs, 0, 0, 0, config.patch_size, &device);
    let loss = objective_loss(&model, None, 0.0, &batch)
        .l1
        .into_scalar::<f32>();
    // By hand: PoseEnc on the whole (unmasked) pair gives the target's latent z against the
    // reference (whose own latent is 0); Render draws the second frame from the first with
    // z in both segment slots; the loss is the mean absolute error.
    let latents = model
        .pose_enc
        .forward_masked(batch.encoder_pairs.clone(), batch.mask.zeros_like());
    let target_latent = latents.clone().narrow(1, 1, 1).narrow(2, 0, 1);
    let per_slot = Tensor::cat(vec![target_latent.clone(), target_latent], 2);
    let latents = Tensor::cat(vec![per_slot.zeros_like(), per_slot], 1);
    let prediction = model.render.forward(
        batch.context.clone(),
        PoseLatents::PerSegment(latents),
        Some(batch.mask.zeros_like()),
    );
    let by_hand = mean_error_to_second_frames(&pairs, prediction);
    assert!((loss - by_hand).abs() <= 1e-6, "{loss} vs {by_hand}");
}

#[test]
fn autoencode_loss_falls_with_adamw() {
    let (start, end) = train_tiny(ObjectiveVariant::Autoencode, 43, 150);
    println!("autoencode L1: first five steps {start:.4}, last five {end:.4}");
    assert!(end < 0.7 * start, "loss went from {start} to {end}");
}

/// The stage-1 objective of `variant` with no mask, no self-decoding and no augmentation:
/// what is left is the variant's own wiring of PoseEnc and Render.
fn bare_objective(variant: ObjectiveVariant) -> Stage1Config {
    Stage1Config {
        unmasked_probability: 1.0,
        self_decode_probability: 0.0,
        augment: settings::objective::AugmentConfig {
            jitter_probability: 0.0,
            blur_probability: 0.0,
            ..Default::default()
        },
        variant,
        ..Stage1Config::default()
    }
}

/// Render's per-segment latents `(B, 3, 2, Cp)` for the extra-view variants, by hand: the
/// reference's zero, then the extra view's and the target's latents against the reference
/// (slot 0 of an unmasked read) in both slots; `joint` reads all three views in one PoseEnc
/// call, otherwise each view is read as a pair with the reference.
fn latents_by_hand(
    model: &XFactor,
    reference: &Tensor<4>,
    extra: &Tensor<4>,
    target: &Tensor<4>,
    no_mask: &Tensor<2>,
    joint: bool,
) -> Tensor<4> {
    let (extra_latent, target_latent) = if joint {
        let all = Tensor::stack::<5>(vec![reference.clone(), extra.clone(), target.clone()], 1);
        let latents = model.pose_enc.forward_masked(all, no_mask.clone());
        (
            latents.clone().narrow(1, 1, 1).narrow(2, 0, 1),
            latents.narrow(1, 2, 1).narrow(2, 0, 1),
        )
    } else {
        let read = |view: &Tensor<4>| {
            let pair = Tensor::stack::<5>(vec![reference.clone(), view.clone()], 1);
            model
                .pose_enc
                .forward_masked(pair, no_mask.clone())
                .narrow(1, 1, 1)
                .narrow(2, 0, 1)
        };
        (read(extra), read(target))
    };
    let both_slots = |latent: Tensor<4>| Tensor::cat(vec![latent.clone(), latent], 2);
    let extra_slots = both_slots(extra_latent);
    Tensor::cat(
        vec![
            extra_slots.zeros_like(),
            extra_slots,
            both_slots(target_latent),
        ],
        1,
    )
}

#[test]
fn extra_view_variants_render_from_two_context_views_as_by_hand() {
    let device = Device::flex();
    let config = tiny_config();
    let model = XFactor::new(&config, 3, &device).unwrap();
    let mut stream = Stream::new(&[11]);
    let samples: Vec<_> = (0..3).map(|_| sliding_triple(&mut stream)).collect();
    let stack = |index: usize| {
        let pixels: Vec<f32> = samples
            .iter()
            .flat_map(|s| s[index].1.pixels.iter().copied())
            .collect();
        Tensor::<4>::from_data(TensorData::new(pixels, [3, SIDE, SIDE, 3]), &device)
    };
    let (reference, extra, target) = (stack(0), stack(1), stack(2));
    let tokens = config.tokens_per_view();
    let no_mask = Tensor::<2>::zeros([3, tokens], &device);
    for (variant, joint) in [
        (ObjectiveVariant::ExtraViewDecoder, false),
        (ObjectiveVariant::ExtraViewEncoderDecoder, true),
    ] {
        let objective = bare_objective(variant);
        let batch = objective.batch_with_extra_view(&samples, 0, 0, 0, config.patch_size, &device);
        let expected_encoder = if joint { [3, 3] } else { [6, 2] };
        assert_eq!(
            batch.encoder_pairs.dims()[..2],
            expected_encoder,
            "{variant:?}"
        );
        let loss = objective_loss(&model, None, 0.0, &batch)
            .l1
            .into_scalar::<f32>();
        // By hand: the extra view's and the target's latents against the reference (slot 0
        // of an unmasked read), the reference's zero, Render from reference and extra view.
        let latents = latents_by_hand(&model, &reference, &extra, &target, &no_mask, joint);
        let context = Tensor::stack::<5>(vec![reference.clone(), extra.clone()], 1);
        let prediction = model.render.forward(
            context,
            PoseLatents::PerSegment(latents),
            Some(no_mask.clone()),
        );
        let by_hand = (target.clone() - prediction)
            .abs()
            .mean()
            .into_scalar::<f32>();
        assert!(
            (loss - by_hand).abs() <= 1e-6,
            "{variant:?}: {loss} vs {by_hand}"
        );
    }
}

#[test]
fn extra_view_losses_fall_with_adamw() {
    for (variant, seed) in [
        (ObjectiveVariant::ExtraViewDecoder, 44),
        (ObjectiveVariant::ExtraViewEncoderDecoder, 45),
    ] {
        let (start, end) = train_tiny(variant, seed, 150);
        println!("{variant:?} L1: first five steps {start:.4}, last five {end:.4}");
        assert!(
            end < 0.7 * start,
            "{variant:?}: loss went from {start} to {end}"
        );
    }
}

#[test]
fn se3_plucker_renders_the_other_frame_from_the_rays_of_its_camera() {
    let device = Device::flex();
    let variant = ObjectiveVariant::Se3Plucker;
    let config = tiny_config_for(variant);
    let model = XFactor::new(&config, 5, &device).unwrap();
    let objective = Stage1Config {
        variant,
        ..Stage1Config::default()
    };
    for sample in 0..200 {
        let draw = objective.draw(0, 0, sample);
        assert!(draw.mask.is_empty() && !draw.self_decode, "sample {sample}");
    }
    let mut stream = Stream::new(&[12]);
    let pairs: Vec<_> = (0..4).map(|_| sliding_pair(&mut stream)).collect();
    let batch = objective.batch(&pairs, 0, 0, 0, config.patch_size, &device);
    let loss = objective_loss(&model, None, 0.0, &batch)
        .l1
        .into_scalar::<f32>();

    // By hand: PoseEnc reads the unmasked pair; the reference's camera vector is exactly 0
    // (the identity camera), the target's is c.
    let cameras = model.pose_enc.forward(batch.encoder_pairs.clone());
    assert_eq!(cameras.dims(), [4, 2, CAMERA_VECTOR_VALUES]);
    let reference = cameras
        .clone()
        .narrow(1, 0, 1)
        .try_into_vec_as::<f32>()
        .unwrap();
    assert!(reference.iter().all(|&v| v == 0.0), "{reference:?}");
    // Render conditioned on those cameras' rays draws the second frame from the first.
    let target_camera = cameras.narrow(1, 1, 1);
    let both = Tensor::cat(vec![target_camera.zeros_like(), target_camera], 1);
    let prediction = model.render.forward(
        batch.context.clone(),
        PoseLatents::Single(both.clone()),
        None,
    );
    let by_hand = mean_error_to_second_frames(&pairs, prediction);
    assert!((loss - by_hand).abs() <= 1e-6, "{loss} vs {by_hand}");

    // The views share the target's focal length: the context camera's own φ is not read;
    // its pose is (a rotation component that is not a mere rescaling of a column), and so
    // is the target's camera.
    let render = |cameras: Tensor<3>| {
        model
            .render
            .forward(batch.context.clone(), PoseLatents::Single(cameras), None)
    };
    let nudge = |view: usize, value: usize| {
        let mut offset = vec![0.0f32; 2 * CAMERA_VECTOR_VALUES];
        offset[view * CAMERA_VECTOR_VALUES + value] = 0.5;
        both.clone()
            + Tensor::<3>::from_data(
                TensorData::new(offset, [1, 2, CAMERA_VECTOR_VALUES]),
                &device,
            )
    };
    let base = render(both.clone());
    let change = |cameras: Tensor<3>| {
        (render(cameras) - base.clone())
            .abs()
            .max()
            .into_scalar::<f32>()
    };
    let focal = CAMERA_VECTOR_VALUES - 1;
    assert_eq!(change(nudge(0, focal)), 0.0, "the context's focal length");
    for (view, value) in [(0, 1), (0, 6), (1, 1), (1, 6), (1, focal)] {
        let moved = change(nudge(view, value));
        assert!(moved > 1e-5, "view {view} value {value}: change {moved}");
    }
}

#[test]
fn se3_plucker_loss_falls_with_adamw() {
    let (start, end) = train_tiny(ObjectiveVariant::Se3Plucker, 46, 150);
    println!("se3_plucker L1: first five steps {start:.4}, last five {end:.4}");
    assert!(end < 0.7 * start, "loss went from {start} to {end}");
}
