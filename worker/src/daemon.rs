//! The worker's life: register, await an assignment, do it (train one rank of a group, or
//! evaluate), and go back for the next, until the coordinator says the job is done. The parts
//! live beside this file: `session` (coordinator RPCs and heartbeats), `shutdown` (signals),
//! `training` (one generation's steps), `evaluate`, `checkpoints` (upload and commit).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use anyhow::{Context, bail};
use proto::v1::GenerationFailure;
use proto::v1::assignment::Work;
use settings::{DeviceChoice, XFactorConfig};
use tokio_util::sync::CancellationToken;

use crate::checkpoints::CorruptCheckpoint;
use crate::collective::{CollectiveError, CollectiveService, Link, Mailbox, PeerTls, spawn_server};
use crate::session::{Progress, await_assignment, connect, heartbeats, leave, register};
use crate::{evaluate, metrics, shutdown, training};

/// Consecutive generations that may fail before the worker gives up.
const MAX_CONSECUTIVE_FAILURES: u32 = 8;

/// How a worker is started.
#[derive(Debug, Clone)]
pub struct WorkerOptions {
    /// Coordinator URL, `http://host:port`.
    pub coordinator: String,
    /// The job token.
    pub token: String,
    /// Where the Collective service binds (`127.0.0.1:0` picks a free port).
    pub listen: String,
    /// Address peers should use, when it differs from the bound one (NAT, `0.0.0.0`).
    pub advertise: Option<String>,
    /// The device to train on; `None` follows the job.
    pub device: Option<DeviceChoice>,
    /// Threads per micro-batch; `None` follows the job (0 there: every core).
    pub threads: Option<usize>,
    /// Name in logs.
    pub name: String,
    /// When set: the model config this worker insists on.
    pub expected_model_config: Option<XFactorConfig>,
    /// Longest wait for a peer's chunk.
    pub collective_timeout: Duration,
    /// Scratch space for checkpoints on their way to and from the store.
    pub scratch: PathBuf,
    /// `host:port` for Prometheus `/metrics`; `None`: no endpoint.
    pub metrics_address: Option<String>,
    /// TLS towards the coordinator and between ranks; `None`: plain HTTP/2.
    pub tls: Option<WorkerTls>,
    /// Fault drill: from this step on, perturb this replica's all-reduced gradients (a
    /// silently faulty accelerator) so the job's divergence handling can be exercised.
    pub drill_diverge_from_step: Option<u64>,
}

/// A worker's TLS files. With `identity`, its Collective service runs TLS too and peers are
/// dialled over TLS (every worker of a job must then have one).
#[derive(Debug, Clone)]
pub struct WorkerTls {
    /// CA that signed the coordinator's (and peers') certificates.
    pub ca: PathBuf,
    /// Name the certificates must carry; `None`: the host of the address dialled.
    pub domain: Option<String>,
    /// This worker's certificate and key, for its Collective service.
    pub identity: Option<(PathBuf, PathBuf)>,
}

impl WorkerTls {
    pub(crate) fn client(&self, host: &str) -> anyhow::Result<tonic::transport::ClientTlsConfig> {
        let domain = self.domain.as_deref().unwrap_or(host);
        Ok(proto::tls::client_config(&self.ca, domain)?)
    }

    fn peers(&self) -> anyhow::Result<Option<PeerTls>> {
        let Some((cert, key)) = &self.identity else {
            return Ok(None);
        };
        let server = proto::tls::server_config(cert, key)?;
        proto::tls::client_config(&self.ca, self.domain.as_deref().unwrap_or("localhost"))?;
        Ok(Some(PeerTls {
            server,
            ca: self.ca.clone(),
            domain: self.domain.clone(),
        }))
    }
}

/// How a generation ended for this worker.
pub enum Ending {
    /// The stage (or this generation's part of it) is done.
    Done,
    /// SIGTERM arrived; the last step finished cleanly and nothing is half-committed.
    Stopping,
    /// The coordinator suspends the job: this worker's part is committed (rank 0) or needs
    /// nothing more (the others); it exits without leaving, so the generation stays whole
    /// until the commit is in.
    Suspended,
}

/// What every generation of this worker shares.
#[derive(Clone, Copy)]
pub struct Group<'a> {
    /// How the worker was started.
    pub options: &'a WorkerOptions,
    /// How to reach peers.
    pub link: &'a Link,
    /// Chunks from the left neighbour.
    pub mailbox: &'a Mailbox,
    /// Shared with the heartbeat task.
    pub progress: &'a Progress,
    /// Cancelled on SIGTERM.
    pub shutdown: &'a CancellationToken,
}

