//! Benchmark of one stage-1 step (PoseEnc + Render forward and backward with the L1 loss) on the
//! benchmark configuration, and of the paper-scale model's construction and forward pass.
//!
//! `cargo bench -p trainer-core --bench model_step -- [--backend cpu|wgpu] [--steps N]
//! [--batch B] [--skip-paper]`. Prints its configuration, then one `key=value` line.

use std::time::Instant;

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use trainer_core::backend::BackendChoice;
use trainer_core::model::PoseLatents;
use trainer_core::rng::Stream;
use trainer_core::{XFactor, XFactorConfig};

struct Options {
    backend: BackendChoice,
    steps: usize,
    batch: usize,
    paper: bool,
}

fn parse_options() -> Options {
    let mut options = Options {
        backend: BackendChoice::Cpu,
        steps: 5,
        batch: 8,
        paper: true,
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--backend" => {
                options.backend = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--backend cpu|wgpu")
            }
            "--steps" => {
                options.steps = args.next().and_then(|v| v.parse().ok()).expect("--steps N")
            }
            "--batch" => {
                options.batch = args.next().and_then(|v| v.parse().ok()).expect("--batch B")
            }
            "--skip-paper" => options.paper = false,
            _ => {}
        }
    }
    options
}

fn uniform<const D: usize>(shape: [usize; D], seed: u64, device: &Device) -> Tensor<D> {
    let mut stream = Stream::new(&[seed]);
    let count = shape.iter().product();
    let values: Vec<f32> = (0..count)
        .map(|_| stream.uniform_in(-1.0, 1.0) as f32)
        .collect();
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// Two of the four patch-grid quadrants marked as segment 1, the same for every sample.
fn two_quadrant_mask(batch: usize, grid: usize, device: &Device) -> Tensor<2> {
    let half = grid / 2;
    let values: Vec<f32> = (0..batch)
        .flat_map(|_| {
            (0..grid * grid).map(move |i| {
                let (row, col) = (i / grid, i % grid);
                ((row < half) == (col < half)) as u8 as f32
            })
        })
        .collect();
    Tensor::from_data(TensorData::new(values, [batch, grid * grid]), device)
}

/// One stage-1 step; returns (forward seconds, backward seconds).
fn stage1_step(model: &XFactor, pair: &Tensor<5>, mask: &Tensor<2>) -> (f64, f64) {
    let [b, _, h, w, c] = pair.dims();
    let start = Instant::now();
    let poses = model.pose_enc.forward_masked(pair.clone(), mask.clone());
    let swapped = Tensor::cat(
        vec![poses.clone().narrow(2, 1, 1), poses.narrow(2, 0, 1)],
        2,
    );
    let pred = model.render.forward(
        pair.clone().narrow(1, 0, 1),
        PoseLatents::PerSegment(swapped),
        Some(mask.clone()),
    );
    let target = pair.clone().narrow(1, 1, 1).reshape([b, h, w, c]);
    let loss = (target - pred).abs().mean();
    let loss_value = loss.clone().into_scalar::<f32>();
    let forward = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let grads = loss.backward();
    let kernel_grad = model
        .render
        .pixel_head
        .dense_2
        .kernel
        .val()
        .grad(&grads)
        .expect("gradient reaches the pixel head");
    let grad_sum = kernel_grad.abs().sum().into_scalar::<f32>();
    assert!(loss_value.is_finite() && grad_sum.is_finite());
    (forward, start.elapsed().as_secs_f64())
}

fn main() {
    let options = parse_options();
    let config = XFactorConfig::benchmark();
    let device = options.backend.device().autodiff();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "config: backend={} threads={threads} batch={} image={} patch={} width={} heads={} layers={}+{} pose_dim={} global_tokens={} steps={}",
        options.backend.name(),
        options.batch,
        config.image_size,
        config.patch_size,
        config.width,
        config.num_heads,
        config.pose_layers,
        config.render_layers,
        config.pose_dim,
        config.global_tokens,
        options.steps
    );
    let model = XFactor::new(&config, 0, &device).expect("benchmark config is valid");
    let side = config.image_size;
    let pair = uniform([options.batch, 2, side, side, 3], 1, &device);
    let mask = two_quadrant_mask(options.batch, config.grid_side(), &device);

    let warmup = stage1_step(&model, &pair, &mask);
    let mut forward = Vec::new();
    let mut backward = Vec::new();
    for _ in 0..options.steps {
        let (f, b) = stage1_step(&model, &pair, &mask);
        forward.push(f);
        backward.push(b);
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let forward_s = median(&mut forward);
    let backward_s = median(&mut backward);
    let step_s = forward_s + backward_s;
    let mut line = format!(
        "backend={} batch={} params={} warmup_step_s={:.3} step_s={step_s:.3} forward_s={forward_s:.3} backward_s={backward_s:.3} pairs_per_s={:.2} vs_jax_0.99s={:.2}",
        options.backend.name(),
        options.batch,
        model.num_params(),
        warmup.0 + warmup.1,
        options.batch as f64 / step_s,
        step_s / 0.99,
    );

    if options.paper {
        let paper = XFactorConfig::paper();
        let inference = options.backend.device();
        let start = Instant::now();
        let big = XFactor::new(&paper, 0, &inference).expect("paper config is valid");
        let build_s = start.elapsed().as_secs_f64();
        let side = paper.image_size;
        let pair = uniform([1, 2, side, side, 3], 2, &inference);
        let start = Instant::now();
        let poses = big.pose_enc.forward(pair.clone());
        let image = big
            .render
            .forward(pair.narrow(1, 0, 1), PoseLatents::Single(poses), None);
        let checksum = image.sum().into_scalar::<f32>();
        let forward_s = start.elapsed().as_secs_f64();
        assert!(checksum.is_finite());
        line.push_str(&format!(
            " paper_params={} paper_build_s={build_s:.2} paper_forward_b1_s={forward_s:.2}",
            big.num_params()
        ));
    }
    println!("{line}");
}
