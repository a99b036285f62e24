//! The parameter checksum at the paper model's size (305M float32 values, 1.22 GB): the
//! CRC-32 fed four bytes at a time (how `parameter_checksum` hashed until issue 40) beside
//! the bulk hash over the cores it does now, and the read of every parameter to the host
//! alone (one tensor at a time, nothing hashed) for the floor. It prints the checksum's share of JAX's H200 step
//! (0.47 s) and the interval that keeps it under 2% of the steps.
//!
//! `cargo bench -p trainer-core --bench checksum [-- --model paper|benchmark --repeats N]`

use std::time::Instant;

use settings::XFactorConfig;
use trainer_core::flat::parameter_checksum;
use trainer_core::standin::{LayoutModel, layout_of};

/// JAX's stage-1 step of the paper model on one H200 at batch 64 (SPEC, the figure).
const JAX_STEP_S: f64 = 0.47;

fn flag(args: &[String], name: &str, default: &str) -> String {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .cloned()
        .unwrap_or_else(|| default.into())
}

/// The fastest of `repeats` runs of `work`, and its result.
fn fastest<T>(repeats: usize, mut work: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut result = None;
    for _ in 0..repeats.max(1) {
        let started = Instant::now();
        let value = work();
        best = best.min(started.elapsed().as_secs_f64());
        result = Some(value);
    }
    (best, result.expect("at least one run"))
}

fn main() {
    trainer_core::allocator::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let model = flag(&args, "--model", "paper");
    let repeats: usize = flag(&args, "--repeats", "3").parse().expect("--repeats N");
    let config = match model.as_str() {
        "paper" => XFactorConfig::paper(),
        "benchmark" => XFactorConfig::benchmark(),
        other => panic!("--model {other}: expected paper or benchmark"),
    };
    let layout = layout_of(&config).expect("a valid model");
    let standin = LayoutModel::scaled(&layout, 1.0, &trainer_core::Device::flex());
    let module = standin.parameters();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (read_s, bytes) = fastest(repeats, || {
        module
            .iter()
            .map(|param| param.val().into_data().as_bytes().len())
            .sum::<usize>()
    });
    let (by_value_s, by_value) = fastest(1, || {
        let mut hasher = crc32fast::Hasher::new();
        for param in module {
            for value in param.val().into_data().iter::<f32>() {
                hasher.update(&value.to_le_bytes());
            }
        }
        hasher.finalize()
    });
    let (checksum_s, bulk) = fastest(repeats, || parameter_checksum(module));
    assert_eq!(
        by_value, bulk,
        "both ways of hashing give the same checksum"
    );
    let share = checksum_s / JAX_STEP_S;
    let every_for_2pct = (share / 0.02).ceil().max(1.0);
    println!(
        "bench=checksum model={model} params={} bytes={bytes} threads={threads} repeats={repeats} \
         value_by_value_s={by_value_s:.3} read_only_s={read_s:.3} checksum_s={checksum_s:.3} \
         checksum_gbs={:.2} speedup={:.1} share_of_jax_step={share:.3} \
         every_for_2pct={every_for_2pct}",
        bytes / 4,
        bytes as f64 / 1e9 / checksum_s,
        by_value_s / checksum_s,
    );
}
