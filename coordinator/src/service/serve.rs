//! Serving a job to its end: the gRPC server (the Coordinator service behind the job-token
//! check, the health service beside it), the ticker that drives the state machine and keeps the
//! lease, and the orderly stop that writes the last records before the server goes.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use proto::v1::coordinator_server::CoordinatorServer;
use settings::Phase;
use tokio::sync::{Mutex, Notify};
use tokio::task::JoinHandle;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Server;

use super::{CoordinatorService, Recorders, ServeError, history, lease, store, tensorboard};
use crate::health::JobHealth;
use crate::job::Report;

/// How often the state machine ticks: short enough that a lost worker or a formed group is
/// acted on at once, long enough that the ticker costs nothing next to a training step.
const TICK_EVERY: Duration = Duration::from_millis(50);

/// The spawned gRPC server, and what stops it.
pub(super) struct RunningServer {
    /// What probes are told about the job.
    pub(super) health: JobHealth,
    /// Notified to start the server's graceful shutdown.
    shutdown: Arc<Notify>,
    /// The server task, ending once the graceful shutdown has drained the open calls.
    task: JoinHandle<Result<(), tonic::transport::Error>>,
}

impl CoordinatorService {
    /// Starts serving on the YAML's `listen` address: the Coordinator service behind the
    /// job-token check, and the health service outside it, since probes carry no token.
    pub(super) async fn start_server(&self, token: &str) -> Result<RunningServer, ServeError> {
        let address = self.listen_address().await?;
        let mut builder = self.server_builder().await?;
        let coordinator = InterceptedService::new(
            CoordinatorServer::new(self.clone())
                .max_decoding_message_size(proto::MAX_MESSAGE_BYTES)
                .max_encoding_message_size(proto::MAX_MESSAGE_BYTES),
            proto::RequireToken::new(token),
        );
        let shutdown = Arc::new(Notify::new());
        let stop_serving = shutdown.clone();
        let (health, health_server) = JobHealth::new().await;
        let task = tokio::spawn(
            builder
                .add_service(coordinator)
                .add_service(health_server)
                .serve_with_shutdown(address, async move { stop_serving.notified().await }),
        );
        tracing::info!(%address, "coordinator listening");
        Ok(RunningServer {
            health,
            shutdown,
            task,
        })
    }

    /// The socket address of the YAML's `listen` key, a host name looked up.
    async fn listen_address(&self) -> Result<SocketAddr, ServeError> {
        let listen = self.state.lock().await.plan().config.listen.0.clone();
        tokio::net::lookup_host(&listen)
            .await
            .ok()
            .and_then(|mut addresses| addresses.next())
            .ok_or_else(|| ServeError::Address(listen.clone()))
    }

    /// The transport, serving TLS with the YAML's certificate when it names one.
    async fn server_builder(&self) -> Result<Server, ServeError> {
        let builder = Server::builder();
        let Some(tls) = self.state.lock().await.plan().config.tls.clone() else {
            return Ok(builder);
        };
        let failed = |source: Box<dyn std::error::Error + Send + Sync>| ServeError::Tls {
            cert: tls.cert.0.clone(),
            key: tls.key.0.clone(),
            source,
        };
        let settings = proto::tls::server_config(Path::new(&tls.cert.0), Path::new(&tls.key.0))
            .map_err(|e| failed(e.into()))?;
        builder.tls_config(settings).map_err(|e| failed(e.into()))
    }

    /// The step history and the TensorBoard runs under the checkpoint URI, each training
    /// stage's run starting with the resolved configuration it trains with. The steps an
    /// earlier coordinator of this job recorded are read back first, so the report and the
    /// curves cover the whole run, not only the steps since this start.
    pub(super) async fn open_recorders(&self) -> Result<Mutex<Recorders>, ServeError> {
        let earlier = history::History::read_all(&self.checkpoints)
            .await
            .map_err(ServeError::OpenStore)?;
        if !earlier.is_empty() {
            tracing::info!(
                steps = earlier.len(),
                "step history of earlier runs read back"
            );
            self.state.lock().await.restore_history(earlier);
        }
        let mut recorders = Recorders {
            history: history::History::open(self.checkpoints.clone())
                .await
                .map_err(ServeError::OpenStore)?,
            board: tensorboard::TensorBoard::new(self.checkpoints.clone()),
        };
        let (config, stages) = {
            let state = self.state.lock().await;
            (
                tensorboard::resolved_config(state.plan()),
                state.plan().trained_stages(),
            )
        };
        for stage in stages {
            recorders.board.record_config(stage, &config);
        }
        Ok(Mutex::new(recorders))
    }

