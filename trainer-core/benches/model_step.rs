//! Benchmark of one stage-1 step (PoseEnc + Render forward and backward with the L1 loss) on the
//! benchmark configuration, and of the paper-scale model's construction and forward pass.
//!
//! `cargo bench -p trainer-core --bench model_step -- [--backend cpu|wgpu] [--steps N]
//! [--warmup N] [--batch B] [--shards S] [--skip-paper] [--skip-jax]`; shards default to the
//! core count on the CPU backend and to 1 on the GPU backends. Warm-up steps (3 by default)
//! come first: fusion builds and autotunes its kernels on the steps after the first. On
//! cubecl's devices one more step times its kernels on the device (`kernel_device_s`, their
//! sum; `kernel_span_s`, first start to last end) beside its wall time (`profiled_step_s`):
//! device time well under the step's says the host is the limit.
//! Prints its configuration, then one `key=value` line.
//!
//! In the same run it times the JAX peer (`tools/reference/xfactor_reference.py bench`: the
//! same model and batch, jitted, float32) with the Python of `XFACTOR_JAX_PYTHON` or of
//! `~/.cache/xfactor-dist/jax-env` (`scripts/setup-jax.sh` makes it), and prints
//! `vs_jax=ours/theirs` (seconds per step; below 1 means ours is faster). Without that Python
//! the line says `vs_jax=unavailable` and why.

use std::time::Instant;

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use data::rng::Stream;
use settings::model::Precision;
use trainer_core::allocator;
use trainer_core::backend::{
    Backend, BackendDevices, MemoryFigures, count_kernels, default_shards, time_kernels,
};
use trainer_core::model::PoseLatents;
use trainer_core::sharded::sharded_gradients;
use trainer_core::{XFactor, XFactorConfig};

struct Options {
    backend: Backend,
    /// Threads that split the batch; by default one per core on the CPU backend, one on a GPU
    /// (`trainer_core::backend::default_shards`).
    shards: usize,
    steps: usize,
    /// Steps run before the timed ones.
    warmup: usize,
    batch: usize,
    paper: bool,
    jax: bool,
    /// `benchmark` or `paper`: the model whose training step is timed.
    model: String,
    /// `f32`, or `bf16`/`f16`: the release's mixed precision in that half type.
    precision: String,
    /// `f32`, or `bf16`/`f16`: the type products and attention compute in (`model.compute`).
    compute: String,
    /// The JAX reference script (by default the checkout's).
    reference: String,
    /// Recompute activations in the backward pass instead of keeping them (burn's gradient
    /// checkpointing), trading time for memory.
    checkpointing: bool,
}

fn parse_options() -> Options {
    let mut options = Options {
        backend: Backend::Cpu,
        shards: 0,
        steps: 5,
        warmup: 3,
        batch: 8,
        paper: true,
        jax: true,
        model: "benchmark".into(),
        precision: "f32".into(),
        compute: "f32".into(),
        reference: concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../tools/reference/xfactor_reference.py"
        )
        .into(),
        checkpointing: false,
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--backend" => {
                options.backend = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--backend cpu|wgpu|vulkan|cuda|libtorch")
            }
            "--steps" => {
                options.steps = args.next().and_then(|v| v.parse().ok()).expect("--steps N")
            }
            "--warmup" => {
                options.warmup = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--warmup N")
            }
            "--batch" => {
                options.batch = args.next().and_then(|v| v.parse().ok()).expect("--batch B")
            }
            "--shards" => {
                options.shards = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--shards N")
            }
            "--skip-paper" => options.paper = false,
            "--skip-jax" => options.jax = false,
            "--checkpointing" => options.checkpointing = true,
            "--model" => options.model = args.next().expect("--model benchmark|paper"),
            "--precision" => options.precision = args.next().expect("--precision f32|bf16|f16"),
            "--compute" => options.compute = args.next().expect("--compute f32|bf16|f16"),
            "--reference" => options.reference = args.next().expect("--reference SCRIPT.py"),
            _ => {}
        }
    }
    if options.shards == 0 {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        options.shards = default_shards(options.backend, cores);
    }
    // A shard holds at least one sample.
    options.shards = options.shards.clamp(1, options.batch.max(1));
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

