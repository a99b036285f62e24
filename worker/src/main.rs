//! `xfactor-worker`: a worker daemon that joins a job's coordinator and trains until the job
//! ends; `xfactor-worker allreduce-bench` times the ring all-reduce between processes.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{CommandFactory, Parser, Subcommand};
use proto::auth::TokenArgs;
use proto::tls::TlsClientArgs;
use settings::{DeviceChoice, DeviceSet};
use telemetry::logging::LogArgs;
use worker::bench::BenchArgs;
use worker::{WorkerOptions, WorkerTls, run};

/// A worker daemon that joins a job's coordinator and trains until the job ends.
#[derive(Debug, Parser)]
#[command(
    name = "xfactor-worker",
    version = telemetry::VERSION,
    after_help = "Examples:
  join a job (token from $XFACTOR_TOKEN), serving Prometheus metrics:
    xfactor-worker --coordinator http://coordinator:50051 --metrics-address 0.0.0.0:9091
  under Slurm (srun in deploy/slurm/xfactor.sbatch), the coordinator address and the
  worker's name come from the job's variables; --no-slurm turns that off:
    srun --ntasks-per-node=1 xfactor-worker",
    subcommand_negates_reqs = true,
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    daemon: DaemonArgs,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Runs one rank of the all-reduce benchmark (benches/allreduce.rs starts the ranks)
    AllreduceBench(BenchArgs),
    /// Runs one rank of the data-path benchmark (scripts/bench-scaling.sh starts the ranks)
    PathBench(worker::bench::path::PathBenchArgs),
}

#[derive(Debug, clap::Args)]
struct DaemonArgs {
    /// The coordinator, http(s)://HOST:PORT (under Slurm by default the job's first node,
    /// port 50051 or $XFACTOR_COORDINATOR_PORT)
    #[arg(long, value_name = "URL")]
    coordinator: Option<String>,
    /// Ignores the Slurm variables (SLURM_JOB_ID, SLURM_JOB_NODELIST, ...) this worker would
    /// otherwise take its defaults from; XFACTOR_SLURM=off does the same
    #[arg(long)]
    no_slurm: bool,
    #[command(flatten)]
    token: TokenArgs,
    /// Where the collective service binds (port 0: any free port; under Slurm the default
    /// becomes 0.0.0.0:0, so peers on other nodes reach it)
    #[arg(long, value_name = "HOST:PORT", default_value = LOOPBACK_ANY_PORT)]
    listen: String,
    /// Address peers dial, when it differs from the bound one (NAT, 0.0.0.0); a HOST alone
    /// takes the bound port (under Slurm by default the node's name)
    #[arg(long, value_name = "HOST[:PORT]")]
    advertise: Option<String>,
    /// Compute device (by default the job's): auto (the best present: CUDA, libtorch on CUDA,
    /// Vulkan, a wgpu GPU, else the CPU), cpu, wgpu, or vulkan, cuda, libtorch in a build with
    /// that cargo feature
    #[arg(long, value_name = "auto|cpu|wgpu|vulkan|cuda|libtorch")]
    device: Option<DeviceChoice>,
    /// Devices this worker drives, one model replica each: all of the backend's, the first
    /// N, or indices (0,2); gradients are summed across them before the ring. The CPU is one
    /// device; N on it runs N replicas there (by default the job's)
    #[arg(long, value_name = "all|N|IDS")]
    devices: Option<DeviceSet>,
    /// Recompute activations in the backward pass instead of keeping them: less device memory,
    /// more time per step (the benchmark model on the CPU: 40% less peak memory, 32% slower)
    #[arg(long)]
    activation_checkpointing: bool,
    /// Threads per micro-batch (by default the job's; when neither says, one per core on
    /// the CPU backend and one on a GPU)
    #[arg(long, value_name = "N")]
    threads: Option<usize>,
    /// Name in logs (by default worker-PID, or slurm-JOB-TASK under Slurm)
    #[arg(long, value_name = "NAME")]
    name: Option<String>,
    /// Model config (JSON) this worker insists on; registration fails on another
    #[arg(long, value_name = "MODEL.json")]
    model_config: Option<PathBuf>,
    /// Longest wait for a peer's chunk, in seconds
    #[arg(long, value_name = "SECONDS", default_value_t = 120.0, value_parser = positive_seconds)]
    collective_timeout_s: f64,
    /// After SIGTERM, how long a worker still busy in its step (wedged in a computation, or
    /// waiting on a peer) gets before it leaves the job anyway and exits 0; a second signal
    /// leaves at once
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0, value_parser = positive_seconds)]
    shutdown_grace_s: f64,
    /// Where compiled GPU kernels and autotune's choices are kept across restarts (cubecl's
    /// cache; by default xfactor-dist/kernels in the user's cache): a worker on CUDA otherwise
    /// compiles and tunes for minutes before its first step, again after every restart. A
    /// cubecl.toml or burn.toml in the working folder or above it takes precedence
    #[arg(long, value_name = "DIR", env = "XFACTOR_KERNEL_CACHE")]
    kernel_cache: Option<PathBuf>,
    /// Scratch space for checkpoints (by default a fresh folder in the system's temp dir)
    #[arg(long, value_name = "DIR")]
    scratch: Option<PathBuf>,
    #[command(flatten)]
    log: LogArgs,
    /// Serves Prometheus /metrics and /healthz here
    #[arg(long, value_name = "HOST:PORT")]
    metrics_address: Option<String>,
    #[command(flatten)]
    tls: TlsClientArgs,
    /// This worker's certificate (PEM): its collective service runs TLS and peers are dialled over TLS
    #[arg(long, value_name = "CERT.pem", requires_all = ["tls_key", "tls_ca"])]
    tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert
    #[arg(long, value_name = "KEY.pem", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Fault drill: from this step on, this worker perturbs its copy of the all-reduced
    /// gradients, so its replica silently diverges as on a faulty accelerator; the
    /// coordinator's parameter checksums must catch it. Never set it in a real run
    #[arg(long, value_name = "STEP")]
    drill_diverge_from_step: Option<u64>,
}

