//! `xfactor-local`: the whole system on one machine: generates a small RE10K-layout dataset,
//! writes its cluster YAML, and runs a coordinator and worker processes on loopback through
//! both stages.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::Child;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use coordinator::config::ModelPreset;
use coordinator::local::watch::{Ended, failure_reason, watch};
use coordinator::local::{LocalJob, figures, free_port};
use coordinator::progress;
use proto::v1::StatusRequest;
use proto::v1::coordinator_client::CoordinatorClient;
use settings::DeviceChoice;
use settings::objective::ObjectiveVariant;
use settings::work::WireFormat;
use telemetry::logging::LogArgs;

/// Folder of the run when `--dir` is not given.
const DEFAULT_DIR: &str = "xfactor-local-run";

/// The local job's settings before any flag, whose values `--help` shows as defaults.
fn defaults() -> LocalJob {
    LocalJob::demo(Path::new(DEFAULT_DIR), 0)
}

/// `f32` or `bf16`, as the YAML's `workers.allreduce_wire` reads it.
fn wire_format(name: &str) -> Result<WireFormat, serde_norway::Error> {
    serde_norway::from_str(name)
}

/// A `--stage1-peak-lr` that is not a learning rate.
#[derive(Debug, thiserror::Error)]
#[error("`{0}` is not a learning rate above 0")]
struct NotARate(String);

/// A learning rate: a finite number above 0.
fn positive_rate(text: &str) -> Result<f64, NotARate> {
    match text.parse::<f64>() {
        Ok(rate) if rate.is_finite() && rate > 0.0 => Ok(rate),
        _ => Err(NotARate(text.to_string())),
    }
}

/// `transfer`, `autoencode`, ...: an objective variant as the YAML's `objective.variant` reads it.
fn objective_variant(name: &str) -> Result<ObjectiveVariant, serde_norway::Error> {
    serde_norway::from_str(name)
}

/// A count that must be at least one (workers, pixels): refused by clap, naming the flag, before
/// any data is generated (the coordinator would refuse the YAML only after that).
fn at_least_one_usize() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::<usize>::new().range(1..)
}

/// Checks a `--preset` against the cluster YAML's `model.preset` names.
fn preset_name(name: &str) -> Result<String, serde_norway::Error> {
    serde_norway::from_str::<ModelPreset>(name).map(|_| name.to_string())
}

