//! `xfactor-worker`: a worker daemon that joins a job's coordinator and trains until the job
//! ends; `xfactor-worker allreduce-bench` times the ring all-reduce between processes.

use std::time::Duration;

use anyhow::{Context, bail};
use telemetry::cli::{Flags, init_logging};
use worker::daemon::{WorkerOptions, WorkerTls, run};

const USAGE: &str = "usage:
  xfactor-worker --coordinator http(s)://HOST:PORT (--token TOKEN | --token-env VAR)
                 [--listen 127.0.0.1:0] [--advertise HOST:PORT] [--device auto|cpu|wgpu]
                 [--threads N] [--name NAME] [--model-config MODEL.json]
                 [--collective-timeout-s 120] [--scratch DIR] [--log-format human|json]
                 [--metrics-address HOST:PORT]
                 [--tls-ca CA.pem [--tls-domain NAME] [--tls-cert CERT.pem --tls-key KEY.pem]]
  xfactor-worker allreduce-bench --rank R --peers A,B,... --sizes-mb 1,16,64,100 [--repeats 5] [--threads 1] [--chunk-values N]";

/// TLS settings from `--tls-*`: the CA is required for any TLS, and the certificate and key
/// come as a pair.
fn tls_options(flags: &Flags) -> anyhow::Result<Option<WorkerTls>> {
    let identity = match (flags.get("tls-cert"), flags.get("tls-key")) {
        (Some(cert), Some(key)) => Some((cert.into(), key.into())),
        (None, None) => None,
        _ => bail!("--tls-cert and --tls-key go together"),
    };
    match flags.get("tls-ca") {
        Some(ca) => Ok(Some(WorkerTls {
            ca: ca.into(),
            domain: flags.get("tls-domain").map(str::to_string),
            identity,
        })),
        None if identity.is_some() || flags.has("tls-domain") => {
            bail!("--tls-cert, --tls-key and --tls-domain need --tls-ca")
        }
        None => Ok(None),
    }
}

fn main() -> anyhow::Result<()> {
    // Before any thread exists: large buffers (gradients, chunks, tensors) are reused from the
    // heap instead of being mapped, faulted in and unmapped every step.
    let tuning = trainer_core::allocator::keep_freed_memory();
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("allreduce-bench") {
        let flags = Flags::parse(
            &args[1..],
            &[],
            &[
                "rank",
                "peers",
                "sizes-mb",
                "repeats",
                "threads",
                "chunk-values",
            ],
        )
        .map_err(|e| anyhow::anyhow!("{e}\n{USAGE}"))?;
        return worker::bench::run_rank(&flags);
    }
    let flags = Flags::parse(
        &args,
        &[],
        &[
            "coordinator",
            "token",
            "token-env",
            "listen",
            "advertise",
            "device",
            "threads",
            "name",
            "model-config",
            "collective-timeout-s",
            "scratch",
            "log-format",
            "metrics-address",
            "tls-ca",
            "tls-domain",
            "tls-cert",
            "tls-key",
        ],
    )
    .map_err(|e| anyhow::anyhow!("{e}\n{USAGE}"))?;
    init_logging(flags.get("log-format")).map_err(anyhow::Error::msg)?;
    tracing::debug!(?tuning, "allocator tuned");
    let token = match (flags.get("token"), flags.get("token-env")) {
        (Some(token), _) => token.to_string(),
        (None, Some(var)) => {
            std::env::var(var).with_context(|| format!("--token-env: {var} is not set"))?
        }
        (None, None) => bail!("give --token or --token-env\n{USAGE}"),
    };
    let threads = flags
        .get("threads")
        .map(|t| {
            t.parse::<usize>()
                .with_context(|| format!("--threads `{t}` is not a whole number"))
        })
        .transpose()?;
    let timeout = flags
        .get("collective-timeout-s")
        .map(|t| {
            t.parse::<f64>()
                .with_context(|| format!("--collective-timeout-s `{t}` is not a number"))
        })
        .transpose()?
        .unwrap_or(120.0);
    let expected_model_config = flags
        .get("model-config")
        .map(|path| {
            let text =
                std::fs::read_to_string(path).with_context(|| format!("--model-config {path}"))?;
            serde_json::from_str::<settings::XFactorConfig>(&text)
                .with_context(|| format!("--model-config {path} is not a model config"))
        })
        .transpose()?;
    let scratch = match flags.get("scratch") {
        Some(dir) => dir.into(),
        None => std::env::temp_dir().join(format!("xfactor-worker-{}", std::process::id())),
    };
    let options = WorkerOptions {
        coordinator: flags
            .require("coordinator")
            .map_err(anyhow::Error::msg)?
            .to_string(),
        token,
        listen: flags.get("listen").unwrap_or("127.0.0.1:0").to_string(),
        advertise: flags.get("advertise").map(str::to_string),
        device: flags
            .get("device")
            .map(str::parse::<settings::DeviceChoice>)
            .transpose()?,
        threads,
        name: flags
            .get("name")
            .map_or_else(|| format!("worker-{}", std::process::id()), str::to_string),
        expected_model_config,
        collective_timeout: Duration::from_secs_f64(timeout),
        scratch,
        metrics_address: flags.get("metrics-address").map(str::to_string),
        tls: tls_options(&flags)?,
    };
    run(options)
}
