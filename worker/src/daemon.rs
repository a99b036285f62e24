//! The worker's life: register, await an assignment, train the assigned stage as one rank of
//! the group, and go back for the next assignment, until the coordinator says the job is done.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use proto::v1::assignment::Action;
use proto::v1::coordinator_client::CoordinatorClient;
use proto::v1::{
    Assignment, AwaitAssignmentRequest, CheckpointCommit, HeartbeatRequest, LeaveRequest,
    LossTerms, RegisterRequest, StepReport,
};
use telemetry::Registry;
use tokio::runtime::Runtime;
use tokio::sync::watch;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use trainer_core::backend::BackendChoice;
use trainer_core::data::prefetch::{Prefetched, Schedule};
use trainer_core::data::spec::{DataSpec, RankSource, rank_slice};
use trainer_core::flat::{flatten_gradients, parameter_checksum, unflatten_gradients};
use trainer_core::lpips::Lpips;
use trainer_core::trainer::{TrainConfig, Trainer};
use trainer_core::{XFactor, XFactorConfig};

use crate::checkpoints;
use crate::collective::{CollectiveService, Link, PeerTls, Ring, spawn_server};
use crate::metrics;

/// Consecutive generations that may fail before the worker gives up.
const MAX_CONSECUTIVE_FAILURES: u32 = 8;

type Client = CoordinatorClient<InterceptedService<Channel, proto::AttachToken>>;

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
    /// `cpu`, `wgpu` or `auto`; `None` follows the job.
    pub device: Option<String>,
    /// Threads per micro-batch; `None` follows the job (0 there: every core).
    pub threads: Option<usize>,
    /// Name in logs.
    pub name: String,
    /// When set: the model config (JSON) this worker insists on.
    pub expected_model_config: Option<String>,
    /// Longest wait for a peer's chunk.
    pub collective_timeout: Duration,
    /// Scratch space for checkpoints on their way to and from the store.
    pub scratch: PathBuf,
    /// `host:port` for Prometheus `/metrics`; `None`: no endpoint.
    pub metrics_address: Option<String>,
    /// TLS towards the coordinator and between ranks; `None`: plain HTTP/2.
    pub tls: Option<WorkerTls>,
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
    fn client(&self, host: &str) -> anyhow::Result<tonic::transport::ClientTlsConfig> {
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
enum Ending {
    /// The stage (or this generation's part of it) is done.
    Done,
    /// SIGTERM arrived; the last step finished cleanly and nothing is half-committed.
    Stopping,
}

/// Shared between the training thread and the heartbeat task.
struct Progress {
    worker: AtomicU64,
    generation: AtomicU64,
    step: AtomicU64,
    cancel: watch::Sender<bool>,
    stopping: watch::Sender<bool>,
    metrics: Arc<Registry>,
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
    let address = runtime.block_on(serve_collective(&options, collective, &link))?;
    let mut client = runtime.block_on(connect(
        &options.coordinator,
        &options.token,
        options.tls.as_ref(),
    ))?;
    let (cancel, _) = watch::channel(false);
    let (stopping, _) = watch::channel(false);
    let progress = Arc::new(Progress {
        worker: AtomicU64::new(0),
        generation: AtomicU64::new(0),
        step: AtomicU64::new(0),
        cancel,
        stopping,
        metrics: Arc::new(Registry::new()),
    });
    if let Some(address) = &options.metrics_address {
        runtime.block_on(telemetry::http::serve(
            address,
            Arc::clone(&progress.metrics),
        ))?;
    }
    runtime.spawn(watch_for_termination(Arc::clone(&progress)));
    let interval = runtime.block_on(register(&mut client, &options, &address, &progress))?;
    runtime.spawn(heartbeats(client.clone(), progress.clone(), interval));
    let mut after = 0;
    let mut failures = 0;
    loop {
        let mut stopping = progress.stopping.subscribe();
        let waited = runtime.block_on(async {
            tokio::select! {
                assignment = await_assignment(&mut client, &progress, after) => Some(assignment),
                _ = stopping.wait_for(|stop| *stop) => None,
            }
        });
        let Some(waited) = waited else {
            return leave(&runtime, &mut client, &progress);
        };
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
        if assignment.action == Action::Finish as i32 {
            tracing::info!("the job is finished");
            return Ok(());
        }
        after = assignment.generation;
        progress.generation.store(after, Ordering::SeqCst);
        progress.cancel.send_replace(false);
        let span = tracing::info_span!(
            "generation",
            generation = after,
            rank = assignment.rank,
            world_size = assignment.world_size,
            stage = assignment.stage
        );
        let _entered = span.enter();
        let ended = if assignment.action == Action::Evaluate as i32 {
            evaluate(&runtime, &mut client, &options, &progress, &assignment)
        } else {
            train_generation(
                &runtime,
                &mut client,
                &options,
                &link,
                &mailbox,
                &progress,
                &assignment,
            )
        };
        match ended {
            Ok(Ending::Done) => {
                failures = 0;
                tracing::info!("stage {} done in this generation", assignment.stage);
            }
            Ok(Ending::Stopping) => {
                drop(_entered);
                return leave(&runtime, &mut client, &progress);
            }
            Err(error) => {
                failures += 1;
                progress.metrics.add(&metrics::RESTARTS, &[], 1.0);
                tracing::warn!(error = %format!("{error:#}"), "generation abandoned");
                if failures >= MAX_CONSECUTIVE_FAILURES {
                    bail!("{failures} generations in a row failed; last error: {error:#}");
                }
            }
        }
    }
}

/// Sets `stopping` on SIGTERM or Ctrl-C; the training loop finishes its step and leaves.
async fn watch_for_termination(progress: Arc<Progress>) {
    let mut terminate =
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(signal) => signal,
            Err(error) => {
                tracing::warn!(%error, "SIGTERM cannot be caught; shutdown will be abrupt");
                return;
            }
        };
    let interrupted = || async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        _ = terminate.recv() => {}
        () = interrupted() => {}
    }
    tracing::warn!(
        "shutdown requested: finishing the current step, then leaving the job (signal again to stop at once)"
    );
    progress.stopping.send_replace(true);
    tokio::select! {
        _ = terminate.recv() => {}
        () = interrupted() => {}
    }
    tracing::warn!(
        "second signal: stopping now; the last committed checkpoint stays the resume point"
    );
    std::process::exit(130);
}

