//! The worker's life: register, await an assignment, do it (train one rank of a group, or
//! evaluate), and go back for the next, until the coordinator says the job is done. The layers
//! it drives live beside this file: `session` (coordinator RPCs and heartbeats), `training`
//! and `evaluate` (one generation's work), `failure` (whose fault a failed generation was),
//! `shutdown` (signals).

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use anyhow::{Context, bail};
use settings::work::{Assignment, GenerationFailure, Work};
use tokio::runtime::Runtime;

use crate::collective::{CollectiveService, Link, server};
use crate::context::{Ending, WorkerContext};
use crate::options::{WorkerOptions, WorkerTls};
use crate::progress::Progress;
use crate::session::{
    AwaitError, Client, await_assignment, connect, heartbeats, leave, register, say_goodbye,
};
use crate::shutdown::Shutdown;
use crate::streaks::{AfterFailure, Blame, FailureStreaks, jitter};
use crate::{device, evaluate, failure, health, metrics, training};

/// The reason a worker gives the coordinator when a signal makes it leave.
const SIGNALLED: &str = "SIGTERM";

/// Runs the worker until the job finishes. Blocking; owns its async runtime, and ends every
/// task it started before it returns.
pub fn run(options: WorkerOptions) -> anyhow::Result<()> {
    let progress = Arc::new(Progress::new());
    if let Some(choice) = options.device {
        // A device this host lacks is refused before the worker reaches for anything else.
        device::resolve(choice, &progress.metrics)?;
    }
    // One I/O thread: RPCs, heartbeats and the collective streams are light, and the ring
    // all-reduce runs fastest when its chunks never change threads. Training uses its own.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let shutdown = Shutdown::default();
    let served = join_and_serve(&runtime, &shutdown, &options, &progress);
    shutdown.join(&runtime);
    served
}

/// Starts the servers, the signal watcher and the heartbeats as tasks of `shutdown`, joins the
/// job and serves it until it ends.
fn join_and_serve(
    runtime: &Runtime,
    shutdown: &Shutdown,
    options: &WorkerOptions,
    progress: &Arc<Progress>,
) -> anyhow::Result<()> {
    let link = Link {
        token: options.token.clone(),
        timeout: options.collective_timeout,
        tls: options
            .tls
            .as_ref()
            .map(WorkerTls::peers)
            .transpose()?
            .flatten(),
        // Each generation's ring takes its lanes from its assignment (`join_ring`).
        lanes: 0,
    };
    let collective = CollectiveService::default();
    let mailbox = collective.mailbox();
    let (address, health_reporter) = runtime.block_on(serve_collective(
        options, collective, &link, shutdown, runtime,
    ))?;
    let mut client = runtime.block_on(connect(
        &options.coordinator,
        &options.token,
        options.tls.as_ref(),
    ))?;
    if let Some(address) = &options.metrics_address {
        let health = Progress::health(progress);
        let metrics = Arc::clone(&progress.metrics);
        let (_, serving) = runtime.block_on(telemetry::http::bind(address, metrics, health))?;
        shutdown.spawn(runtime, serving);
    }
    let (farewell_client, farewell_progress) = (client.clone(), Arc::clone(progress));
    shutdown.watch_signals(
        runtime,
        options.shutdown_grace,
        Box::new(move || {
            Box::pin(async move {
                let mut client = farewell_client;
                say_goodbye(&mut client, &farewell_progress, SIGNALLED).await;
            })
        }),
    );
    let interval = runtime.block_on(register(&mut client, options, &address, progress))?;
    shutdown.spawn(
        runtime,
        heartbeats(client.clone(), progress.clone(), interval),
    );
    let mirror = health::mirror_membership(health_reporter, progress.clone(), interval);
    shutdown.spawn(runtime, mirror);
    let context = WorkerContext {
        options,
        link: &link,
        mailbox: &mailbox,
        progress,
        shutdown,
    };
    Daemon {
        runtime,
        client,
        context,
        address,
    }
    .serve()
}

/// The worker between assignments.
struct Daemon<'a> {
    runtime: &'a Runtime,
    client: Client,
    context: WorkerContext<'a>,
    /// The collective address it registers with.
    address: String,
}

