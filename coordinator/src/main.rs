//! `xfactor-coordinator`: runs a job from a cluster YAML, or prints a running job's status.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
use coordinator::config::ClusterConfig;
use coordinator::plan::Plan;
use coordinator::service::CoordinatorService;
use proto::auth::TokenArgs;
use proto::tls::TlsClientArgs;
use proto::v1::StatusRequest;
use proto::v1::coordinator_client::CoordinatorClient;
use telemetry::logging::LogArgs;

/// Runs a job from a cluster YAML, or prints a running job's status.
#[derive(Debug, Parser)]
#[command(
    name = "xfactor-coordinator",
    version = telemetry::VERSION,
    after_help = "Examples:
  check a cluster YAML and print the plan:
    xfactor-coordinator run --config deploy/examples/local.yaml --dry-run
  run the job (workers then join with xfactor-worker --coordinator http://HOST:50051):
    xfactor-coordinator run --config cluster.yaml --report report.json
  a running job's progress:
    xfactor-coordinator status --address http://HOST:50051 --token-env XFACTOR_TOKEN"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Runs the job the cluster YAML describes until it ends
    Run(RunArgs),
    /// Prints a running job's status in one line
    Status(StatusArgs),
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// The cluster YAML
    #[arg(long, value_name = "CLUSTER.yaml")]
    config: PathBuf,
    /// Prints the resolved plan (ranks, shards, steps) and exits
    #[arg(long)]
    dry_run: bool,
    /// Where the job report (JSON) is written when the job ends
    #[arg(long, value_name = "REPORT.json")]
    report: Option<PathBuf>,
    /// Serves Prometheus /metrics and /healthz here (by default the YAML's metrics_listen, if any)
    #[arg(long, value_name = "HOST:PORT")]
    metrics_address: Option<String>,
    #[command(flatten)]
    log: LogArgs,
}

#[derive(Debug, clap::Args)]
struct StatusArgs {
    /// The coordinator, http(s)://HOST:PORT
    #[arg(long, value_name = "URL", required_unless_present = "page")]
    address: Option<String>,
    /// Read the status page's /api/status at the coordinator's metrics address instead (the
    /// snapshot the page draws)
    #[arg(long, value_name = "HOST:PORT", conflicts_with = "address")]
    page: Option<String>,
    #[command(flatten)]
    token: TokenArgs,
    #[command(flatten)]
    tls: TlsClientArgs,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    match cli.command {
        Command::Run(args) => {
            args.log.init()?;
            runtime.block_on(run(&args))
        }
        Command::Status(args) => runtime.block_on(status(&args)),
    }
}