/// The stage-1 L1 loss of samples `[start, start + count)`, weighted by their share of the
/// batch so shard losses add up to the batch mean.
fn stage1_loss(
    model: &XFactor,
    pair: &Tensor<5>,
    mask: &Tensor<2>,
    start: usize,
    count: usize,
) -> Tensor<1> {
    let [batch, _, h, w, c] = pair.dims();
    let pair = pair.clone().narrow(0, start, count);
    let mask = mask.clone().narrow(0, start, count);
    let poses = model.pose_enc.forward_masked(pair.clone(), mask.clone());
    let swapped = Tensor::cat(
        vec![poses.clone().narrow(2, 1, 1), poses.narrow(2, 0, 1)],
        2,
    );
    let pred = model.render.forward(
        pair.clone().narrow(1, 0, 1),
        PoseLatents::PerSegment(swapped),
        Some(mask),
    );
    let target = pair.narrow(1, 1, 1).reshape([count, h, w, c]);
    (target - pred).abs().mean() * (count as f64 / batch as f64)
}

/// One stage-1 forward and backward pass over the batch split into `shards`; returns seconds.
fn stage1_step(model: &XFactor, pair: &Tensor<5>, mask: &Tensor<2>, shards: usize) -> f64 {
    let batch = pair.dims()[0];
    let start = Instant::now();
    let (loss, grads) = sharded_gradients(model, shards, |copy, shard| {
        let begin = shard * batch / shards;
        let end = (shard + 1) * batch / shards;
        stage1_loss(copy, pair, mask, begin, end - begin)
    });
    let kernel_grad: Tensor<2> = grads
        .get(model.render.pixel_head.dense_2.kernel.id)
        .expect("gradient reaches the pixel head");
    let grad_sum = kernel_grad.abs().sum().into_scalar::<f32>();
    assert!(loss.is_finite() && grad_sum.is_finite());
    start.elapsed().as_secs_f64()
}

/// Bytes of float32 parameters and of AdamW's two moments for `params` parameters: what every
/// device holds whatever the backend reports.
fn training_bytes(params: usize) -> (usize, usize) {
    (params * 4, params * 8)
}

/// The Python that runs the JAX peer, when there is one.
fn jax_python() -> Option<std::path::PathBuf> {
    if let Some(python) = std::env::var_os("XFACTOR_JAX_PYTHON") {
        return Some(python.into());
    }
    let python = settings::cache::project_cache().join("jax-env/bin/python");
    python.exists().then_some(python)
}

/// Why the JAX peer did not run.
#[derive(Debug, thiserror::Error)]
enum PeerUnavailable {
    #[error("no JAX Python: run scripts/setup-jax.sh or set XFACTOR_JAX_PYTHON")]
    NoPython,
    #[error("the JAX peer takes one layer count for PoseEnc and Render")]
    LayerCounts,
    #[error("{python} does not start")]
    Spawn {
        python: String,
        #[source]
        source: std::io::Error,
    },
    #[error("the JAX peer failed ({status}): {last_line}")]
    Failed { status: String, last_line: String },
}

/// Runs the JAX peer on `config` at `batch` for `steps` steps; its `key=value` figures, or
/// why it did not run.
fn jax_peer(
    script: &str,
    config: &XFactorConfig,
    batch: usize,
    steps: usize,
) -> Result<String, PeerUnavailable> {
    let python = jax_python().ok_or(PeerUnavailable::NoPython)?;
    if config.pose_layers != config.render_layers {
        return Err(PeerUnavailable::LayerCounts);
    }
    let number = |value: usize| value.to_string();
    let output = std::process::Command::new(&python)
        .arg(script)
        .arg("bench")
        .args(["--batch", &number(batch), "--steps", &number(steps.max(1))])
        .args([
            "--height",
            &number(config.image_size),
            "--width",
            &number(config.image_size),
        ])
        .args([
            "--patch-size",
            &number(config.patch_size),
            "--features",
            &number(config.width),
        ])
        .args([
            "--num-heads",
            &number(config.num_heads),
            "--num-layers",
            &number(config.pose_layers),
        ])
        .args([
            "--pose-dim",
            &number(config.pose_dim),
            "--global-tokens",
            &number(config.global_tokens),
        ])
        .output()
        .map_err(|source| PeerUnavailable::Spawn {
            python: python.display().to_string(),
            source,
        })?;
    let stdout = String::from_utf8_lossy(&output.stdout);
    let figures = stdout.lines().find(|line| line.contains("jax_step_s="));
    match figures {
        Some(line) if output.status.success() => Ok(line.trim().to_string()),
        _ => Err(PeerUnavailable::Failed {
            status: output.status.to_string(),
            last_line: String::from_utf8_lossy(&output.stderr)
                .lines()
                .last()
                .unwrap_or("")
                .to_string(),
        }),
    }
}

