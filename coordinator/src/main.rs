//! `xfactor-coordinator`: runs a job from a cluster YAML, or prints a running job's status.

use std::path::Path;

use anyhow::{Context, bail};
use coordinator::config::ClusterConfig;
use coordinator::plan::Plan;
use coordinator::service::CoordinatorService;
use proto::v1::StatusRequest;
use proto::v1::coordinator_client::CoordinatorClient;
use telemetry::cli::{Flags, init_logging};

const USAGE: &str = "usage:
  xfactor-coordinator run --config CLUSTER.yaml [--dry-run] [--report REPORT.json]
                          [--metrics-address HOST:PORT] [--log-format human|json]
  xfactor-coordinator status --address http(s)://HOST:PORT (--token TOKEN | --token-env VAR)
                             [--tls-ca CA.pem] [--tls-domain NAME]";

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some((command, rest)) = args.split_first() else {
        bail!("{USAGE}");
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    match command.as_str() {
        "run" => {
            let flags = Flags::parse(
                rest,
                &["dry-run"],
                &["config", "report", "log-format", "metrics-address"],
            )
            .map_err(|e| anyhow::anyhow!("{e}\n{USAGE}"))?;
            init_logging(flags.get("log-format")).map_err(anyhow::Error::msg)?;
            runtime.block_on(run(&flags))
        }
        "status" => {
            let flags = Flags::parse(
                rest,
                &[],
                &["address", "token", "token-env", "tls-ca", "tls-domain"],
            )
            .map_err(|e| anyhow::anyhow!("{e}\n{USAGE}"))?;
            runtime.block_on(status(&flags))
        }
        other => bail!("unknown command `{other}`\n{USAGE}"),
    }
}

async fn run(flags: &Flags) -> anyhow::Result<()> {
    let path = flags.require("config").map_err(anyhow::Error::msg)?;
    let config = ClusterConfig::from_file(Path::new(path))?;
    let token = config.auth.resolve()?;
    let plan = Plan::build(config).await?;
    if flags.has("dry-run") {
        print!("{}", plan.describe());
        return Ok(());
    }
    let metrics_address = flags
        .get("metrics-address")
        .map(str::to_string)
        .or_else(|| plan.config.metrics_listen.as_ref().map(|a| a.0.clone()));
    let service = CoordinatorService::new(plan).await?;
    if let Some(address) = metrics_address {
        telemetry::http::serve(&address, service.metrics()).await?;
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
    let report = service.run(&token, shutdown).await?;
    let json = serde_json::to_string_pretty(&report)?;
    if let Some(path) = flags.get("report") {
        std::fs::write(path, &json).with_context(|| format!("writing the report to {path}"))?;
    }
    tracing::info!(outcome = %report.outcome, restarts = report.restarts, mismatches = report.checksum_mismatches.len(), "job ended");
    if let Some(reason) = report.outcome.strip_prefix("failed: ") {
        bail!("the job failed: {reason}");
    }
    if !report.checksum_mismatches.is_empty() {
        bail!(
            "ranks disagreed on parameters: {:?}",
            report.checksum_mismatches
        );
    }
    Ok(())
}

async fn status(flags: &Flags) -> anyhow::Result<()> {
    let address = flags.require("address").map_err(anyhow::Error::msg)?;
    let token = match (flags.get("token"), flags.get("token-env")) {
        (Some(token), _) => token.to_string(),
        (None, Some(var)) => std::env::var(var).with_context(|| format!("{var} is not set"))?,
        (None, None) => bail!("give --token or --token-env"),
    };
    let mut endpoint = tonic::transport::Endpoint::from_shared(address.to_string())
        .with_context(|| format!("`{address}` is not a URL"))?;
    if let Some(ca) = flags.get("tls-ca") {
        if endpoint.uri().scheme_str() != Some("https") {
            bail!("--tls-ca needs an https:// address, got `{address}`");
        }
        let domain = match flags.get("tls-domain") {
            Some(domain) => domain.to_string(),
            None => endpoint.uri().host().unwrap_or("localhost").to_string(),
        };
        endpoint = endpoint.tls_config(proto::tls::client_config(Path::new(ca), &domain)?)?;
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
    Ok(())
}
