//! Benchmark of full training steps (batch assembly, forward, backward, AdamW) for stage 1 and
//! stage 2 on the benchmark configuration, with and without LPIPS, on generated scenes.
//!
//! `cargo bench -p trainer-core --bench objective_step -- [--steps N] [--batch B]`. LPIPS uses
//! the random-weight fixture of the pretrained layout (`../shared/fixtures`, or
//! `$XFACTOR_SHARED/fixtures`): the same network, so the same cost.

use std::path::PathBuf;
use std::time::Instant;

use burn::tensor::Device;
use data::scenes::SceneConfig;
use data::synthetic::SyntheticDataset;
use settings::objective::{Stage1Config, Stage2Config};
use settings::optim::{AdamWConfig, Schedule};
use settings::train::{StageObjective, TrainConfig};
use trainer_core::allocator;
use trainer_core::lpips::Lpips;
use trainer_core::trainer::Trainer;
use trainer_core::{XFactor, XFactorConfig};

fn argument(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let tuning = allocator::keep_freed_memory();
    let steps = argument("--steps", 2);
    let batch = argument("--batch", 8);
    let shards = std::thread::available_parallelism().map_or(1, |n| n.get());
    let model_config = XFactorConfig::benchmark();
    let device = Device::flex().autodiff();
    let shared = std::env::var_os("XFACTOR_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared"));
    let lpips = Lpips::from_file(
        &shared.join("fixtures/lpips-vgg16-random.safetensors"),
        &device,
    )
    .expect("LPIPS weights of the pretrained layout");
    let mut dataset = SyntheticDataset::generate(
        0,
        4,
        4,
        8,
        &SceneConfig {
            image_size: model_config.image_size,
            ..SceneConfig::default()
        },
    );
    println!(
        "config: backend=cpu shards={shards} allocator_tuned={} batch={batch} image={} width={} heads={} layers={}+{} stage2_views=6 steps={steps}",
        tuning.heap_for_large_blocks && tuning.keep_freed_top,
        model_config.image_size,
        model_config.width,
        model_config.num_heads,
        model_config.pose_layers,
        model_config.render_layers,
    );
    let mut line = Vec::new();
    for (label, views, weight) in [
        ("stage1", 2, 0.0),
        ("stage1_lpips", 2, 0.5),
        ("stage2", 6, 0.0),
        ("stage2_lpips", 6, 0.5),
    ] {
        dataset.views = views;
        let objective = if views == 2 {
            StageObjective::Stage1(Stage1Config {
                lpips_weight: weight,
                ..Stage1Config::default()
            })
        } else {
            StageObjective::Stage2(Stage2Config {
                lpips_weight: weight,
                ..Stage2Config::default()
            })
        };
        let config = TrainConfig {
            seed: 0,
            objective,
            global_batch: batch,
            micro_batch: batch,
            shards,
            schedule: Schedule::default(),
            optimizer: AdamWConfig::default(),
        };
        let model = XFactor::new(&model_config, 0, &device).expect("benchmark config is valid");
        let network = (weight > 0.0).then(|| lpips.clone());
        let mut trainer =
            Trainer::new(config, model_config.clone(), model, network, &device).expect("trainer");
        trainer.train_step(&dataset).expect("warm-up step");
        let mut times: Vec<f64> = (0..steps)
            .map(|_| {
                let start = Instant::now();
                trainer.train_step(&dataset).expect("step");
                start.elapsed().as_secs_f64()
            })
            .collect();
        times.sort_by(f64::total_cmp);
        line.push(format!("{label}_step_s={:.3}", times[times.len() / 2]));
    }
    println!("{}", line.join(" "));
}
