//! One rank of the data-path benchmark: the worker's whole step ([`DataPath`]: flatten, local
//! reduction, ring, AdamW update, checksum) on a model's parameter layout, with the forward
//! and backward pass replaced by a wait of `--compute-s` (JAX's H200 step of the paper model
//! by default). Rank 0 prints one `key=value` line of medians over the timed steps.

use std::time::{Duration, Instant};

use data::{BatchSource, SampleError, Samples};
use settings::XFactorConfig;
use settings::work::WireFormat;
use trainer_core::standin::{LayoutModel, layout_of};
use trainer_core::trainer::{SliceLoss, StepMetrics};

use super::RankArgs;
use crate::datapath::{
    Applied, ChecksumPlan, Computed, DataPath, ReplicaError, ReplicaModel, StepFigures,
};
use crate::progress::Progress;

/// The flags of `xfactor-worker path-bench`.
#[derive(Debug, Clone, clap::Args)]
pub struct PathBenchArgs {
    /// Its place in the ring
    #[command(flatten)]
    pub ring: RankArgs,
    /// The model whose parameter layout is stepped: paper or benchmark
    #[arg(long, value_name = "NAME", default_value = "paper")]
    pub model: String,
    /// Fraction of every tensor's elements kept (the payload scaled down)
    #[arg(long, value_name = "F", default_value_t = 1.0)]
    pub scale: f64,
    /// Seconds each replica waits in place of its forward and backward pass
    #[arg(long, value_name = "S", default_value_t = 0.47)]
    pub compute_s: f64,
    /// Timed steps (after one untimed warm-up step)
    #[arg(long, value_name = "N", default_value_t = 4)]
    pub steps: usize,
    /// Replicas of this worker (they share the CPU device)
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub replicas: usize,
    /// How the ring carries the gradients
    #[arg(long, value_name = "f32|bf16", default_value = "f32", value_parser = parse_wire)]
    pub wire: WireFormat,
    /// A parameter checksum every this many steps (the benchmark checks every step unless
    /// told otherwise, so its figures include the checksum)
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub checksum_every: u64,
    /// Values per collective chunk (by default the ring's)
    #[arg(long, value_name = "N")]
    pub chunk_values: Option<usize>,
    /// The model's layout (elements per tensor, one per line): read from this file when it
    /// exists, else built from the model and written there, so that ranks started later do
    /// not each build the model
    #[arg(long, value_name = "PATH")]
    pub layout_file: Option<std::path::PathBuf>,
}

/// `f32` or `bf16`, as the cluster YAML names them.
fn parse_wire(text: &str) -> Result<WireFormat, serde_json::Error> {
    serde_json::from_value(serde_json::Value::String(text.into()))
}

/// A replica whose compute is a wait and whose parameters are a [`LayoutModel`].
struct WaitingReplica {
    model: LayoutModel,
    compute: Duration,
    step: u64,
}

impl ReplicaModel for WaitingReplica {
    fn step(&self) -> u64 {
        self.step
    }

    fn parameter_count(&self) -> usize {
        self.model.parameter_count()
    }

    fn gradients_into(
        &self,
        _: &dyn BatchSource,
        out: &mut [f32],
    ) -> Result<Computed, ReplicaError> {
        std::thread::sleep(self.compute);
        let grads = self.model.backward();
        let copying = Instant::now();
        self.model.gradients_into(grads, out)?;
        Ok(Computed {
            loss: SliceLoss {
                total: 0.25,
                l1: 0.25,
                lpips: f32::NAN,
            },
            copy_s: copying.elapsed().as_secs_f64(),
        })
    }

    fn apply(&mut self, sum: &[f32], loss: f32) -> Result<Applied, ReplicaError> {
        let learning_rate = 1e-4;
        let uploading = Instant::now();
        let grads = self.model.upload(sum)?;
        let upload_s = uploading.elapsed().as_secs_f64();
        let report = self.model.update(&grads, learning_rate);
        self.step += 1;
        Ok(Applied {
            metrics: StepMetrics {
                step: self.step - 1,
                loss,
                learning_rate,
                grad_norm: report.grad_norm,
                applied: report.applied,
            },
            upload_s,
        })
    }

    fn checksum(&self) -> u32 {
        self.model.checksum()
    }
}

/// The benchmark's replicas read no data: every request is answered with no samples.
struct NoData;

impl BatchSource for NoData {
    fn samples(&self, _: u64, _: u64, _: usize) -> Result<Samples, SampleError> {
        Ok(Samples::Pairs(Vec::new()))
    }
}