async fn run(args: &RunArgs) -> anyhow::Result<()> {
    // Before indexing, which can take minutes: a batch system's warning then still suspends
    // (at once, as nothing trains yet) instead of killing the process.
    let suspender = tokio_util::sync::CancellationToken::new();
    tokio::spawn(suspend_on_usr1(suspender.clone()));
    let config = ClusterConfig::from_file(&args.config)?;
    let token = config.auth.resolve()?;
    let viewing = config
        .viewing
        .as_ref()
        .map(|viewing| viewing.0.resolve())
        .transpose()?;
    let plan = Plan::build(config).await?;
    if args.dry_run {
        print!("{}", plan.describe());
        return Ok(());
    }
    let metrics_address = args
        .metrics_address
        .clone()
        .or_else(|| plan.config.metrics_listen.as_ref().map(|a| a.0.clone()));
    let service = CoordinatorService::new(plan)
        .await?
        .suspended_by(suspender.clone());
    if let Some(address) = metrics_address {
        telemetry::http::serve_with(
            &address,
            service.metrics(),
            telemetry::http::always_healthy(),
            service.status_page(&token, viewing.as_deref())?,
        )
        .await?;
    }
    let shutdown = async {
        let mut terminate =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(signal) => signal,
                Err(_) => return std::future::pending().await,
            };
        tokio::select! {
            _ = terminate.recv() => {}
            _ = tokio::signal::ctrl_c() => {}
        }
    };
    let mut report = service.run(&token, shutdown).await?;
    if suspender.is_cancelled() {
        report.outcome = report.outcome.replacen("stopped", "suspended", 1);
    }
    let json = serde_json::to_string_pretty(&report)?;
    if let Some(path) = &args.report {
        std::fs::write(path, &json)
            .with_context(|| format!("writing the report to {}", path.display()))?;
    }
    tracing::info!(outcome = %report.outcome, restarts = report.restarts, mismatches = report.checksum_mismatches.len(), "job ended");
    if suspender.is_cancelled() {
        tracing::warn!(
            code = SUSPENDED_EXIT_CODE,
            "suspended: rerun or requeue the job to resume from its last commit"
        );
        std::process::exit(SUSPENDED_EXIT_CODE);
    }
    if let Some(reason) = report.outcome.strip_prefix("failed: ") {
        bail!("the job failed: {reason}");
    }
    if !report.checksum_mismatches.is_empty() {
        // Each divergence rolled the group back to a commit the replicas agreed on, so the
        // weights the job ends with are sound; the operator still wants to know.
        tracing::warn!(
            mismatches = ?report.checksum_mismatches,
            exclusions = report.exclusions.len(),
            "replicas diverged during the job; each time the group rolled back to its last commit"
        );
    }
    Ok(())
}

/// The exit status of a suspended job (`EX_TEMPFAIL`): the batch script requeues on it.
const SUSPENDED_EXIT_CODE: i32 = 75;

/// Suspends the job on SIGUSR1, which Slurm sends before the time limit
/// (`--signal=B:USR1@90`, forwarded by `deploy/slurm/xfactor.sbatch`); a repeated signal is
/// harmless.
async fn suspend_on_usr1(suspender: tokio_util::sync::CancellationToken) {
    let Ok(mut usr1) =
        tokio::signal::unix::signal(tokio::signal::unix::SignalKind::user_defined1())
    else {
        tracing::warn!(
            "SIGUSR1 cannot be caught; a batch system's warning will not suspend the job"
        );
        return;
    };
    while usr1.recv().await.is_some() {
        tracing::warn!("SIGUSR1: suspending the job");
        suspender.cancel();
    }
}

async fn status(args: &StatusArgs) -> anyhow::Result<()> {
    let token = args.token.resolve()?;
    let address = match (&args.address, &args.page) {
        (_, Some(page)) => {
            let snapshot = coordinator::status::fetch(page, &token).await?;
            for line in coordinator::status::summary(&snapshot) {
                println!("{line}");
            }
            return Ok(());
        }
        (Some(address), None) => address,
        (None, None) => bail!("give --address (the coordinator) or --page (its metrics address)"),
    };
    let mut endpoint = tonic::transport::Endpoint::from_shared(address.clone())
        .with_context(|| format!("`{address}` is not a URL"))?;
    if let Some(tls) = args.tls.client_config(endpoint.uri())? {
        endpoint = endpoint.tls_config(tls)?;
    }
    let channel = endpoint
        .connect()
        .await
        .with_context(|| format!("cannot reach the coordinator at {address}"))?;
    let mut client = CoordinatorClient::with_interceptor(channel, proto::AttachToken::new(&token)?);
    let status = client.status(StatusRequest {}).await?.into_inner();
    println!(
        "job={} phase={} generation={} workers={} step={}/{} job_steps={}/{} last_loss={} restarts={} last_commit={}",
        status.job_name,
        proto::convert::status_label(&status),
        status.generation,
        status.workers,
        status.step,
        status.total_steps,
        status.job_steps_done,
        status.job_steps_total,
        status.last_loss,
        status.restarts,
        if status.last_commit.is_empty() {
            "-"
        } else {
            &status.last_commit
        }
    );
    for worker in &status.worker_list {
        println!("{}", proto::convert::worker_line(worker));
    }
    Ok(())
}
