//! Learning on generated scenes: the stage-1 loss falls, and poses read from one scene move the
//! camera correctly in another (better than the mean-image baseline). Prints the curve.

use burn::tensor::{Device, Tensor, TensorData};
use data::Image;
use data::scenes::SceneConfig;
use data::synthetic::SyntheticDataset;
use settings::objective::Stage1Config;
use settings::optim::{AdamWConfig, Schedule};
use settings::train::{StageObjective, TrainConfig};
use trainer_core::model::PoseLatents;
use trainer_core::trainer::Trainer;
use trainer_core::{XFactor, XFactorConfig};

const SIDE: usize = 32;
const STEPS: u64 = 300;
const SCENES: u64 = 8;
const TRAJECTORIES: u64 = 12;

fn upload(images: &[&Image], device: &Device) -> Tensor<5> {
    let values: Vec<f32> = images.iter().flat_map(|i| i.pixels.clone()).collect();
    Tensor::from_data(
        TensorData::new(values, [images.len(), 1, SIDE, SIDE, 3]),
        device,
    )
}

/// Mean L1 of rendering scene `(s + 1) % SCENES` along the motion read from scene `s`, for every
/// trajectory and scene, and of two baselines: the mean target image and the unmoved context.
fn transfer_errors(
    model: &XFactor,
    dataset: &SyntheticDataset,
    device: &Device,
) -> (f32, f32, f32) {
    let (first, last) = (0usize, 3usize);
    let mut sources_first = Vec::new();
    let mut sources_last = Vec::new();
    let mut contexts = Vec::new();
    let mut targets = Vec::new();
    for trajectory in 0..TRAJECTORIES {
        for scene in 0..SCENES {
            let source = dataset.sequence(scene, trajectory).unwrap();
            let other = dataset.sequence((scene + 1) % SCENES, trajectory).unwrap();
            sources_first.push(&source.frames[first]);
            sources_last.push(&source.frames[last]);
            contexts.push(&other.frames[first]);
            targets.push(&other.frames[last]);
        }
    }
    let count = targets.len();
    let pairs = Tensor::cat(
        vec![
            upload(&sources_first, device),
            upload(&sources_last, device),
        ],
        1,
    );
    let poses = model.pose_enc.forward(pairs);
    let rendered = model
        .render
        .forward(upload(&contexts, device), PoseLatents::Single(poses), None)
        .try_into_vec_as::<f32>()
        .unwrap();
    let target_values: Vec<f32> = targets.iter().flat_map(|i| i.pixels.clone()).collect();
    let context_values: Vec<f32> = contexts.iter().flat_map(|i| i.pixels.clone()).collect();
    let per_image = SIDE * SIDE * 3;
    let mean_image: Vec<f32> = (0..per_image)
        .map(|p| {
            (0..count)
                .map(|i| target_values[i * per_image + p])
                .sum::<f32>()
                / count as f32
        })
        .collect();
    let l1 = |prediction: &dyn Fn(usize) -> f32| {
        (0..target_values.len())
            .map(|i| (prediction(i) - target_values[i]).abs())
            .sum::<f32>()
            / target_values.len() as f32
    };
    (
        l1(&|i| rendered[i]),
        l1(&|i| mean_image[i % per_image]),
        l1(&|i| context_values[i]),
    )
}

#[test]
fn stage1_learns_transferable_motion_on_generated_scenes() {
    let device = Device::flex().autodiff();
    let dataset = SyntheticDataset::generate(
        0,
        SCENES,
        TRAJECTORIES,
        6,
        &SceneConfig {
            image_size: SIDE,
            ..SceneConfig::default()
        },
    );
    let model_config = XFactorConfig::small(SIDE);
    let config = TrainConfig {
        seed: 0,
        objective: StageObjective::Stage1(Stage1Config {
            lpips_weight: 0.0,
            ..Stage1Config::default()
        }),
        global_batch: 16,
        micro_batch: 16,
        shards: 2,
        schedule: Schedule {
            initial_lr: 1e-5,
            peak_lr: 1e-3,
            final_lr: 1e-4,
            warmup_steps: 20,
            total_steps: STEPS,
        },
        optimizer: AdamWConfig::default(),
    };
    let model = XFactor::new(&model_config, 0, &device).unwrap();
    let untrained = transfer_errors(&model, &dataset, &device);
    let mut trainer = Trainer::new(config, model_config, model, None, &device).unwrap();
    let mut window = Vec::new();
    let mut curve = Vec::new();
    for _ in 0..STEPS {
        let metrics = trainer.train_step(&dataset).unwrap();
        window.push(metrics.loss);
        if window.len() == 25 {
            curve.push(window.iter().sum::<f32>() / 25.0);
            window.clear();
        }
    }
    let trained = transfer_errors(trainer.model(), &dataset, &device);
    let curve_text: Vec<String> = curve.iter().map(|l| format!("{l:.4}")).collect();
    println!("stage1_l1_curve_per_25_steps={}", curve_text.join(","));
    println!(
        "transfer_l1_trained={:.4} transfer_l1_untrained={:.4} mean_image_l1={:.4} copy_context_l1={:.4}",
        trained.0, untrained.0, trained.1, trained.2
    );
    let (start, end) = (curve[0], curve[curve.len() - 1]);
    assert!(end < 0.6 * start, "loss fell only from {start} to {end}");
    assert!(
        trained.0 < trained.1,
        "transfer {} vs mean image {}",
        trained.0,
        trained.1
    );
    assert!(trained.0 < untrained.0);
}
