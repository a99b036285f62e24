//! The Coordinator gRPC service over the job state, and the loop that runs a job to its end.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use proto::v1::coordinator_server::{Coordinator, CoordinatorServer};
use proto::v1::{
    Assignment, AwaitAssignmentRequest, CheckpointCommit, CommitAck, HeartbeatReply,
    HeartbeatRequest, JobStatus, LeaveReply, LeaveRequest, RegisterReply, RegisterRequest,
    StatusRequest, StepAck, StepReport,
};
use tokio::sync::{Mutex, Notify};
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status};
use tracing::Instrument;
use trainer_core::XFactorConfig;
use trainer_core::data::store::DataRoot;

use telemetry::Registry;

use crate::job::{Commit, Durable, EVALUATE_STAGE, JobState, Report, Timing};
use crate::metrics;
use crate::plan::Plan;

/// Name of the job-state object under the checkpoint URI.
const DURABLE_OBJECT: &str = "job.json";

/// The service: shared job state plus a signal for waiters.
#[derive(Clone)]
pub struct CoordinatorService {
    state: Arc<Mutex<JobState>>,
    changed: Arc<Notify>,
    checkpoints: DataRoot,
    heartbeat_interval_s: f64,
    metrics: Arc<Registry>,
}

/// Why a job could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The listen address is not `host:port`.
    #[error("listen address `{0}` is not host:port")]
    Address(String),
    /// The checkpoint store could not be opened or read.
    #[error("checkpoint store: {0}")]
    Store(String),
    /// The server failed.
    #[error("gRPC server: {0}")]
    Transport(String),
    /// The TLS files in the YAML could not be used.
    #[error("tls: {0}")]
    Tls(String),
}

impl CoordinatorService {
    /// A service over `plan`; reads the checkpoint store's `job.json` so a restarted
    /// coordinator continues where the last one committed.
    pub async fn new(plan: Plan) -> Result<Self, ServeError> {
        let config = &plan.config;
        let checkpoints = DataRoot::create(&config.checkpoint.uri.0)
            .map_err(|e| ServeError::Store(e.to_string()))?;
        let durable = match checkpoints.read(DURABLE_OBJECT).await {
            Ok(bytes) => {
                let durable: Durable = serde_json::from_slice(&bytes).map_err(|e| {
                    ServeError::Store(format!(
                        "{}/{DURABLE_OBJECT} is not a job state: {e}",
                        checkpoints.uri()
                    ))
                })?;
                if durable.job != config.job.0 {
                    return Err(ServeError::Store(format!(
                        "{}/{DURABLE_OBJECT} belongs to job `{}`, not `{}`: use another checkpoint.uri",
                        checkpoints.uri(),
                        durable.job,
                        config.job.0
                    )));
                }
                tracing::info!(stage = durable.stage, last_commit = ?durable.last_commit, "resuming the job from its checkpoint store");
                Some(durable)
            }
            Err(_) => None,
        };
        let workers = &config.workers;
        let timing = Timing {
            heartbeat_timeout: Duration::from_secs_f64(workers.heartbeat_timeout_s.0),
            quorum_timeout: Duration::from_secs_f64(workers.quorum_timeout_s.0),
            regroup_grace: Duration::from_secs_f64(workers.regroup_grace_s.0),
        };
        let heartbeat_interval_s = workers.heartbeat_interval_s.0;
        Ok(Self {
            state: Arc::new(Mutex::new(JobState::new(plan, timing, durable))),
            changed: Arc::new(Notify::new()),
            checkpoints,
            heartbeat_interval_s,
            metrics: Arc::new(Registry::new()),
        })
    }

    /// The series this service publishes, for the `/metrics` endpoint.
    pub fn metrics(&self) -> Arc<Registry> {
        Arc::clone(&self.metrics)
    }

    fn publish(&self, state: &JobState) {
        let live: Vec<String> = state.live_workers().iter().map(u64::to_string).collect();
        metrics::forget_departed(&self.metrics, &live);
        metrics::record_status(
            &self.metrics,
            &state.status(),
            state.durable().stage,
            state.group_throughput(),
            state.mismatches(),
        );
    }