/// Runs the whole system on one machine: generates a small RE10K-layout dataset, writes its
/// cluster YAML, and runs a coordinator and worker processes on loopback through both stages.
#[derive(Debug, Parser)]
#[command(
    name = "xfactor-local",
    version = telemetry::VERSION,
    // A flag given twice takes its last value, so scripts append overrides to a recipe's flags.
    args_override_self = true,
    after_help = "Examples:
  the README's first run (two CPU workers on generated data, then the evaluation):
    xfactor-local
  longer, in another folder:
    xfactor-local --dir my-run --stage1-steps 2000 --stage2-steps 500"
)]
struct Cli {
    /// Folder for the data, the YAML, the logs, the checkpoints and the report
    #[arg(long, value_name = "DIR", default_value = DEFAULT_DIR)]
    dir: PathBuf,
    /// Worker processes
    #[arg(long, value_name = "N", default_value_t = defaults().workers, value_parser = at_least_one_usize())]
    workers: usize,
    /// Steps of stage 1
    #[arg(long, value_name = "N", default_value_t = defaults().stage1_steps, value_parser = clap::value_parser!(u64).range(1..))]
    stage1_steps: u64,
    /// Steps stage 1's learning-rate cosine and window curriculum span (by default its steps):
    /// more trains the first --stage1-steps of a longer schedule, step for step as its full run
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    stage1_schedule_steps: Option<u64>,
    /// Steps of stage 2
    #[arg(long, value_name = "N", default_value_t = defaults().stage2_steps, value_parser = clap::value_parser!(u64).range(1..))]
    stage2_steps: u64,
    /// Train stage 1 alone and evaluate its final weights (the checkpoint the paper's Table 3
    /// compares); stage 2's settings are written to the YAML but not trained
    #[arg(long)]
    stage1_only: bool,
    /// Model preset: tiny, small (the transfer recipe's), benchmark or paper
    #[arg(long, value_name = "PRESET", default_value_t = defaults().preset, value_parser = preset_name)]
    preset: String,
    /// Generated training scenes (each rendered along every camera path)
    #[arg(long, value_name = "N", default_value_t = defaults().scenes, value_parser = clap::value_parser!(u64).range(1..))]
    scenes: u64,
    /// Generated camera paths per scene
    #[arg(long, value_name = "N", default_value_t = defaults().trajectories, value_parser = clap::value_parser!(u64).range(1..))]
    paths: u64,
    /// Seed of the data, the training and the evaluation's scenes
    #[arg(long, value_name = "N", default_value_t = defaults().seed)]
    seed: u64,
    /// Peak learning rate of stage 1's warm-up and cosine schedule
    #[arg(long, value_name = "LR", default_value_t = defaults().stage1_peak_lr, value_parser = positive_rate)]
    stage1_peak_lr: f64,
    /// Objective of both stages, as the YAML's `objective.variant` (the paper's Table 3):
    /// transfer (XFactor's), autoencode, se3_plucker, extra_view_decoder or
    /// extra_view_encoder_decoder (the last two in stage 1 only)
    #[arg(long, value_name = "VARIANT", default_value = "transfer", value_parser = objective_variant)]
    variant: ObjectiveVariant,
    /// Pose-latent size instead of the preset's (Table 3's "bottleneck": autoencode through a
    /// smaller one)
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    pose_dim: Option<u64>,
    /// Held-out scenes the evaluation generates; the last quarter test the pose probe, the rest
    /// train it (the transfer recipe's: 64)
    #[arg(long, value_name = "N", default_value_t = defaults().evaluation.scenes, value_parser = clap::value_parser!(u64).range(4..))]
    evaluation_scenes: u64,
    /// Steps of the evaluation's pose probe (the paper's: 10000; the first run's: 1000)
    #[arg(long, value_name = "N", default_value_t = defaults().evaluation.probe_steps as u64, value_parser = clap::value_parser!(u64).range(1..))]
    probe_steps: u64,
    /// Width of the evaluation's pose probe (the paper's: 256; the first run's: 64)
    #[arg(long, value_name = "N", default_value_t = defaults().evaluation.probe_width as u64, value_parser = clap::value_parser!(u64).range(1..))]
    probe_width: u64,
    /// Training resolution in pixels
    #[arg(long, value_name = "PX", default_value_t = defaults().image_size, value_parser = at_least_one_usize())]
    image_size: usize,
    /// Samples per step over all workers
    #[arg(long, value_name = "N", default_value_t = defaults().global_batch, value_parser = clap::value_parser!(u64).range(1..))]
    global_batch: u64,
    /// Samples per forward pass
    #[arg(long, value_name = "N", default_value_t = defaults().micro_batch, value_parser = clap::value_parser!(u64).range(1..))]
    micro_batch: u64,
    /// Commit a checkpoint every N steps
    #[arg(long, value_name = "N", default_value_t = defaults().checkpoint_every, value_parser = clap::value_parser!(u64).range(1..))]
    checkpoint_every: u64,
    /// Device of every worker: cpu, wgpu, vulkan, cuda, libtorch or auto (the GPU roads need a
    /// worker built with their feature, beside this binary)
    #[arg(long, value_name = "DEVICE", default_value = "cpu")]
    device: DeviceChoice,
    /// How the ring carries gradients: f32, or bf16 (half the bytes, summed in float32)
    #[arg(long, value_name = "WIRE", default_value = "f32", value_parser = wire_format)]
    allreduce_wire: WireFormat,
    /// Skips the evaluation stage
    #[arg(long)]
    no_evaluate: bool,
    /// Only writes the dataset and DIR/cluster.yaml (for another launcher, e.g. Slurm), then exits
    #[arg(long)]
    prepare_only: bool,
    /// The coordinator's port (by default a free one)
    #[arg(long, value_name = "PORT")]
    port: Option<u16>,
    /// The port of the coordinator's status page and /metrics (by default a free one)
    #[arg(long, value_name = "PORT")]
    status_port: Option<u16>,
    /// The host the coordinator listens on (0.0.0.0 for workers on other hosts)
    #[arg(long, value_name = "HOST", default_value = "127.0.0.1")]
    listen_host: String,
    #[command(flatten)]
    log: LogArgs,
}