/// The value of `key=` in a `key=value` line.
fn figure(line: &str, key: &str) -> Option<f64> {
    line.split_whitespace()
        .find_map(|pair| pair.strip_prefix(key)?.strip_prefix('=')?.parse().ok())
}

/// `f32`, `bf16` or `f16`, as `flag` spelled it.
fn float_type(flag: &str, value: &str) -> Precision {
    match value {
        "f32" => Precision::F32,
        "bf16" => Precision::Bf16,
        "f16" => Precision::F16,
        other => panic!("{flag} {other}: expected f32, bf16 or f16"),
    }
}

/// The model the options ask for, at their precision (the release's mixed precision: its
/// rounding points in the half type, float32 weights) and compute type.
fn model_config(options: &Options) -> (XFactorConfig, Precision) {
    let config = match options.model.as_str() {
        "benchmark" => XFactorConfig::benchmark(),
        "paper" => XFactorConfig::paper(),
        other => panic!("--model {other}: expected benchmark or paper"),
    };
    let precision = float_type("--precision", &options.precision);
    (
        XFactorConfig {
            precision,
            compute: float_type("--compute", &options.compute),
            ..config
        },
        precision,
    )
}

/// The JAX peer's figures for the same step, and our step time over theirs.
fn jax_figures(options: &Options, config: &XFactorConfig, step_s: f64) -> String {
    match jax_peer(&options.reference, config, options.batch, options.steps) {
        Ok(figures) => match figure(&figures, "jax_step_s") {
            Some(theirs) => format!(" {figures} vs_jax={:.2}", step_s / theirs),
            None => format!(" {figures}"),
        },
        Err(why) => {
            eprintln!("jax: {why}");
            " vs_jax=unavailable".into()
        }
    }
}

/// The paper model's size, build time and one batch-1 forward pass on `device`.
fn paper_figures(device: &Device) -> String {
    let paper = XFactorConfig::paper();
    let start = Instant::now();
    let big = XFactor::new(&paper, 0, device).expect("paper config is valid");
    let build_s = start.elapsed().as_secs_f64();
    let side = paper.image_size;
    let pair = uniform([1, 2, side, side, 3], 2, device);
    let start = Instant::now();
    let poses = big.pose_enc.forward(pair.clone());
    let image = big
        .render
        .forward(pair.narrow(1, 0, 1), PoseLatents::Single(poses), None);
    let checksum = image.sum().into_scalar::<f32>();
    let forward_s = start.elapsed().as_secs_f64();
    assert!(checksum.is_finite());
    let (param_bytes, optimizer_bytes) = training_bytes(big.num_params());
    format!(
        " paper_params={} paper_param_bytes={param_bytes} paper_optimizer_bytes={optimizer_bytes} paper_build_s={build_s:.2} paper_forward_b1_s={forward_s:.2}",
        big.num_params()
    )
}