/// `--listen`'s default outside Slurm.
const LOOPBACK_ANY_PORT: &str = "127.0.0.1:0";

/// Why a flag's value is not a usable number of seconds.
#[derive(Debug, thiserror::Error)]
enum SecondsError {
    /// Not a number at all.
    #[error("{0}")]
    NotANumber(#[from] std::num::ParseFloatError),
    /// Zero, negative, or too large for a `Duration`.
    #[error("expected a number of seconds above 0")]
    OutOfRange,
}

/// A whole number of seconds or a fraction, above zero and small enough for a `Duration`.
fn positive_seconds(text: &str) -> Result<f64, SecondsError> {
    let seconds: f64 = text.parse()?;
    if seconds > 0.0 && Duration::try_from_secs_f64(seconds).is_ok() {
        Ok(seconds)
    } else {
        Err(SecondsError::OutOfRange)
    }
}

impl DaemonArgs {
    /// The daemon's options; reads the expected model config.
    fn into_options(self) -> anyhow::Result<WorkerOptions> {
        let token = self.token.resolve()?;
        let expected_model_config = self
            .model_config
            .map(|path| {
                let text = std::fs::read_to_string(&path)
                    .with_context(|| format!("--model-config {}", path.display()))?;
                serde_json::from_str::<settings::XFactorConfig>(&text).with_context(|| {
                    format!("--model-config {} is not a model config", path.display())
                })
            })
            .transpose()?;
        let pid = std::process::id();
        let slurm = if self.no_slurm {
            None
        } else {
            worker::slurm::from_environment()?
        };
        if let Some(launch) = &slurm {
            tracing::info!(
                job = %launch.job_id,
                task = launch.task,
                tasks = ?launch.tasks,
                node = ?launch.node,
                gpus = ?launch.gpus,
                restarts = launch.restarts,
                "launched by Slurm: defaults taken from its variables (--no-slurm turns this off)"
            );
        }
        let slurm_default =
            |pick: fn(&worker::slurm::SlurmLaunch) -> Option<String>| slurm.as_ref().and_then(pick);
        let Some(coordinator) = self
            .coordinator
            .or_else(|| slurm_default(|l| l.coordinator.clone()))
        else {
            Cli::command()
                .error(
                    clap::error::ErrorKind::MissingRequiredArgument,
                    "--coordinator <URL> is required outside a Slurm job (no SLURM_JOB_NODELIST)",
                )
                .exit();
        };
        let listen = match (&slurm, self.listen.as_str()) {
            (Some(_), LOOPBACK_ANY_PORT) => "0.0.0.0:0".to_string(),
            _ => self.listen,
        };
        let advertise = self.advertise.or_else(|| slurm_default(|l| l.node.clone()));
        let name = self
            .name
            .or_else(|| slurm_default(|l| Some(l.worker_name())))
            .unwrap_or_else(|| format!("worker-{pid}"));
        let tls = self.tls.tls_ca.map(|ca| WorkerTls {
            ca,
            domain: self.tls.tls_domain,
            identity: self.tls_cert.zip(self.tls_key),
        });
        Ok(WorkerOptions {
            coordinator,
            token,
            listen,
            advertise,
            device: self.device,
            devices: self.devices,
            activation_checkpointing: self.activation_checkpointing,
            threads: self.threads,
            name,
            expected_model_config,
            collective_timeout: Duration::from_secs_f64(self.collective_timeout_s),
            shutdown_grace: Duration::from_secs_f64(self.shutdown_grace_s),
            scratch: self
                .scratch
                .unwrap_or_else(|| std::env::temp_dir().join(format!("xfactor-worker-{pid}"))),
            metrics_address: self.metrics_address,
            tls,
            drill_diverge_from_step: self.drill_diverge_from_step,
        })
    }
}

fn main() -> anyhow::Result<()> {
    // Before any thread exists: large buffers (gradients, chunks, tensors) are reused from the
    // heap instead of being mapped, faulted in and unmapped every step.
    let tuning = trainer_core::allocator::keep_freed_memory();
    let cli = Cli::parse();
    match cli.command {
        Some(Command::AllreduceBench(args)) => return worker::bench::run_rank(&args),
        Some(Command::PathBench(args)) => return worker::bench::path::run_rank(&args),
        None => {}
    }
    cli.daemon.log.init()?;
    tracing::debug!(?tuning, "allocator tuned");
    keep_kernels(cli.daemon.kernel_cache.clone());
    run(cli.daemon.into_options()?)
}

/// Points cubecl's kernel cache at `--kernel-cache` (or the default folder) before any GPU
/// work. A folder that cannot be made costs compile time, not the run: it is logged.
fn keep_kernels(folder: Option<PathBuf>) {
    let folder = folder.unwrap_or_else(trainer_core::backend::default_kernel_cache);
    match trainer_core::backend::keep_kernels_in(&folder) {
        Ok(kept) => tracing::info!(?kept, "GPU kernel cache"),
        Err(error) => tracing::warn!(
            "{:#}: GPU kernels are compiled and tuned again after a restart",
            anyhow::Error::from(error)
        ),
    }
}
