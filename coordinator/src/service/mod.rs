//! The Coordinator gRPC service over the job state, and the loop that runs a job to its end.
//! The RPC handlers are in `rpc`, the checkpoint-store side (job state, commit verification)
//! in `store`.

use std::sync::Arc;
use std::time::{Duration, Instant};

use data::store::{DataRoot, ObjectVersion, StoreError};
use settings::Phase;
use telemetry::Registry;
use tokio::sync::{Mutex, Notify};
use tokio_util::sync::CancellationToken;

use crate::config::NonNegative;
use crate::job::{JobState, Report, StepRecord, Timing};
use crate::metrics;
use crate::plan::Plan;

pub mod history;
pub mod lease;
mod rpc;
mod serve;
mod sessions;
pub mod store;
pub mod tensorboard;

/// The service: shared job state plus a signal for waiters.
#[derive(Clone)]
pub struct CoordinatorService {
    state: Arc<Mutex<JobState>>,
    changed: Arc<Notify>,
    /// Cancelled when the job ends or a stop is requested: long-polling RPCs return at once,
    /// so the server's graceful shutdown does not wait on them.
    stopping: CancellationToken,
    /// Cancelled to suspend the job (SIGUSR1, a batch system's warning before its time limit):
    /// step acknowledgements ask rank 0 to commit and every worker to exit.
    suspending: CancellationToken,
    checkpoints: DataRoot,
    heartbeat_interval_s: f64,
    metrics: Arc<Registry>,
    /// The version of `job.json` this coordinator last read or wrote (see `store::write_durable`).
    durable_version: Arc<Mutex<Option<ObjectVersion>>>,
    /// Each registration's secret, checked on every request that names a worker.
    sessions: Arc<sessions::Sessions>,
    /// Each generation's ring secrets, handed out with training assignments.
    ring_secrets: Arc<sessions::RingSecrets>,
    /// This coordinator's hold on the checkpoint URI.
    lease: Arc<lease::Lease>,
    /// The step history and TensorBoard writers, once opened (`run`): the tick writes the
    /// steps as they seal, and a commit writes every step up to its own before `job.json`.
    recorders: Arc<std::sync::OnceLock<Arc<Mutex<Recorders>>>>,
}

/// Longest wait for rank 0's commit once the job is being suspended.
pub const SUSPEND_LIMIT: Duration = Duration::from_secs(60);

/// What the job's steps are written to as they finish, beside the checkpoints.
struct Recorders {
    /// The step history as JSON lines.
    history: history::History,
    /// The TensorBoard runs.
    board: tensorboard::TensorBoard,
}

/// `workers.<key>` as a `Duration`: the loader bounds every such key (`config/checks.rs`),
/// and a configuration built otherwise is refused here rather than panicking.
fn duration(key: &'static str, seconds: NonNegative) -> Result<Duration, ServeError> {
    Duration::try_from_secs_f64(seconds.0).map_err(|error| ServeError::Duration {
        key,
        reason: error.to_string(),
    })
}