    /// Ticks the job until it is done, writing each training stage's curves as it ends, then
    /// sees the workers off. Returns the lease error if another coordinator took the job over
    /// meanwhile (this one must then stop without touching the store again).
    pub(super) async fn tick_until_done(
        &self,
        health: &JobHealth,
        recorders: &Mutex<Recorders>,
    ) -> Option<lease::LeaseError> {
        let (mut phase, stages) = {
            let state = self.state.lock().await;
            (state.phase(), state.plan().trained_stages())
        };
        let mut renewed = Instant::now();
        loop {
            tokio::time::sleep(TICK_EVERY).await;
            if let Err(lost) = self.keep_lease(&mut renewed).await {
                return Some(lost);
            }
            let (done, now_phase) = self.tick_job(recorders).await;
            for &stage in &stages {
                if phase <= stage && stage < now_phase {
                    self.write_curves(stage).await;
                }
            }
            phase = phase.max(now_phase);
            if done {
                self.see_workers_off(health, recorders).await;
                return None;
            }
        }
    }

    /// Renews the lease once [`lease::RENEW_EVERY`] has passed since `renewed`. A renewal that
    /// merely failed is retried at the next tick; a lease lost to another coordinator is
    /// returned.
    async fn keep_lease(&self, renewed: &mut Instant) -> Result<(), lease::LeaseError> {
        if renewed.elapsed() < lease::RENEW_EVERY {
            return Ok(());
        }
        match self.lease.renew().await {
            Ok(()) => *renewed = Instant::now(),
            Err(lost @ lease::LeaseError::Lost { .. }) => return Err(lost),
            Err(error) => {
                tracing::warn!(error = %store::chain(&error), "lease not renewed; retrying");
            }
        }
        Ok(())
    }

    /// One tick of the state machine: publishes the metrics, records the steps that finished,
    /// and wakes the waiting RPCs when something changed. Returns whether the job is done, and
    /// its phase.
    async fn tick_job(&self, recorders: &Mutex<Recorders>) -> (bool, Phase) {
        let (changed, done, phase, records) = {
            let mut state = self.state.lock().await;
            let changed = state.tick(Instant::now());
            self.publish(&state);
            let done = state.finished();
            (changed, done, state.phase(), state.take_history(done))
        };
        self.append_history(recorders, &records).await;
        if changed {
            self.changed.notify_waiters();
        }
        (done, phase)
    }

    /// The job is done: records its evaluation, tells probes, and lets every worker collect its
    /// FINISH (a few heartbeats) before the server goes.
    async fn see_workers_off(&self, health: &JobHealth, recorders: &Mutex<Recorders>) {
        self.record_evaluation(recorders).await;
        health.job_ending().await;
        let heartbeats = Duration::try_from_secs_f64(self.heartbeat_interval_s * 4.0)
            .unwrap_or(Duration::ZERO)
            .clamp(Duration::from_secs(1), Duration::from_secs(60));
        tokio::time::sleep(heartbeats).await;
    }

    /// Stops the job however it ended: releases the long-polling RPCs, writes the last steps
    /// and any failure, shuts the server down, and returns the report, or the lease error when
    /// the job was `fenced` by another coordinator (whose lease is then left alone).
    pub(super) async fn stop(
        &self,
        server: RunningServer,
        recorders: &Mutex<Recorders>,
        fenced: Option<lease::LeaseError>,
    ) -> Result<Report, ServeError> {
        self.stopping.cancel();
        let records = self.state.lock().await.take_history(true);
        self.append_history(recorders, &records).await;
        self.record_failure().await;
        let RunningServer {
            health,
            shutdown,
            task,
        } = server;
        health.job_ending().await;
        health.close().await;
        shutdown.notify_one();
        task.await
            .map_err(ServeError::Task)?
            .map_err(ServeError::Transport)?;
        if let Some(lost) = fenced {
            tracing::error!(error = %lost, "another coordinator took this job over");
            return Err(ServeError::Lease(lost));
        }
        self.lease.release().await;
        let report = self.state.lock().await.report();
        Ok(report)
    }
}
