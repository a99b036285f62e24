//! One attention's forward and backward pass, the model's fused op (`SoftmaxAttention`: one
//! autodiff node that keeps q, k, v and recomputes the weights in its backward pass) against
//! the op-by-op attention burn's autodiff differentiates (it keeps the scores and weights), in
//! the same run on the same device.
//!
//! `cargo bench -p trainer-core --bench attention_step -- [--backend cpu|wgpu|vulkan|cuda]
//! [--batch 8] [--heads 16] [--tokens 640] [--head-dim 64] [--steps 3] [--unmasked]`
//!
//! The defaults are the paper model's pose-encoder global attention at batch 8: 16 heads of
//! 64, two views of 256 patches and 2 x 32 global tokens, and a `(batch, 1, N, N)` segment
//! mask (two segments; the model's own masks have the same shape). Per variant it prints the
//! median step time, the memory the forward pass leaves for the backward pass (resident host
//! memory on the CPU backend and lavapipe, the pools' live bytes on cubecl devices) and the
//! peak resident memory of the step.

use std::time::Instant;

use burn::tensor::{Device, Tensor};
use trainer_core::backend::{Backend, BackendDevices, MemoryFigures};
use trainer_core::model::{op_by_op_attention, segment_bias, softmax_attention};

struct Options {
    backend: Backend,
    batch: usize,
    heads: usize,
    tokens: usize,
    head_dim: usize,
    steps: usize,
    masked: bool,
}

fn parse_options() -> Options {
    let mut options = Options {
        backend: Backend::Cpu,
        batch: 8,
        heads: 16,
        tokens: 640,
        head_dim: 64,
        steps: 3,
        masked: true,
    };
    let mut args = std::env::args().skip(1);
    let number = |args: &mut dyn Iterator<Item = String>, name: &str| -> usize {
        args.next()
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{name} takes a positive number"))
    };
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--backend" => {
                options.backend = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--backend cpu|wgpu|vulkan|cuda|libtorch")
            }
            "--batch" => options.batch = number(&mut args, "--batch"),
            "--heads" => options.heads = number(&mut args, "--heads"),
            "--tokens" => options.tokens = number(&mut args, "--tokens"),
            "--head-dim" => options.head_dim = number(&mut args, "--head-dim"),
            "--steps" => options.steps = number(&mut args, "--steps"),
            "--unmasked" => options.masked = false,
            _ => {}
        }
    }
    options
}

/// The model's segment bias for two segments, the first and second half of the tokens.
fn two_segments(batch: usize, tokens: usize, device: &Device) -> Tensor<4> {
    let ids: Vec<f32> = (0..tokens).map(|i| (2 * i / tokens) as f32).collect();
    let ids = Tensor::<1>::from_floats(ids.as_slice(), device);
    segment_bias(ids.reshape([1, tokens]).expand([batch, tokens]))
}

type Attention = fn(Tensor<4>, Tensor<4>, Tensor<4>, Option<&Tensor<4>>) -> Tensor<4>;

/// Resets the process's peak resident memory (`VmHWM`), so each variant's peak is its own.
fn reset_peak_resident() {
    // Linux only; elsewhere the peak stays the process's and the printed figure says so.
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Steps of one variant; prints its figures and returns its median step time.
fn run_variant(name: &str, attend: Attention, options: &Options, device: &Device) -> f64 {
    let shape = [
        options.batch,
        options.heads,
        options.tokens,
        options.head_dim,
    ];
    // Deterministic inputs in [-1, 1], a different pattern for each of q, k, v and the loss.
    let draw = |seed: usize| {
        let count = shape.iter().product::<usize>();
        let values: Vec<f32> = (0..count)
            .map(|i| ((i * 7 + seed * 13) as f32 * 0.618_034).sin())
            .collect();
        Tensor::<4>::from_data(burn::tensor::TensorData::new(values, shape), device)
    };
    let bias = options
        .masked
        .then(|| two_segments(options.batch, options.tokens, device));
    let weights = draw(3);
    let inference = device.clone().inner();
    reset_peak_resident();
    let mut times = Vec::new();
    let mut retained = (0i64, 0i64);
    for step in 0..=options.steps {
        let (q, k, v) = (draw(0), draw(1), draw(2));
        let (q, k, v) = (q.require_grad(), k.require_grad(), v.require_grad());
        let _ = weights.clone().sum().into_scalar::<f32>();
        let before = MemoryFigures::read(&inference);
        let start = Instant::now();
        let out = attend(q.clone(), k.clone(), v.clone(), bias.as_ref());
        let _ = out.clone().sum().into_scalar::<f32>();
        let after_forward = MemoryFigures::read(&inference);
        let grads = (out * weights.clone()).sum().backward();
        let _ = q.grad(&grads).map(|g| g.sum().into_scalar::<f32>());
        let elapsed = start.elapsed().as_secs_f64();
        // The first step compiles kernels and tunes them on cubecl devices: not timed.
        if step > 0 {
            times.push(elapsed);
            let delta =
                |a: Option<u64>, b: Option<u64>| a.zip(b).map_or(0, |(a, b)| a as i64 - b as i64);
            retained = (
                delta(after_forward.host_resident, before.host_resident),
                delta(after_forward.pool_in_use, before.pool_in_use),
            );
        }
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    let peak = MemoryFigures::read(&inference)
        .host_peak_resident
        .unwrap_or(0);
    println!(
        "variant={name} step_s={median:.4} kept_for_backward_host_bytes={} kept_for_backward_pool_bytes={} peak_resident_bytes={peak}",
        retained.0, retained.1
    );
    median
}

fn main() {
    let options = parse_options();
    let device = match options.backend.device() {
        Ok(device) => device.autodiff(),
        Err(error) => {
            println!("backend={} unavailable=\"{error}\"", options.backend);
            std::process::exit(2);
        }
    };
    println!(
        "config: backend={} batch={} heads={} tokens={} head_dim={} masked={} steps={}",
        options.backend.name(),
        options.batch,
        options.heads,
        options.tokens,
        options.head_dim,
        options.masked,
        options.steps
    );
    let op_by_op = run_variant("op_by_op", op_by_op_attention, &options, &device);
    let fused = run_variant("fused", softmax_attention, &options, &device);
    println!(
        "backend={} fused_step_s={fused:.4} op_by_op_step_s={op_by_op:.4} fused_speedup={:.2}",
        options.backend.name(),
        op_by_op / fused
    );
}