/// The run's sizes from the flags: workers, steps, batch, model, data, schedule, evaluation.
fn size_run(job: &mut LocalJob, cli: &Cli) -> anyhow::Result<()> {
    if let Some(span) = cli
        .stage1_schedule_steps
        .filter(|span| *span < cli.stage1_steps)
    {
        anyhow::bail!(
            "--stage1-schedule-steps {span} is shorter than --stage1-steps {}: a schedule spans at least the steps it trains",
            cli.stage1_steps
        );
    }
    job.workers = cli.workers;
    job.stage1_steps = cli.stage1_steps;
    job.stage1_schedule_steps = cli.stage1_schedule_steps;
    job.stage2_steps = cli.stage2_steps;
    job.stage1_only = cli.stage1_only;
    job.global_batch = cli.global_batch;
    job.micro_batch = cli.micro_batch;
    job.checkpoint_every = cli.checkpoint_every;
    job.image_size = cli.image_size;
    job.evaluate = !cli.no_evaluate;
    job.preset = cli.preset.clone();
    job.scenes = cli.scenes;
    job.trajectories = cli.paths;
    job.seed = cli.seed;
    job.stage1_peak_lr = cli.stage1_peak_lr;
    job.objective_variant = (cli.variant != ObjectiveVariant::Transfer).then_some(cli.variant);
    job.pose_dim = cli.pose_dim.map(usize::try_from).transpose()?;
    job.evaluation.scenes = cli.evaluation_scenes;
    job.evaluation.probe_test_scenes = cli.evaluation_scenes / 4;
    job.evaluation.probe_steps = usize::try_from(cli.probe_steps)?;
    job.evaluation.probe_width = usize::try_from(cli.probe_width)?;
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    cli.log.init()?;
    let dir = cli.dir.clone();
    let port = match cli.port {
        Some(port) => port,
        None => free_port()?,
    };
    let mut job = LocalJob::demo(&dir, port);
    size_run(&mut job, &cli)?;
    job.listen_host = cli.listen_host;
    job.coordinator_metrics_port = Some(match cli.status_port {
        Some(port) => port,
        None => free_port()?,
    });
    job.device = cli.device;
    job.allreduce_wire = cli.allreduce_wire;
    if job.checkpoint_dir().exists() {
        std::fs::remove_dir_all(job.checkpoint_dir())?;
    }
    let runtime = tokio::runtime::Runtime::new()?;
    runtime.block_on(job.prepare())?;
    if cli.prepare_only {
        println!("{}", job.config_path().display());
        return Ok(());
    }
    let binaries = std::env::current_exe()?
        .parent()
        .context("the binary has no folder")?
        .to_path_buf();
    let started = Instant::now();
    let mut coordinator = job.spawn_coordinator(&binaries)?;
    let mut workers = (0..job.workers)
        .map(|i| job.spawn_worker(&binaries, i))
        .collect::<anyhow::Result<Vec<_>>>()?;
    tracing::info!(
        dir = %dir.display(),
        workers = job.workers,
        "coordinator and workers started; logs in coordinator.log and worker-*.log"
    );
    if let Some(port) = job.coordinator_metrics_port {
        tracing::info!(token = job.token(), "status page: http://127.0.0.1:{port}/");
    }
    let done = Arc::new(AtomicBool::new(false));
    let bar = std::io::stderr()
        .is_terminal()
        .then(|| runtime.spawn(draw_progress(job.clone(), started, Arc::clone(&done))));
    let ended = watch(&mut coordinator, &mut workers, Duration::from_millis(250))?;
    done.store(true, Ordering::SeqCst);
    if let Some(bar) = bar {
        let _ = runtime.block_on(bar);
    }
    let status = match ended {
        Ended::Coordinator(status) => status,
        Ended::WorkerFailed { index, status } => {
            stop(&mut coordinator, &mut workers);
            return Err(worker_failed(&dir, index, status));
        }
    };
    for worker in &mut workers {
        if status.success() {
            worker.wait()?;
        } else {
            let _ = worker.kill();
        }
    }
    if !status.success() {
        bail!(
            "the coordinator failed ({status}); see {}/coordinator.log",
            dir.display()
        );
    }
    print_figures(&job, started.elapsed().as_secs_f64())
}

/// The error of a job stopped because worker `index` failed, with its reason from its log.
fn worker_failed(dir: &Path, index: usize, status: std::process::ExitStatus) -> anyhow::Error {
    let log = dir.join(format!("worker-{index}.log"));
    let reason = std::fs::read_to_string(&log)
        .ok()
        .and_then(|text| failure_reason(&text))
        .unwrap_or_else(|| "no reason in its log".into());
    anyhow::anyhow!(
        "worker local-{index} failed ({status}) while the job ran, so the job stopped: \
         {reason}; see {}",
        log.display()
    )
}

/// Kills every process of the job and reaps it.
fn stop(coordinator: &mut Child, workers: &mut [Child]) {
    for child in std::iter::once(coordinator).chain(workers.iter_mut()) {
        let _ = child.kill();
        let _ = child.wait();
    }
}