    /// Writes `curves/stage{stage}.csv` and `.png` under the checkpoint URI. A failure is
    /// logged, not fatal: the curves are a convenience, the report holds every step.
    async fn write_curves(&self, stage: u32) {
        let curve = self.state.lock().await.curve(stage);
        let csv = format!("curves/stage{stage}.csv");
        let png = format!("curves/stage{stage}.png");
        let written = async {
            self.checkpoints
                .write(&csv, curve.to_csv().into_bytes())
                .await
                .map_err(|e| e.to_string())?;
            let image = curve.to_png().map_err(|e| e.to_string())?;
            self.checkpoints
                .write(&png, image)
                .await
                .map_err(|e| e.to_string())
        };
        match written.await {
            Ok(()) => {
                tracing::info!(stage, steps = curve.rows.len(), uri = %self.checkpoints.uri(), "loss curves written under curves/")
            }
            Err(error) => tracing::warn!(stage, %error, "loss curves not written"),
        }
    }

    /// Runs the job: serves RPCs, ticks the state machine, and returns the report once both
    /// stages are done (after giving workers a moment to hear so), or when `shutdown` fires.
    pub async fn run(
        self,
        token: &str,
        shutdown: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> Result<Report, ServeError> {
        let listen = self.state.lock().await.plan().config.listen.0.clone();
        let address: SocketAddr = tokio::net::lookup_host(&listen)
            .await
            .ok()
            .and_then(|mut a| a.next())
            .ok_or_else(|| ServeError::Address(listen.clone()))?;
        let server = InterceptedService::new(
            CoordinatorServer::new(self.clone())
                .max_decoding_message_size(proto::MAX_MESSAGE_BYTES)
                .max_encoding_message_size(proto::MAX_MESSAGE_BYTES),
            proto::RequireToken::new(token),
        );
        let tls = self.state.lock().await.plan().config.tls.clone();
        let mut builder = tonic::transport::Server::builder();
        if let Some(tls) = tls {
            let settings = proto::tls::server_config(Path::new(&tls.cert.0), Path::new(&tls.key.0))
                .map_err(|e| ServeError::Tls(e.to_string()))?;
            builder = builder.tls_config(settings).map_err(|e| {
                ServeError::Tls(format!(
                    "certificate {} with key {}: {e}",
                    tls.cert.0, tls.key.0
                ))
            })?;
        }
        let finished = Arc::new(Notify::new());
        let stop_server = finished.clone();
        let serve = tokio::spawn(
            builder
                .add_service(server)
                .serve_with_shutdown(address, async move { stop_server.notified().await }),
        );
        tracing::info!(%address, "coordinator listening");
        let ticker = {
            let service = self.clone();
            async move {
                let mut stage = service.state.lock().await.durable().stage;
                loop {
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    let (changed, done, now_stage) = {
                        let mut state = service.state.lock().await;
                        let changed = state.tick(Instant::now());
                        service.publish(&state);
                        (changed, state.finished(), state.durable().stage)
                    };
                    if changed {
                        service.changed.notify_waiters();
                    }
                    for finished_stage in stage..now_stage.min(EVALUATE_STAGE) {
                        service.write_curves(finished_stage).await;
                    }
                    stage = stage.max(now_stage);
                    if done {
                        // Let every worker collect its FINISH before the server goes.
                        tokio::time::sleep(Duration::from_secs_f64(
                            (service.heartbeat_interval_s * 4.0).max(1.0),
                        ))
                        .await;
                        return;
                    }
                }
            }
        };
        tokio::select! {
            () = ticker => {}
            () = shutdown => tracing::warn!("shutdown requested: the job stops; rerun to resume from its last commit"),
        }
        finished.notify_one();
        match serve.await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(ServeError::Transport(e.to_string())),
            Err(e) => return Err(ServeError::Transport(e.to_string())),
        }
        let report = self.state.lock().await.report();
        Ok(report)
    }