/// Runs the worker until the job finishes. Blocking; owns its async runtime.
pub fn run(options: WorkerOptions) -> anyhow::Result<()> {
    // One I/O thread: RPCs, heartbeats and the collective streams are light, and the ring
    // all-reduce runs fastest when its chunks never change threads. Training uses its own.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let link = Link {
        token: options.token.clone(),
        timeout: options.collective_timeout,
        tls: options
            .tls
            .as_ref()
            .map(WorkerTls::peers)
            .transpose()?
            .flatten(),
    };
    let collective = CollectiveService::default();
    let mailbox = collective.mailbox();
    let (address, health) = runtime.block_on(serve_collective(&options, collective, &link))?;
    let mut client = runtime.block_on(connect(
        &options.coordinator,
        &options.token,
        options.tls.as_ref(),
    ))?;
    let progress = Arc::new(Progress::new());
    if let Some(address) = &options.metrics_address {
        runtime.block_on(telemetry::http::serve(
            address,
            Arc::clone(&progress.metrics),
            Progress::health(&progress),
        ))?;
    }
    let shutdown = shutdown::on_signals(&runtime);
    let interval = runtime.block_on(register(&mut client, &options, &address, &progress))?;
    runtime.spawn(heartbeats(client.clone(), progress.clone(), interval));
    runtime.spawn(crate::health::mirror_membership(
        health,
        progress.clone(),
        interval,
    ));
    let mut after = 0;
    let mut failures = 0;
    let mut failure: Option<GenerationFailure> = None;
    loop {
        let waited = runtime.block_on(async {
            tokio::select! {
                assignment = await_assignment(&mut client, &progress, after, failure.as_ref()) => Some(assignment),
                () = shutdown.cancelled() => None,
            }
        });
        let Some(waited) = waited else {
            return leave(&runtime, &mut client, &progress);
        };
        failure = None;
        let assignment = match waited {
            Ok(assignment) => assignment,
            Err(status) if status.code() == tonic::Code::NotFound => {
                tracing::warn!(reason = %status.message(), "registering again");
                runtime.block_on(register(&mut client, &options, &address, &progress))?;
                after = 0;
                continue;
            }
            Err(status) => bail!("coordinator: {}", status.message()),
        };
        let generation = assignment.generation;
        let work = match assignment.work {
            Some(Work::Finish(_)) => {
                tracing::info!("the job is finished");
                return Ok(());
            }
            Some(work) => work,
            None => bail!("the coordinator sent generation {generation} without work"),
        };
        after = generation;
        progress.generation.store(after, Ordering::SeqCst);
        progress.cancel.send_replace(false);
        let span = tracing::info_span!("generation", generation);
        let _entered = span.enter();
        let group = Group {
            options: &options,
            link: &link,
            mailbox: &mailbox,
            progress: &progress,
            shutdown: &shutdown,
        };
        let ended = match &work {
            Work::Train(train) => {
                training::train_generation(&runtime, &mut client, &group, generation, train)
            }
            Work::Evaluate(evaluate) => {
                evaluate::evaluate(&runtime, &mut client, &group, generation, evaluate)
            }
            Work::Finish(_) => Ok(Ending::Done),
        };
        match ended {
            Ok(Ending::Done) => {
                failures = 0;
                tracing::info!("generation {generation} done");
            }
            Ok(Ending::Stopping) => {
                drop(_entered);
                return leave(&runtime, &mut client, &progress);
            }
            Ok(Ending::Suspended) => {
                tracing::warn!(
                    "the coordinator suspended the job; exiting (a requeued job resumes from its last commit)"
                );
                return Ok(());
            }
            Err(error) => {
                failures += 1;
                progress.metrics.add(&metrics::RESTARTS, &[], 1.0);
                tracing::warn!(error = %format!("{error:#}"), "generation abandoned");
                failure = Some(GenerationFailure {
                    reason: format!("{error:#}"),
                    suspect_rank: suspect_rank(&error),
                    corrupt_checkpoint: error
                        .chain()
                        .find_map(|cause| cause.downcast_ref::<CorruptCheckpoint>())
                        .map(|corrupt| corrupt.location.clone())
                        .unwrap_or_default(),
                });
                if failures >= MAX_CONSECUTIVE_FAILURES {
                    bail!("{failures} generations in a row failed; last error: {error:#}");
                }
            }
        }
    }
}

/// The peer rank a failed generation's error points at: the one that timed out, whose stream
/// broke or that sent a bad chunk. `None`: the worker's own failure (an upload, its data).
fn suspect_rank(error: &anyhow::Error) -> Option<u32> {
    let collective = error
        .chain()
        .find_map(|cause| cause.downcast_ref::<CollectiveError>())?;
    match collective {
        CollectiveError::Connect { rank, .. }
        | CollectiveError::PeerGone { rank }
        | CollectiveError::InboundBroken { rank, .. }
        | CollectiveError::Timeout { rank, .. } => Some(*rank as u32),
        CollectiveError::BadChunk { sender, .. } => Some(*sender),
        CollectiveError::Cancelled | CollectiveError::Aborted(_) | CollectiveError::Tls(_) => None,
    }
}

/// Starts the collective service on `--listen`; returns the address peers dial and the
/// reporter of its health service.
async fn serve_collective(
    options: &WorkerOptions,
    service: CollectiveService,
    link: &Link,
) -> anyhow::Result<(String, tonic_health::server::HealthReporter)> {
    let listener = tokio::net::TcpListener::bind(&options.listen)
        .await
        .with_context(|| format!("cannot listen on {}", options.listen))?;
    let bound: SocketAddr = listener.local_addr()?;
    let health = spawn_server(listener, service, link)?;
    let advertised = match &options.advertise {
        // A host alone (a Slurm node's name) takes the port bound here.
        Some(host) if !host.contains(':') => format!("{host}:{}", bound.port()),
        Some(address) => address.clone(),
        None => bound.to_string(),
    };
    Ok((advertised, health))
}