/// Prints the job's figures as one `key=value` line from its report, curves and evaluation,
/// then where to look.
fn print_figures(job: &LocalJob, seconds: f64) -> anyhow::Result<()> {
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(job.report_path())?)?;
    let steps = report["steps"].as_array().cloned().unwrap_or_default();
    let stage = |number: u64| -> Vec<&serde_json::Value> {
        steps.iter().filter(|r| r["stage"] == number).collect()
    };
    let mut figures = Vec::new();
    for &number in job.trained_stages() {
        let records = stage(number);
        let timed = StepTimes::of(&records);
        let (first, last) = loss_ends(
            &job.checkpoint_dir()
                .join(format!("curves/stage{number}.csv")),
        );
        figures.push(format!(
            "stage{number}_loss={first:.4}->{last:.4} stage{number}_step_s={:.4} stage{number}_pairs_per_s={:.2} stage{number}_allreduce_s={:.4} stage{number}_comm_share={:.3}",
            timed.step_s,
            job.global_batch as f64 / timed.step_s,
            timed.allreduce_s,
            timed.allreduce_s / timed.step_s
        ));
    }
    if let Some(location) = report["evaluation"].as_str() {
        figures.push(evaluation_figures(Path::new(location))?);
    }
    println!(
        "outcome={} workers={} device={} preset={} image_size={} global_batch={} micro_batch={} steps={} {} restarts={} checksum_mismatches={} seconds={:.1} report={}",
        report["outcome"].as_str().unwrap_or("?"),
        job.workers,
        job.device,
        job.preset,
        job.image_size,
        job.global_batch,
        job.micro_batch,
        job.trained_steps(),
        figures.join(" "),
        report["restarts"],
        report["checksum_mismatches"].as_array().map_or(0, Vec::len),
        seconds,
        job.report_path().display()
    );
    println!("departs from the release: {}", job.departures().join("; "));
    print_where_to_look(job, report["evaluation"].as_str().map(Path::new));
    Ok(())
}

/// Where the report, the pictures and the TensorBoard runs are, and the command that opens
/// TensorBoard (from the environment `scripts/setup.sh` installs it into).
fn print_where_to_look(job: &LocalJob, evaluation: Option<&Path>) {
    let checkpoints = job.checkpoint_dir();
    if let Some(evaluation) = evaluation {
        println!("report:      {}", evaluation.join("report.md").display());
        println!(
            "pictures:    {}/*.png (reconstructions, transfers along the source camera path, camera paths)",
            evaluation.display()
        );
    }
    let curves: Vec<String> = job
        .trained_stages()
        .iter()
        .map(|stage| format!("stage{stage}.png"))
        .collect();
    println!(
        "curves:      {}/curves/{} (and .svg, .csv)",
        checkpoints.display(),
        curves.join(", ")
    );
    let cache = settings::cache::project_cache();
    println!(
        "tensorboard: {} --logdir {}/tensorboard   (then open http://localhost:6006)",
        cache.join("tensorboard-env/bin/tensorboard").display(),
        checkpoints.display()
    );
}

/// Redraws the progress line from the coordinator's status twice a second until `done`.
async fn draw_progress(job: LocalJob, started: Instant, done: Arc<AtomicBool>) {
    let address = format!("http://127.0.0.1:{}", job.port);
    let mut client = None;
    while !done.load(Ordering::SeqCst) {
        tokio::time::sleep(Duration::from_millis(500)).await;
        if client.is_none() {
            let Ok(endpoint) = tonic::transport::Endpoint::from_shared(address.clone()) else {
                return;
            };
            let Ok(attach) = proto::AttachToken::new(job.token()) else {
                return;
            };
            if let Ok(channel) = endpoint.connect().await {
                client = Some(CoordinatorClient::with_interceptor(channel, attach));
            }
        }
        let Some(connected) = client.as_mut() else {
            continue;
        };
        if let Ok(status) = connected.status(StatusRequest {}).await {
            let line = progress::line(&status.into_inner(), started.elapsed());
            let mut stderr = std::io::stderr();
            let _ = write!(stderr, "\r{line}\x1b[K");
            let _ = stderr.flush();
        }
    }
    eprintln!();
}

/// The mean loss of a stage's first and of its last tenth of steps (at most 50 each), from
/// its curve CSV: the report keeps only the newest steps, and single steps are noisy.
fn loss_ends(csv: &Path) -> (f64, f64) {
    let losses: Vec<f64> = std::fs::read_to_string(csv)
        .unwrap_or_default()
        .lines()
        .skip(1)
        .filter_map(|line| line.split(',').nth(1)?.parse().ok())
        .collect();
    let count = (losses.len() / 10).clamp(1, 50);
    let mean = |values: &[f64]| values.iter().sum::<f64>() / values.len().max(1) as f64;
    if losses.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    (
        mean(&losses[..count]),
        mean(&losses[losses.len() - count..]),
    )
}