impl Daemon<'_> {
    /// Awaits assignments and does them until the job is finished, SIGTERM arrives or this
    /// worker failed too many generations in a row by its own fault (`streaks`).
    fn serve(mut self) -> anyhow::Result<()> {
        let mut after = 0;
        let mut streaks = FailureStreaks::default();
        let mut failure: Option<GenerationFailure> = None;
        loop {
            let Some(waited) = self.next_assignment(after, failure.take().as_ref()) else {
                return leave(
                    self.runtime,
                    &mut self.client,
                    self.context.progress,
                    SIGNALLED,
                );
            };
            let assignment = match waited {
                Ok(assignment) => assignment,
                Err(AwaitError::Unknown(reason)) => {
                    tracing::warn!(%reason, "registering again");
                    let (options, progress) = (self.context.options, self.context.progress);
                    self.runtime.block_on(register(
                        &mut self.client,
                        options,
                        &self.address,
                        progress,
                    ))?;
                    after = 0;
                    continue;
                }
                Err(error) => return Err(error.into()),
            };
            after = assignment.generation;
            match self.work(&assignment) {
                Ok(Some(Ending::Done)) => {
                    streaks.succeeded();
                    tracing::info!("generation {after} done");
                }
                Ok(Some(Ending::Stopping)) => {
                    return leave(
                        self.runtime,
                        &mut self.client,
                        self.context.progress,
                        SIGNALLED,
                    );
                }
                Ok(Some(Ending::Suspended)) => {
                    tracing::warn!(
                        "the coordinator suspended the job; exiting (a requeued job resumes from its last commit)"
                    );
                    return Ok(());
                }
                Ok(None) => {
                    tracing::info!("the job is finished");
                    return Ok(());
                }
                Err(error) if self.context.shutdown.is_cancelled() => {
                    tracing::info!(error = %format!("{error:#}"), "the generation ended with the shutdown");
                    return leave(
                        self.runtime,
                        &mut self.client,
                        self.context.progress,
                        SIGNALLED,
                    );
                }
                Err(error) => failure = Some(self.failed(&error, &mut streaks)?),
            }
        }
    }

    /// The next assignment after generation `after`; `None` once SIGTERM arrived.
    fn next_assignment(
        &mut self,
        after: u64,
        failure: Option<&GenerationFailure>,
    ) -> Option<Result<Assignment, AwaitError>> {
        let progress = self.context.progress;
        let shutdown = self.context.shutdown;
        let client = &mut self.client;
        self.runtime.block_on(async {
            tokio::select! {
                assignment = await_assignment(client, progress, after, failure) => Some(assignment),
                () = shutdown.cancelled() => None,
            }
        })
    }

    /// Does one assignment; `None` when it says the job is finished.
    fn work(&mut self, assignment: &Assignment) -> anyhow::Result<Option<Ending>> {
        let generation = assignment.generation;
        let progress = self.context.progress;
        progress.generation.store(generation, Ordering::SeqCst);
        progress.begin_generation(self.context.shutdown.generation());
        let _span = tracing::info_span!("generation", generation).entered();
        let (runtime, client, context) = (self.runtime, &mut self.client, &self.context);
        match &assignment.work {
            Work::Train(work) => {
                training::train_generation(runtime, client, context, generation, work).map(Some)
            }
            Work::Evaluate(work) => {
                evaluate::evaluate(runtime, client, context, generation, work).map(Some)
            }
            Work::Finish => Ok(None),
        }
    }

    /// Counts a failed generation, waits as `streaks` decides when the fault was someone
    /// else's, and builds the report the next request for work carries; gives up only after
    /// [`crate::streaks::MAX_OWN_FAILURES`] own failures in a row.
    fn failed(
        &mut self,
        error: &anyhow::Error,
        streaks: &mut FailureStreaks,
    ) -> anyhow::Result<GenerationFailure> {
        let progress = self.context.progress;
        progress.metrics.add(&metrics::RESTARTS, &[], 1.0);
        let report = failure::report(error);
        if failure::cannot_run_here(error) {
            // No retry can bring a device this build or host lacks: leave now, with the
            // reason, rather than sitting out generation after generation.
            leave(self.runtime, &mut self.client, progress, &report.reason)?;
            bail!(
                "this worker cannot do the job's work on this host, so it left the job: {error:#}"
            );
        }
        tracing::warn!(error = %report.reason, cause = ?report.cause, "generation abandoned");
        let draw = jitter(progress.worker_id(), streaks.in_a_row() + 1);
        let blame = if failure::ended_by_coordinator(error) {
            Blame::Coordinator
        } else {
            Blame::of(&report.cause)
        };
        match streaks.failed(blame, draw) {
            AfterFailure::GiveUp { own_in_a_row } => {
                bail!(
                    "{own_in_a_row} generations in a row failed by this worker's own fault; last error: {error:#}"
                )
            }
            AfterFailure::Retry {
                pause,
                blame,
                in_a_row,
            } if !pause.is_zero() => {
                tracing::warn!(
                    cause = blame.name(),
                    in_a_row,
                    pause_s = pause.as_secs_f64(),
                    "not this worker's fault: waiting, then asking for work again"
                );
                let waiting = [("cause", blame.name())];
                progress.metrics.set(&metrics::WAITING, &waiting, 1.0);
                let shutdown = self.context.shutdown;
                self.runtime.block_on(async {
                    tokio::select! {
                        () = tokio::time::sleep(pause) => {}
                        () = shutdown.cancelled() => {}
                    }
                });
                progress.metrics.set(&metrics::WAITING, &waiting, 0.0);
            }
            AfterFailure::Retry { .. } => {}
        }
        Ok(report)
    }
}

/// Starts the collective service on `--listen` as a task `shutdown` owns; returns the address
/// peers dial and the reporter of its health service.
async fn serve_collective(
    options: &WorkerOptions,
    service: CollectiveService,
    link: &Link,
    shutdown: &Shutdown,
    runtime: &Runtime,
) -> anyhow::Result<(String, tonic_health::server::HealthReporter)> {
    let listener = tokio::net::TcpListener::bind(&options.listen)
        .await
        .with_context(|| format!("cannot listen on {}", options.listen))?;
    let bound: SocketAddr = listener.local_addr()?;
    let (health, serving) = server(listener, service, link)?;
    shutdown.spawn(runtime, serving);
    let advertised = match &options.advertise {
        // A host alone (a Slurm node's name) takes the port bound here.
        Some(host) if !host.contains(':') => format!("{host}:{}", bound.port()),
        Some(address) => address.clone(),
        None => bound.to_string(),
    };
    Ok((advertised, health))
}