    /// Checks that every file a checkpoint's `COMMIT.json` lists exists with its size.
    async fn verify(location: &str) -> Result<(), String> {
        let root = DataRoot::open(location).map_err(|e| e.to_string())?;
        let manifest = root
            .read("COMMIT.json")
            .await
            .map_err(|e| format!("no COMMIT.json at {location}: {e}"))?;
        let manifest: serde_json::Value = serde_json::from_slice(&manifest)
            .map_err(|e| format!("{location}/COMMIT.json is not JSON: {e}"))?;
        let listed = root.list().await.map_err(|e| e.to_string())?;
        let files = manifest["files"]
            .as_array()
            .ok_or_else(|| format!("{location}/COMMIT.json lists no files"))?;
        for file in files {
            let (Some(name), Some(size)) = (file["name"].as_str(), file["bytes"].as_u64()) else {
                return Err(format!(
                    "{location}/COMMIT.json has a malformed entry {file}"
                ));
            };
            match listed.iter().find(|l| l.path == name) {
                Some(found) if found.size == size => {}
                Some(found) => {
                    return Err(format!(
                        "{location}/{name} holds {} bytes, COMMIT.json says {size}",
                        found.size
                    ));
                }
                None => return Err(format!("{location}/{name} is missing")),
            }
        }
        Ok(())
    }
}

#[tonic::async_trait]
impl Coordinator for CoordinatorService {
    async fn register(
        &self,
        request: Request<RegisterRequest>,
    ) -> Result<Response<RegisterReply>, Status> {
        let request = request.into_inner();
        let span = tracing::info_span!("rpc_register", worker = %request.worker_name);
        self.admit(request).instrument(span).await
    }

    async fn await_assignment(
        &self,
        request: Request<AwaitAssignmentRequest>,
    ) -> Result<Response<Assignment>, Status> {
        let request = request.into_inner();
        let span = tracing::debug_span!("rpc_await_assignment", worker = request.worker_id);
        self.assign(request).instrument(span).await
    }

    async fn heartbeat(
        &self,
        request: Request<HeartbeatRequest>,
    ) -> Result<Response<HeartbeatReply>, Status> {
        let request = request.into_inner();
        let span = tracing::trace_span!("rpc_heartbeat", worker = request.worker_id);
        async {
            let (known, generation_current) = self.state.lock().await.heartbeat(
                request.worker_id,
                request.generation,
                Instant::now(),
            );
            self.metrics.add(&metrics::HEARTBEATS, &[], 1.0);
            Ok(Response::new(HeartbeatReply {
                generation_current,
                known,
            }))
        }
        .instrument(span)
        .await
    }

    async fn report_step(&self, request: Request<StepReport>) -> Result<Response<StepAck>, Status> {
        let report = request.into_inner();
        let span = tracing::debug_span!(
            "rpc_report_step",
            worker = report.worker_id,
            step = report.step
        );
        async {
            let mut state = self.state.lock().await;
            state.heartbeat(report.worker_id, report.generation, Instant::now());
            let generation_current = state.report_step(report.worker_id, &report);
            if generation_current {
                let rank0 = state.is_rank0(report.worker_id);
                metrics::record_step(&self.metrics, &report, rank0);
            }
            Ok(Response::new(StepAck { generation_current }))
        }
        .instrument(span)
        .await
    }

    async fn commit_checkpoint(
        &self,
        request: Request<CheckpointCommit>,
    ) -> Result<Response<CommitAck>, Status> {
        let commit = request.into_inner();
        let span = tracing::info_span!("rpc_commit", stage = commit.stage, step = commit.step);
        self.record_commit(commit).instrument(span).await
    }

    async fn status(
        &self,
        _request: Request<StatusRequest>,
    ) -> Result<Response<JobStatus>, Status> {
        let status = async { self.state.lock().await.status() }
            .instrument(tracing::debug_span!("rpc_status"))
            .await;
        Ok(Response::new(status))
    }

    async fn leave(&self, request: Request<LeaveRequest>) -> Result<Response<LeaveReply>, Status> {
        let request = request.into_inner();
        let span = tracing::info_span!("rpc_leave", worker = request.worker_id);
        async {
            let known = {
                let mut state = self.state.lock().await;
                let known = state.leave(request.worker_id, &request.reason);
                if known && state.tick(Instant::now()) {
                    self.changed.notify_waiters();
                }
                known
            };
            if known {
                Ok(Response::new(LeaveReply {}))
            } else {
                Err(Status::not_found(format!(
                    "worker {} is not a member of this job",
                    request.worker_id
                )))
            }
        }
        .instrument(span)
        .await
    }
}