/// Tells the coordinator this worker is gone, so its group re-forms at once.
fn leave(runtime: &Runtime, client: &mut Client, progress: &Progress) -> anyhow::Result<()> {
    let request = LeaveRequest {
        worker_id: progress.worker.load(Ordering::SeqCst),
        reason: "SIGTERM".into(),
    };
    let said = runtime.block_on(async {
        tokio::time::timeout(Duration::from_secs(5), client.leave(request)).await
    });
    match said {
        Ok(Ok(_)) => tracing::info!("left the job"),
        Ok(Err(status)) => {
            tracing::warn!(error = %status.message(), "the coordinator did not hear the leave; it will notice the silence")
        }
        Err(_) => {
            tracing::warn!(
                "the coordinator did not answer the leave in 5 s; it will notice the silence"
            )
        }
    }
    Ok(())
}

async fn serve_collective(
    options: &WorkerOptions,
    service: CollectiveService,
    link: &Link,
) -> anyhow::Result<String> {
    let listener = tokio::net::TcpListener::bind(&options.listen)
        .await
        .with_context(|| format!("cannot listen on {}", options.listen))?;
    let bound: SocketAddr = listener.local_addr()?;
    spawn_server(listener, service, link)?;
    Ok(options
        .advertise
        .clone()
        .unwrap_or_else(|| bound.to_string()))
}