/// Runs one rank; rank 0 prints the figures.
pub fn run_rank(args: &PathBenchArgs) -> anyhow::Result<()> {
    let config = match args.model.as_str() {
        "paper" => XFactorConfig::paper(),
        "benchmark" => XFactorConfig::benchmark(),
        other => anyhow::bail!("--model {other}: expected paper or benchmark"),
    };
    if !(args.scale > 0.0 && args.scale <= 1.0) {
        anyhow::bail!("--scale {}: expected a fraction in (0, 1]", args.scale);
    }
    let runtime = args.ring.runtime()?;
    let layout = layout(&config, args.layout_file.as_deref())?;
    let device = trainer_core::Device::flex();
    let mut replicas: Vec<WaitingReplica> = (0..args.replicas.max(1))
        .map(|_| WaitingReplica {
            model: LayoutModel::scaled(&layout, args.scale, &device),
            compute: Duration::from_secs_f64(args.compute_s.max(0.0)),
            step: 0,
        })
        .collect();
    let place = args.ring.clone();
    let mut ring = runtime.block_on(async move { place.join().await })?;
    if let Some(values) = args.chunk_values {
        ring.set_chunk_values(values);
    }
    let plan = ChecksumPlan {
        every: settings::work::ChecksumEvery::Steps(args.checksum_every),
        commit_every: u64::MAX,
        total_steps: u64::MAX,
    };
    let mut path = DataPath::new(ring.with_wire(args.wire), plan, None);
    let progress = Progress::new();
    let mut steps = Vec::new();
    for step in 0..=args.steps {
        let started = Instant::now();
        let figures = path.step(&runtime, &mut replicas, &NoData, &progress)?;
        if step > 0 {
            steps.push((started.elapsed().as_secs_f64(), figures));
        }
    }
    if args.ring.rank == 0 {
        let parameters = replicas[0].model.parameter_count();
        let unscaled: usize = layout.iter().sum();
        println!(
            "bench=data_path {}",
            summary(args, parameters, unscaled, &steps)
        );
    }
    // Let the peers finish reading before the streams close.
    std::thread::sleep(Duration::from_millis(300));
    Ok(())
}

/// The layout of `config`'s model, through `file` when one is given (see `--layout-file`).
fn layout(config: &XFactorConfig, file: Option<&std::path::Path>) -> anyhow::Result<Vec<usize>> {
    use anyhow::Context;
    if let Some(path) = file.filter(|path| path.exists()) {
        let text = std::fs::read_to_string(path).with_context(|| path.display().to_string())?;
        return text
            .lines()
            .map(|line| {
                line.trim()
                    .parse::<usize>()
                    .with_context(|| format!("{}: {line:?} is not a tensor size", path.display()))
            })
            .collect();
    }
    let layout = layout_of(config)?;
    if let Some(path) = file {
        // Written aside and renamed, so a rank never reads half a file.
        let aside = path.with_extension(format!("{}.part", std::process::id()));
        let text: String = layout.iter().map(|size| format!("{size}\n")).collect();
        std::fs::write(&aside, text).with_context(|| aside.display().to_string())?;
        std::fs::rename(&aside, path).with_context(|| path.display().to_string())?;
    }
    Ok(layout)
}

/// The figures' line: the configuration, then the median of each phase over the steps. The
/// host path is every phase but the optimizer's arithmetic (the device's work on a GPU, the
/// CPU's here): the copy to the host, the local reduction, the ring, the upload and the
/// checksum. A job checks its parameters every `auto` steps of the unscaled model
/// (`unscaled` values) by default, so the step and the host path are also given with the
/// checksum spread over that many steps.
fn summary(
    args: &PathBenchArgs,
    parameters: usize,
    unscaled: usize,
    steps: &[(f64, StepFigures)],
) -> String {
    let median = |of: &dyn Fn(&(f64, StepFigures)) -> f64| {
        let mut values: Vec<f64> = steps.iter().map(of).collect();
        values.sort_by(f64::total_cmp);
        values.get(values.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let step_s = median(&|(seconds, _)| *seconds);
    let phases = |pick: fn(&StepFigures) -> f64| median(&|(_, figures)| pick(figures));
    let copy_s = phases(|f| f.phases.copy_s);
    let local_reduce_s = phases(|f| f.phases.local_reduce_s);
    let ring_s = phases(|f| f.phases.ring_s);
    let upload_s = phases(|f| f.phases.upload_s);
    let update_s = phases(|f| f.phases.apply_s - f.phases.upload_s);
    let checksum_s = phases(|f| f.phases.checksum_s);
    let host_path_s = phases(|f| {
        let p = &f.phases;
        p.copy_s + p.local_reduce_s + p.ring_s + p.upload_s + p.checksum_s
    });
    let auto_every = settings::work::ChecksumEvery::Auto.steps(unscaled);
    let spread_checksum = |seconds: f64| seconds - checksum_s + checksum_s / auto_every as f64;
    let host_path_auto_s = spread_checksum(host_path_s);
    let step_auto_s = spread_checksum(step_s);
    let bytes = parameters as f64 * 4.0;
    let gb = |seconds: f64| bytes / 1e9 / seconds.max(1e-12);
    format!(
        "ranks={} model={} scale={} replicas={} wire={} lanes={} tls={} params={parameters} payload_mb={:.3} \
         compute_s={:.3} steps={} step_s={step_s:.4} copy_s={copy_s:.4} copy_gbs={:.2} \
         local_reduce_s={local_reduce_s:.4} ring_s={ring_s:.4} ring_algbw_gbs={:.3} \
         upload_s={upload_s:.4} upload_gbs={:.2} update_s={update_s:.4} \
         checksum_s={checksum_s:.4} checksum_gbs={:.2} host_path_s={host_path_s:.4} \
         checksum_every_auto={auto_every} host_path_auto_s={host_path_auto_s:.4} \
         step_auto_s={step_auto_s:.4} efficiency={:.4} efficiency_auto={:.4}",
        args.ring.peers.len(),
        args.model,
        args.scale,
        args.replicas,
        args.wire.name(),
        args.ring.lanes,
        args.ring.tls_dir.is_some(),
        bytes / 1e6,
        args.compute_s,
        steps.len(),
        gb(copy_s),
        gb(ring_s),
        gb(upload_s),
        gb(checksum_s),
        args.compute_s / step_s,
        args.compute_s / step_auto_s,
    )
}