fn main() {
    let options = parse_options();
    let tuning = allocator::keep_freed_memory();
    let (config, precision) = model_config(&options);
    let inference = match options.backend.device() {
        Ok(device) => device,
        Err(error) => {
            println!("backend={} unavailable=\"{error}\"", options.backend);
            std::process::exit(2);
        }
    };
    let device = if options.checkpointing {
        inference.clone().autodiff().gradient_checkpointing()
    } else {
        inference.clone().autodiff()
    };
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "config: backend={} threads={threads} shards={} allocator_tuned={} batch={} image={} patch={} width={} heads={} layers={}+{} pose_dim={} global_tokens={} steps={}",
        options.backend.name(),
        options.shards,
        tuning.heap_for_large_blocks && tuning.keep_freed_top,
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

    let (warmups, mut steps, kernels) = timed_steps(&options, &model, &pair, &mask);
    steps.sort_by(f64::total_cmp);
    let step_s = steps[steps.len() / 2];
    let (warmup, warmup_last) = (warmups[0], warmups[warmups.len() - 1]);
    let (param_bytes, optimizer_bytes) = training_bytes(model.num_params());
    let mut line = format!(
        "backend={} model={} precision={} compute={} batch={} shards={} params={} param_bytes={param_bytes} optimizer_bytes={optimizer_bytes} warmup_steps={} warmup_step_s={warmup:.3} warmup_last_step_s={warmup_last:.3} step_s={step_s:.3} min_step_s={:.3} pairs_per_s={:.2} checkpointing={}",
        options.backend.name(),
        options.model,
        precision.name(),
        config.compute.name(),
        options.batch,
        options.shards,
        model.num_params(),
        warmups.len(),
        steps[0],
        options.batch as f64 / step_s,
        if options.checkpointing { "on" } else { "off" }
    );
    // Launches of cubecl's runtimes in one step (none on the CPU backend and libtorch).
    if kernels.total() > 0 {
        line.push_str(&kernel_figures(&kernels, || {
            stage1_step(&model, &pair, &mask, options.shards)
        }));
    }
    // After the steps, before the paper model is built: what this step's model and batch hold
    // (the pools keep the pages they reserved, so theirs is the step's high-water mark).
    line.push_str(&MemoryFigures::read(&inference).key_values());
    if options.jax {
        line.push_str(&jax_figures(&options, &config, step_s));
    }
    if options.paper {
        line.push_str(&paper_figures(&inference));
    }
    println!("{line}");
}

/// The warm-up steps' seconds, the timed steps' seconds and the kernels of the first timed
/// step. On a GPU the first steps compile and autotune their kernels for minutes: each step's
/// time goes to stderr as it ends, so a run cut short still says where it was.
fn timed_steps(
    options: &Options,
    model: &XFactor,
    pair: &Tensor<5>,
    mask: &Tensor<2>,
) -> (Vec<f64>, Vec<f64>, trainer_core::backend::KernelCounts) {
    let started = Instant::now();
    let step = |phase: &str, index: usize| {
        let seconds = stage1_step(model, pair, mask, options.shards);
        eprintln!(
            "progress phase={phase} step={index} step_s={seconds:.3} elapsed_s={:.1}",
            started.elapsed().as_secs_f64()
        );
        seconds
    };
    let warmups: Vec<f64> = (0..options.warmup.max(1))
        .map(|index| step("warmup", index))
        .collect();
    let (counted, kernels) = count_kernels(|| step("timed", 0));
    let steps: Vec<f64> = std::iter::once(counted)
        .chain((1..options.steps).map(|index| step("timed", index)))
        .collect();
    (warmups, steps, kernels)
}

/// The kernels of one step (`kernels`), then one more step (`step`, returning its seconds)
/// with every kernel timed on the device, as `key=value` figures.
fn kernel_figures(
    kernels: &trainer_core::backend::KernelCounts,
    step: impl FnOnce() -> f64,
) -> String {
    let (profiled, time) = time_kernels(step);
    format!(
        " kernels_per_step={} kernel_kinds={} top_kernels={} profiled_step_s={profiled:.3} kernel_device_s={:.3} kernel_span_s={:.3} kernels_timed={} kernel_timing={} device_share={:.2} device_ms_by_kind={}",
        kernels.total(),
        kernels.kinds.len(),
        kernels.top(6),
        time.device_s,
        time.span_s,
        time.timed,
        time.method(),
        time.device_s / profiled.max(1e-9),
        time.top(10)
    )
}