/// Connects to the coordinator, retrying for a while (it may start after the workers).
async fn connect(address: &str, token: &str, tls: Option<&WorkerTls>) -> anyhow::Result<Client> {
    let mut endpoint = tonic::transport::Endpoint::from_shared(address.to_string())
        .with_context(|| format!("coordinator address `{address}` is not a URL"))?
        .connect_timeout(Duration::from_secs(2));
    if let Some(tls) = tls {
        if endpoint.uri().scheme_str() != Some("https") {
            bail!("--tls-ca needs an https:// coordinator address, got `{address}`");
        }
        let host = endpoint.uri().host().unwrap_or("localhost").to_string();
        endpoint = endpoint
            .tls_config(tls.client(&host)?)
            .with_context(|| format!("TLS with the CA {}", tls.ca.display()))?;
    }
    let deadline = Instant::now() + Duration::from_secs(60);
    let channel = loop {
        match endpoint.connect().await {
            Ok(channel) => break channel,
            Err(e) if Instant::now() >= deadline => {
                bail!("cannot reach the coordinator at {address}: {e}")
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    };
    Ok(
        CoordinatorClient::with_interceptor(channel, proto::AttachToken::new(token)?)
            .max_decoding_message_size(proto::MAX_MESSAGE_BYTES),
    )
}

async fn register(
    client: &mut Client,
    options: &WorkerOptions,
    address: &str,
    progress: &Progress,
) -> anyhow::Result<Duration> {
    let reply = client
        .register(RegisterRequest {
            protocol_version: proto::PROTOCOL_VERSION,
            model_config_version: XFactorConfig::SCHEMA_VERSION,
            worker_name: options.name.clone(),
            collective_address: address.to_string(),
            device: options.device.clone().unwrap_or_else(|| "job".into()),
            expected_model_config_json: options.expected_model_config.clone().unwrap_or_default(),
        })
        .await
        .map_err(|status| anyhow!("the coordinator refused registration: {}", status.message()))?
        .into_inner();
    progress.worker.store(reply.worker_id, Ordering::SeqCst);
    tracing::info!(worker = reply.worker_id, job = %reply.job_name, collective = %address, "registered");
    Ok(Duration::from_secs_f64(
        reply.heartbeat_interval_s.max(0.05),
    ))
}

async fn await_assignment(
    client: &mut Client,
    progress: &Progress,
    after: u64,
) -> Result<Assignment, tonic::Status> {
    loop {
        let request = AwaitAssignmentRequest {
            worker_id: progress.worker.load(Ordering::SeqCst),
            after_generation: after,
        };
        match client.await_assignment(request).await {
            Ok(reply) => return Ok(reply.into_inner()),
            Err(status) if status.code() == tonic::Code::Unavailable => {
                tracing::warn!("coordinator unavailable; retrying");
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
            Err(status) => return Err(status),
        }
    }
}

async fn heartbeats(mut client: Client, progress: Arc<Progress>, interval: Duration) {
    loop {
        tokio::time::sleep(interval).await;
        let generation = progress.generation.load(Ordering::SeqCst);
        let request = HeartbeatRequest {
            worker_id: progress.worker.load(Ordering::SeqCst),
            generation,
            step: progress.step.load(Ordering::SeqCst),
        };
        match client.heartbeat(request).await {
            Ok(reply) => {
                progress.metrics.add(&metrics::HEARTBEATS, &[], 1.0);
                let reply = reply.into_inner();
                if !reply.generation_current
                    && generation == progress.generation.load(Ordering::SeqCst)
                    && !*progress.cancel.borrow()
                {
                    progress.cancel.send_replace(true);
                }
            }
            Err(status) => {
                progress.metrics.add(&metrics::HEARTBEAT_FAILURES, &[], 1.0);
                tracing::warn!(error = %status.message(), "heartbeat failed");
            }
        }
    }
}

fn choose_backend(requested: &str) -> anyhow::Result<BackendChoice> {
    match requested {
        "cpu" => Ok(BackendChoice::Cpu),
        "wgpu" => Ok(BackendChoice::Wgpu),
        "auto" | "" => Ok(
            if ["/dev/nvidiactl", "/dev/kfd"]
                .iter()
                .any(|p| Path::new(p).exists())
            {
                BackendChoice::Wgpu
            } else {
                BackendChoice::Cpu
            },
        ),
        other => bail!("device `{other}`: expected auto, cpu or wgpu"),
    }
}

/// Trains the assigned stage from its resume point to its end as one rank of the group.
fn train_generation(
    runtime: &Runtime,
    client: &mut Client,
    options: &WorkerOptions,
    link: &Link,
    mailbox: &crate::collective::Mailbox,
    progress: &Progress,
    assignment: &Assignment,
) -> anyhow::Result<Ending> {
    let rank = assignment.rank as usize;
    let world = assignment.world_size as usize;
    let model_config: XFactorConfig =
        serde_json::from_str(&assignment.model_config_json).context("assignment's model config")?;
    let mut train: TrainConfig = serde_json::from_str(&assignment.train_config_json)
        .context("assignment's trainer config")?;
    let data: DataSpec =
        serde_json::from_str(&assignment.data_json).context("assignment's data spec")?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    train.shards = options
        .threads
        .or((train.shards > 0).then_some(train.shards))
        .unwrap_or(cores);
    let backend = choose_backend(options.device.as_deref().unwrap_or(&assignment.device))?;
    let device = backend.device().autodiff();
    let scratch = options
        .scratch
        .join(format!("worker-{}", progress.worker.load(Ordering::SeqCst)));
    let lpips = if assignment.lpips_weights.is_empty() {
        None
    } else {
        Some(
            Lpips::from_file(Path::new(&assignment.lpips_weights), &device)
                .with_context(|| format!("LPIPS weights {}", assignment.lpips_weights))?,
        )
    };
    let mut trainer = if !assignment.resume_from.is_empty() {
        let dir = scratch.join("resume");
        let _ = std::fs::remove_dir_all(&dir);
        runtime.block_on(checkpoints::download(&assignment.resume_from, &dir))?;
        Trainer::resume(train.clone(), &dir, lpips, &device)
            .with_context(|| format!("resuming from {}", assignment.resume_from))?
    } else if !assignment.init_weights_from.is_empty() {
        let dir = scratch.join("init");
        let _ = std::fs::remove_dir_all(&dir);
        runtime.block_on(checkpoints::download(&assignment.init_weights_from, &dir))?;
        Trainer::from_weights(train.clone(), &dir, lpips, &device)
            .with_context(|| format!("initial weights from {}", assignment.init_weights_from))?
    } else {
        let model = XFactor::new(&model_config, train.seed, &device)?;
        Trainer::new(train.clone(), model_config, model, lpips, &device)?
    };
    tracing::info!(
        backend = backend.name(),
        threads = train.shards,
        start_step = trainer.step(),
        total_steps = assignment.total_steps,
        "training"
    );
    let (first, count) = rank_slice(train.global_batch, world, rank);
    let rank_source = runtime.block_on(RankSource::open(&data, world, rank))?;
    let shard = rank_source.shard_at(trainer.step());
    if !shard.is_empty() {
        tracing::info!(sequences = shard.len(), "data shard of this epoch");
    }
    let schedule = Schedule {
        start_step: trainer.step(),
        first_sample: first,
        global_batch: count,
        micro_batch: train.micro_batch,
    };
    let micro_batches_per_step = count.div_ceil(train.micro_batch.max(1));
    let source = Prefetched::new(rank_source, schedule, 2 * micro_batches_per_step, 1);
    let mut ring = runtime.block_on(Ring::connect(
        mailbox,
        rank,
        &assignment.peers,
        assignment.generation,
        link,
        progress.cancel.subscribe(),
    ))?;
    let registry = &progress.metrics;
    registry.set(&metrics::STAGE, &[], f64::from(assignment.stage));
    registry.set(&metrics::RANK, &[], f64::from(assignment.rank));
    registry.set(&metrics::GENERATION, &[], assignment.generation as f64);
    while trainer.step() < assignment.total_steps {
        let step = trainer.step();
        let _span = tracing::info_span!("step", step).entered();
        if *progress.stopping.borrow() {
            tracing::info!(step, "stopping before this step; nothing of it was applied");
            return Ok(Ending::Stopping);
        }
        if *progress.cancel.borrow() {
            bail!(
                "the coordinator abandoned generation {}",
                assignment.generation
            );
        }
        let started = Instant::now();
        let (loss, grads) = trainer
            .slice_gradients(&source, first, count)
            .with_context(|| format!("gradients of step {step}"))?;
        let mut flat = flatten_gradients(trainer.model(), &grads);
        flat.push(loss);
        let (returned, mut flat, reduce) = ring
            .all_reduce_on(runtime, flat)
            .with_context(|| format!("all-reduce of step {step}"))?;
        ring = returned;
        let loss = flat.pop().unwrap_or(f32::NAN);
        let grads = unflatten_gradients(trainer.model(), &flat)?;
        let outcome = trainer.apply_gradients(&grads, loss);
        let done = trainer.step();
        progress.step.store(done, Ordering::SeqCst);
        let checksum_due =
            done.is_multiple_of(assignment.checksum_every.max(1)) || done == assignment.total_steps;
        let checksum = checksum_due.then(|| parameter_checksum(trainer.model()));
        let elapsed = started.elapsed().as_secs_f64();
        tracing::info!(
            loss = outcome.loss,
            lr = outcome.learning_rate,
            grad_norm = outcome.grad_norm,
            step_s = elapsed,
            allreduce_s = reduce.seconds,
            "step done"
        );
        let skipped_frames = source.inner().skipped_frames();
        registry.set(&metrics::STEP, &[], done as f64);
        registry.set(&metrics::LOSS, &[], f64::from(outcome.loss));
        registry.set(&metrics::LEARNING_RATE, &[], outcome.learning_rate);
        registry.set(&metrics::GRAD_NORM, &[], outcome.grad_norm);
        registry.set(&metrics::STEP_SECONDS, &[], elapsed);
        registry.set(
            &metrics::SAMPLES_PER_SECOND,
            &[],
            count as f64 / elapsed.max(1e-9),
        );
        registry.set(&metrics::ALLREDUCE_SECONDS, &[], reduce.seconds);
        if reduce.seconds > 0.0 {
            let bytes = (flat.len() * std::mem::size_of::<f32>()) as f64;
            registry.set(&metrics::ALLREDUCE_BANDWIDTH, &[], bytes / reduce.seconds);
        }
        registry.set(&metrics::LOADER_QUEUE, &[], source.queued() as f64);
        registry.raise_to(&metrics::SKIPPED_FRAMES, &[], skipped_frames as f64);
        let report = StepReport {
            worker_id: progress.worker.load(Ordering::SeqCst),
            generation: assignment.generation,
            stage: assignment.stage,
            step,
            loss: Some(LossTerms {
                total: outcome.loss,
                learning_rate: outcome.learning_rate,
                grad_norm: outcome.grad_norm,
                applied: outcome.applied,
            }),
            parameter_checksum: checksum.unwrap_or(0),
            checksum_computed: checksum.is_some(),
            samples_per_s: count as f64 / elapsed.max(1e-9),
            allreduce_s: reduce.seconds,
            skipped_frames,
            step_s: elapsed,
        };
        let ack = runtime
            .block_on(client.report_step(report))
            .map_err(|s| anyhow!("step report refused: {}", s.message()))?
            .into_inner();
        if !ack.generation_current {
            bail!("generation {} is no longer current", assignment.generation);
        }
        let commit_due = done.is_multiple_of(assignment.checkpoint_every.max(1))
            || done == assignment.total_steps;
        if rank == 0 && commit_due {
            commit(
                runtime, client, &trainer, &scratch, progress, assignment, done,
            )?;
        }
    }
    Ok(Ending::Done)
}

/// Evaluates the assigned weights (stage 2's final checkpoint) with the job's evaluation spec,
/// uploads the report under the assignment's prefix with its manifest last, and commits it.
fn evaluate(
    runtime: &Runtime,
    client: &mut Client,
    options: &WorkerOptions,
    progress: &Progress,
    assignment: &Assignment,
) -> anyhow::Result<Ending> {
    let spec: evaluation::EvaluationSpec = serde_json::from_str(&assignment.evaluation_json)
        .context("assignment's evaluation spec")?;
    let backend = choose_backend(options.device.as_deref().unwrap_or(&assignment.device))?;
    let scratch = options
        .scratch
        .join(format!("worker-{}", progress.worker.load(Ordering::SeqCst)));
    let weights_dir = scratch.join("evaluate-weights");
    let report_dir = scratch.join("evaluation");
    for dir in [&weights_dir, &report_dir] {
        let _ = std::fs::remove_dir_all(dir);
    }
    runtime.block_on(checkpoints::download(
        &assignment.init_weights_from,
        &weights_dir,
    ))?;
    if *progress.stopping.borrow() {
        return Ok(Ending::Stopping);
    }
    tracing::info!(weights = %assignment.init_weights_from, "evaluating");
    let report = evaluation::run_evaluation(
        &spec,
        &weights_dir.join("model.safetensors"),
        &report_dir,
        &backend.device(),
    )
    .with_context(|| format!("evaluating {}", assignment.init_weights_from))?;
    tracing::info!(
        seconds = report.seconds,
        "evaluation done; report.json, report.md and figures written"
    );
    let location = format!(
        "{}/g{}",
        assignment.checkpoint_prefix, assignment.generation
    );
    runtime.block_on(checkpoints::upload(
        &report_dir,
        &location,
        assignment.stage,
        assignment.total_steps,
    ))?;
    let ack = runtime
        .block_on(client.commit_checkpoint(CheckpointCommit {
            worker_id: progress.worker.load(Ordering::SeqCst),
            generation: assignment.generation,
            stage: assignment.stage,
            step: assignment.total_steps,
            location: location.clone(),
        }))
        .map_err(|s| anyhow!("commit of {location} failed: {}", s.message()))?
        .into_inner();
    if !ack.accepted {
        bail!("commit of {location} refused: {}", ack.reason);
    }
    tracing::info!(%location, "evaluation report committed");
    Ok(Ending::Done)
}

fn commit(
    runtime: &Runtime,
    client: &mut Client,
    trainer: &Trainer,
    scratch: &Path,
    progress: &Progress,
    assignment: &Assignment,
    step: u64,
) -> anyhow::Result<()> {
    let _span = tracing::info_span!("checkpoint", step).entered();
    let dir = scratch.join("save");
    let _ = std::fs::remove_dir_all(&dir);
    trainer.save_checkpoint(&dir)?;
    let location = format!(
        "{}/step-{step:08}-g{}",
        assignment.checkpoint_prefix, assignment.generation
    );
    runtime.block_on(checkpoints::upload(&dir, &location, assignment.stage, step))?;
    let ack = runtime
        .block_on(client.commit_checkpoint(CheckpointCommit {
            worker_id: progress.worker.load(Ordering::SeqCst),
            generation: assignment.generation,
            stage: assignment.stage,
            step,
            location: location.clone(),
        }))
        .map_err(|s| anyhow!("commit of {location} failed: {}", s.message()))?
        .into_inner();
    if !ack.accepted {
        bail!("commit of {location} refused: {}", ack.reason);
    }
    tracing::info!(%location, "checkpoint committed");
    Ok(())
}