/// Mean step and all-reduce times of a stage, leaving out its first step (model set-up and
/// warm-up) when there are others.
struct StepTimes {
    step_s: f64,
    allreduce_s: f64,
}

impl StepTimes {
    fn of(records: &[&serde_json::Value]) -> Self {
        let timed = if records.len() > 1 {
            &records[1..]
        } else {
            records
        };
        let mean = |key: &str| {
            let values: Vec<f64> = timed.iter().filter_map(|r| r[key].as_f64()).collect();
            values.iter().sum::<f64>() / values.len().max(1) as f64
        };
        Self {
            step_s: mean("step_s"),
            allreduce_s: mean("allreduce_s"),
        }
    }
}

/// The headline numbers of the evaluation report at `location`: for each scored checkpoint
/// (stage 1, stage 2) its context views, then reconstruction, TPS and probe figures of the
/// trained model with their spreads beside the untrained model and the pose-free baselines,
/// and the lead over the best baseline.
fn evaluation_figures(location: &Path) -> anyhow::Result<String> {
    let path = location.join("report.json");
    let report: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?,
    )
    .with_context(|| format!("{} is not JSON", path.display()))?;
    let scenes = &report["scenes"];
    let probe = &report["spec"]["probe"];
    let mut figures = vec![format!(
        "eval_split={} eval_scenes={} eval_paths={} probe_width={} probe_steps={} probe_batch={} probe_loss={}",
        scenes["split"].as_str().unwrap_or("?"),
        scenes["scenes"],
        scenes["trajectories"],
        probe["width"],
        probe["steps"],
        probe["batch"],
        probe["loss"].as_str().unwrap_or("?")
    )];
    for stage in report["stages"].as_array().into_iter().flatten() {
        figures.push(stage_figures(stage));
    }
    figures.push(format!(
        "evaluation={}",
        location.join("report.md").display()
    ));
    Ok(figures.join(" "))
}

/// `SE3_Auc@30` of a camera-metrics object and its spread (NaN where the report lacks them).
fn auc30(metrics: &serde_json::Value) -> (f64, f64) {
    figures::auc30(metrics).unwrap_or((f64::NAN, f64::NAN))
}

/// One scored checkpoint's figures, every key prefixed with its label (`stage1_...`).
fn stage_figures(stage: &serde_json::Value) -> String {
    let label = stage["checkpoint"]["label"]
        .as_str()
        .unwrap_or("checkpoint");
    let number = |value: &serde_json::Value| value.as_f64().unwrap_or(f64::NAN);
    let (trained, untrained, baselines) =
        (&stage["trained"], &stage["untrained"], &stage["baselines"]);
    let psnr = |r: &serde_json::Value| number(&r["psnr"]);
    let (copy, mean_colour) = (psnr(&baselines["copy"]), psnr(&baselines["mean_colour"]));
    let ours = psnr(&trained["reconstruction"]);
    let (tps, tps_spread) = auc30(&trained["tps"]["model"]);
    let (probe, probe_spread) = auc30(&trained["probe"]["metrics"]);
    format!(
        "{label}_step={} {label}_contexts={} \
         {label}_psnr={ours:.2} {label}_psnr_spread={:.2} {label}_copy_psnr={copy:.2} \
         {label}_mean_colour_psnr={mean_colour:.2} {label}_untrained_psnr={:.2} \
         {label}_psnr_lead_over_copy={:.2} {label}_psnr_lead_over_best_baseline={:.2} \
         {label}_tps_auc30={tps:.3} {label}_tps_auc30_spread={tps_spread:.3} \
         {label}_no_motion_tps_auc30={:.3} {label}_untrained_tps_auc30={:.3} \
         {label}_tps_copy_share={:.3} \
         {label}_probe_auc30={probe:.3} {label}_probe_auc30_spread={probe_spread:.3} \
         {label}_no_motion_probe_auc30={:.3} {label}_untrained_probe_auc30={:.3}",
        stage["checkpoint"]["step"],
        stage["checkpoint"]["context_views"],
        number(&trained["reconstruction"]["psnr_spread"]),
        psnr(&untrained["reconstruction"]),
        ours - copy,
        ours - copy.max(mean_colour),
        auc30(&baselines["tps_no_motion"]).0,
        auc30(&untrained["tps"]["model"]).0,
        number(&trained["tps"]["copy_share"]),
        auc30(&baselines["probe_no_motion"]).0,
        auc30(&untrained["probe"]["metrics"]).0,
    )
}