impl CoordinatorService {
    async fn admit(&self, request: RegisterRequest) -> Result<Response<RegisterReply>, Status> {
        if request.protocol_version != proto::PROTOCOL_VERSION {
            return Err(Status::failed_precondition(format!(
                "protocol version {} refused: this coordinator speaks version {}; run matching builds",
                request.protocol_version,
                proto::PROTOCOL_VERSION
            )));
        }
        if request.model_config_version != XFactorConfig::SCHEMA_VERSION {
            return Err(Status::failed_precondition(format!(
                "model-config version {} refused: this coordinator uses version {}",
                request.model_config_version,
                XFactorConfig::SCHEMA_VERSION
            )));
        }
        let mut state = self.state.lock().await;
        if !request.expected_model_config_json.is_empty() {
            let job = serde_json::to_value(&state.plan().model)
                .map_err(|e| Status::internal(e.to_string()))?;
            let worker: serde_json::Value =
                serde_json::from_str(&request.expected_model_config_json).map_err(|e| {
                    Status::invalid_argument(format!("expected_model_config_json is not JSON: {e}"))
                })?;
            let differences = differing_fields(&job, &worker);
            if !differences.is_empty() {
                return Err(Status::failed_precondition(format!(
                    "model config differs from the job's: {}",
                    differences.join(", ")
                )));
            }
        }
        if request.collective_address.is_empty() {
            return Err(Status::invalid_argument("collective_address is empty"));
        }
        let id = state.register(
            request.worker_name,
            request.collective_address,
            Instant::now(),
        );
        let job_name = state.plan().config.job.0.clone();
        drop(state);
        self.changed.notify_waiters();
        Ok(Response::new(RegisterReply {
            worker_id: id,
            job_name,
            heartbeat_interval_s: self.heartbeat_interval_s,
        }))
    }

    async fn assign(
        &self,
        request: AwaitAssignmentRequest,
    ) -> Result<Response<Assignment>, Status> {
        loop {
            let notified = self.changed.notified();
            {
                let mut state = self.state.lock().await;
                match state.request_assignment(
                    request.worker_id,
                    request.after_generation,
                    Instant::now(),
                ) {
                    Err(message) => return Err(Status::not_found(message)),
                    Ok(Some(assignment)) => return Ok(Response::new(assignment)),
                    Ok(None) => {}
                }
                if state.tick(Instant::now()) {
                    self.changed.notify_waiters();
                }
            }
            let _ = tokio::time::timeout(Duration::from_millis(200), notified).await;
        }
    }

    async fn record_commit(&self, commit: CheckpointCommit) -> Result<Response<CommitAck>, Status> {
        let refused = |reason: String| {
            tracing::warn!(%reason, "commit refused");
            Ok(Response::new(CommitAck {
                accepted: false,
                reason,
            }))
        };
        if let Err(reason) = Self::verify(&commit.location).await {
            return refused(reason);
        }
        let durable = {
            let mut state = self.state.lock().await;
            let accepted = state.commit(
                commit.worker_id,
                Commit {
                    stage: commit.stage,
                    step: commit.step,
                    location: commit.location.clone(),
                },
                commit.generation,
            );
            if let Err(reason) = accepted {
                return refused(reason);
            }
            self.metrics.add(&metrics::COMMITS, &[], 1.0);
            state.durable().clone()
        };
        let json =
            serde_json::to_vec_pretty(&durable).map_err(|e| Status::internal(e.to_string()))?;
        self.checkpoints
            .write(DURABLE_OBJECT, json)
            .await
            .map_err(|e| Status::unavailable(format!("recording the commit failed: {e}")))?;
        self.changed.notify_waiters();
        Ok(Response::new(CommitAck {
            accepted: true,
            reason: String::new(),
        }))
    }
}

/// `key: job vs worker` for every field whose value differs.
fn differing_fields(job: &serde_json::Value, worker: &serde_json::Value) -> Vec<String> {
    let (Some(job), Some(worker)) = (job.as_object(), worker.as_object()) else {
        return vec![format!("job {job} vs worker {worker}")];
    };
    let mut keys: Vec<&String> = job.keys().chain(worker.keys()).collect();
    keys.sort();
    keys.dedup();
    keys.into_iter()
        .filter(|k| job.get(*k) != worker.get(*k))
        .map(|k| {
            let show =
                |v: Option<&serde_json::Value>| v.map_or("(absent)".to_string(), |v| v.to_string());
            format!(
                "{k}: job {} vs worker {}",
                show(job.get(k)),
                show(worker.get(k))
            )
        })
        .collect()
}