/// Why a job could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The listen address is not `host:port`.
    #[error("listen address `{0}` is not host:port")]
    Address(String),
    /// A duration of `workers:` that no clock holds.
    #[error("workers.{key}: {reason}")]
    Duration {
        /// The key under `workers:`.
        key: &'static str,
        /// Why it is not a duration.
        reason: String,
    },
    /// The checkpoint store could not be opened.
    #[error("checkpoint store")]
    OpenStore(#[source] StoreError),
    /// `job.json` exists but cannot be read: starting over would orphan committed work.
    #[error(
        "{uri}/job.json could not be read; the job does not start over it (fix the store and rerun)"
    )]
    ReadState {
        /// The checkpoint URI.
        uri: String,
        /// What failed.
        #[source]
        source: StoreError,
    },
    /// `job.json` is not a job state.
    #[error("{uri}/job.json is not a job state")]
    CorruptState {
        /// The checkpoint URI.
        uri: String,
        /// The parser's error.
        #[source]
        source: serde_json::Error,
    },
    /// `job.json` belongs to another job.
    #[error(
        "{uri}/job.json belongs to job `{found}`, not `{expected}`: use another checkpoint.uri"
    )]
    OtherJob {
        /// The checkpoint URI.
        uri: String,
        /// The job it belongs to.
        found: String,
        /// This job.
        expected: String,
    },
    /// Another coordinator holds the checkpoint URI, or took it over from this one.
    #[error("coordinator lease")]
    Lease(#[source] lease::LeaseError),
    /// The server failed.
    #[error("gRPC server")]
    Transport(#[source] tonic::transport::Error),
    /// The server task ended abnormally.
    #[error("gRPC server task")]
    Task(#[source] tokio::task::JoinError),
    /// The TLS files in the YAML could not be used.
    #[error("tls: certificate {cert} with key {key}")]
    Tls {
        /// Certificate file.
        cert: String,
        /// Key file.
        key: String,
        /// What was wrong.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

impl CoordinatorService {
    /// A service over `plan`; reads the checkpoint store's `job.json` so a restarted
    /// coordinator continues where the last one committed.
    pub async fn new(plan: Plan) -> Result<Self, ServeError> {
        let config = &plan.config;
        let checkpoints =
            DataRoot::create(&config.checkpoint.uri.0).map_err(ServeError::OpenStore)?;
        // Held before job.json is read, so no other coordinator changes it meanwhile.
        let lease = lease::Lease::claim(checkpoints.clone(), lease::holder_name())
            .await
            .map_err(ServeError::Lease)?;
        let (durable, durable_version) = store::read_durable(&checkpoints, &config.job.0)
            .await?
            .unzip();
        if let Some(durable) = &durable {
            tracing::info!(phase = %durable.phase, last_commit = ?durable.last_commit, "resuming the job from its checkpoint store");
        }
        let workers = &config.workers;
        let timing = Timing {
            heartbeat_timeout: duration("heartbeat_timeout_s", workers.heartbeat_timeout_s)?,
            quorum_timeout: duration("quorum_timeout_s", workers.quorum_timeout_s)?,
            regroup_grace: duration("regroup_grace_s", workers.regroup_grace_s)?,
            stall_timeout: duration("stall_timeout_s", workers.stall_timeout_s)?,
            exclusion: duration("exclusion_s", workers.exclusion_s)?,
        };
        let heartbeat_interval_s = workers.heartbeat_interval_s.0;
        Ok(Self {
            state: Arc::new(Mutex::new(JobState::new(plan, timing, durable))),
            changed: Arc::new(Notify::new()),
            stopping: CancellationToken::new(),
            suspending: CancellationToken::new(),
            checkpoints,
            heartbeat_interval_s,
            metrics: Arc::new(Registry::new()),
            durable_version: Arc::new(Mutex::new(durable_version)),
            sessions: Arc::default(),
            ring_secrets: Arc::default(),
            lease: Arc::new(lease),
            recorders: Arc::default(),
        })
    }

    /// The service suspends the job once `suspender` is cancelled: see
    /// [`CoordinatorService::run`].
    pub fn suspended_by(mut self, suspender: CancellationToken) -> Self {
        self.suspending = suspender;
        self
    }

    /// Once suspension was asked for: returns when every rank of the group has heard it and
    /// rank 0's commit of the step it took effect at is in, when no group is running (nothing
    /// to commit or tell), or after [`SUSPEND_LIMIT`] (the last commit then stays the resume
    /// point). Stopping before every rank heard would leave one waiting for a coordinator
    /// that is gone.
    async fn suspended(&self) {
        self.suspending.cancelled().await;
        self.state.lock().await.request_suspension();
        tracing::warn!(
            "suspending the job: every rank hears it at its next step, rank 0 commits that step, then the workers exit"
        );
        let started = Instant::now();
        while started.elapsed() < SUSPEND_LIMIT {
            tokio::time::sleep(Duration::from_millis(100)).await;
            let state = self.state.lock().await;
            if state.finished() || state.suspension_complete() {
                return;
            }
        }
        tracing::warn!(
            "the suspension was not committed and heard in time; the job resumes from its last commit"
        );
    }

    /// The series this service publishes, for the `/metrics` endpoint.
    pub fn metrics(&self) -> Arc<Registry> {
        Arc::clone(&self.metrics)
    }

    /// The status page's routes, shown to holders of the job's `token` or of the read-only
    /// `viewing` token, for the metrics port.
    pub fn status_page(
        &self,
        token: &str,
        viewing: Option<&str>,
    ) -> Result<axum::Router, crate::status::routes::NoSession> {
        crate::status::routes::routes(Arc::clone(&self.state), token, viewing)
    }

    fn publish(&self, state: &JobState) {
        let live: Vec<String> = state.live_workers().iter().map(u64::to_string).collect();
        metrics::forget_departed(&self.metrics, &live);
        metrics::record_status(
            &self.metrics,
            &state.status(Instant::now()),
            state.phase(),
            state.group_throughput(),
            state.mismatches(),
            state.exclusions(),
        );
    }

    /// Writes `job.json` once more when the job stopped short, so a rerun does not resume it
    /// and operators find the reason beside the checkpoints. A write failure is logged: the
    /// report carries the reason too.
    async fn record_failure(&self) {
        let durable = {
            let state = self.state.lock().await;
            if state.failure().is_none() {
                return;
            }
            state.durable().clone()
        };
        let written = store::write_durable(&self.checkpoints, &durable, &self.durable_version)
            .await
            .map_err(|e| store::chain(&e));
        if let Err(error) = written {
            tracing::warn!(%error, "the failed job's state was not written to job.json");
        }
    }

    /// Adds `records` to the history and the TensorBoard runs under the checkpoint URI. A
    /// failure is logged and the records are kept for the next attempt: the report holds every
    /// step too.
    async fn append_history(&self, recorders: &Mutex<Recorders>, records: &[StepRecord]) {
        let mut recorders = recorders.lock().await;
        if let Err(error) = recorders.history.append(records).await {
            tracing::warn!(error = %store::chain(&error), "step history not written; retrying with the next steps");
        }
        recorders.board.record_steps(records);
        if let Err(error) = recorders.board.flush().await {
            tracing::warn!(error = %store::chain(&error), "TensorBoard events not written; retrying with the next steps");
        }
    }

    /// Puts the committed evaluation's numbers and figures into TensorBoard's `evaluate` run.
    async fn record_evaluation(&self, recorders: &Mutex<Recorders>) {
        let Some(location) = self.state.lock().await.durable().evaluation.clone() else {
            return;
        };
        let mut recorders = recorders.lock().await;
        let recorded = match DataRoot::open(&location) {
            Ok(root) => recorders.board.record_evaluation(&root, 0).await,
            Err(error) => Err(error),
        };
        let flushed = match recorded {
            Ok(()) => recorders.board.flush().await,
            Err(error) => Err(error),
        };
        if let Err(error) = flushed {
            tracing::warn!(%location, error = %store::chain(&error), "the evaluation is not in TensorBoard");
        }
    }

    /// Writes `curves/stage{N}.csv`, `.png` and `.svg` under the checkpoint URI. A failure is
    /// logged, not fatal: the curves are a convenience, the report holds every step.
    async fn write_curves(&self, phase: Phase) {
        let curve = self.state.lock().await.curve(phase);
        let written: Result<(), Box<dyn std::error::Error>> = async {
            self.checkpoints
                .write(&format!("curves/{phase}.csv"), curve.to_csv().into_bytes())
                .await?;
            let image = curve.to_png()?;
            self.checkpoints
                .write(&format!("curves/{phase}.png"), image)
                .await?;
            let document = curve.to_svg()?;
            self.checkpoints
                .write(&format!("curves/{phase}.svg"), document.into_bytes())
                .await?;
            Ok(())
        }
        .await;
        match written {
            Ok(()) => {
                tracing::info!(%phase, steps = curve.rows.len(), uri = %self.checkpoints.uri(), "loss curves written under curves/")
            }
            Err(error) => {
                tracing::warn!(%phase, error = %store::chain(error.as_ref()), "loss curves not written")
            }
        }
    }

    /// Runs the job: serves RPCs, ticks the state machine, and returns the report once both
    /// stages are done (after giving workers a moment to hear so), when `shutdown` fires, or
    /// once a suspension ([`CoordinatorService::suspended_by`]) has its commit.
    pub async fn run(
        self,
        token: &str,
        shutdown: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> Result<Report, ServeError> {
        // The history first: a restarted coordinator's workers re-register within a fraction
        // of a second and report steps, which must land after the steps read back.
        let recorders = self.open_recorders().await?;
        let recorders = self.recorders.get_or_init(|| Arc::new(recorders)).clone();
        let server = self.start_server(token).await?;
        let fenced = tokio::select! {
            lost = self.tick_until_done(&server.health, &recorders) => lost,
            () = shutdown => {
                tracing::warn!("shutdown requested: the job stops; rerun to resume from its last commit");
                None
            }
            () = self.suspended() => {
                tracing::warn!("job suspended; rerun (or requeue) to resume from its last commit");
                None
            }
        };
        self.stop(server, &recorders, fenced).await
    }
}
