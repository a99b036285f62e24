//! The Coordinator RPCs: each one checks its request, asks the job state, and maps a refusal
//! to the gRPC status a worker can act on (not found: register again; failed precondition:
//! wrong build or config; invalid argument: a malformed request).

use std::time::{Duration, Instant};

use proto::convert::{ConvertError, device_from_wire, phase_from_wire, phase_to_wire};
use proto::v1::coordinator_server::Coordinator;
use proto::v1::{
    Assignment, AwaitAssignmentRequest, CheckpointCommit, CommitAck, HeartbeatReply,
    HeartbeatRequest, JobStatus, LeaveReply, LeaveRequest, RegisterReply, RegisterRequest,
    StatusRequest, StepAck, StepReport, WorkerSummary,
};
use settings::XFactorConfig;
use settings::work::{FailureCause, GenerationFailure};
use tonic::{Request, Response, Status};
use tracing::Instrument;

use super::CoordinatorService;
use super::store::{DurableWriteError, chain, verify, write_durable, write_durable_held};
use crate::job::{Commit, Refusal, SuspendAnswer};
use crate::metrics;

/// How long a commit waits for its step's checksums from the other ranks: they finished the
/// same all-reduce as rank 0, so only their hashing and their report are still to come.
const CHECKSUM_WAIT: Duration = Duration::from_secs(30);

/// A request whose typed fields do not convert.
fn malformed(error: ConvertError) -> Status {
    Status::invalid_argument(error.to_string())
}

/// The status a worker acts on for each refusal.
fn refused(refusal: Refusal) -> Status {
    match refusal {
        Refusal::UnknownWorker(_) | Refusal::LostWorker(_) => {
            Status::not_found(refusal.to_string())
        }
        Refusal::StaleGeneration(_)
        | Refusal::NotInGroup(_)
        | Refusal::WrongPhase { .. }
        | Refusal::Unverified { .. }
        | Refusal::ChecksumsDiffer { .. } => Status::failed_precondition(refusal.to_string()),
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
        self.sessions.check(request.worker_id, &request.session)?;
        if let Some(failure) = &request.failure {
            let failure = GenerationFailure::try_from(failure).map_err(malformed)?;
            self.record_failure_report(&request, &failure).await?;
        }
        self.assign(request).instrument(span).await
    }

    async fn heartbeat(
        &self,
        request: Request<HeartbeatRequest>,
    ) -> Result<Response<HeartbeatReply>, Status> {
        let request = request.into_inner();
        let span = tracing::trace_span!("rpc_heartbeat", worker = request.worker_id);
        self.sessions.check(request.worker_id, &request.session)?;
        async {
            let activity =
                proto::convert::activity_from_wire(request.activity, "heartbeat.activity")
                    .map_err(malformed)?;
            let device =
                proto::convert::reported_device(request.device.as_ref(), "heartbeat.device")
                    .map_err(malformed)?;
            let mut state = self.state.lock().await;
            let (known, generation_current) = state.heartbeat(
                request.worker_id,
                request.generation,
                Some((activity, request.step)),
                Instant::now(),
            );
            if let Some(device) = device {
                state.record_device(request.worker_id, device);
            }
            drop(state);
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
        self.sessions.check(report.worker_id, &report.session)?;
        async {
            let phase = phase_from_wire(report.phase, "step.phase").map_err(malformed)?;
            let device = proto::convert::reported_device(report.device.as_ref(), "step.device")
                .map_err(malformed)?;
            let mut state = self.state.lock().await;
            state.heartbeat(report.worker_id, report.generation, None, Instant::now());
            if let Some(device) = device {
                state.record_device(report.worker_id, device);
            }
            let step = settings::work::StepReport::from(&report);
            let generation_current = state.report_step(report.worker_id, phase, &step);
            if generation_current {
                let rank0 = state.is_rank0(report.worker_id);
                metrics::record_step(&self.metrics, &report, rank0);
            }
            let answer = if generation_current {
                state.suspends(report.worker_id, report.generation, report.step)
            } else {
                SuspendAnswer::Continue
            };
            Ok(Response::new(StepAck {
                generation_current,
                suspend: answer == SuspendAnswer::Suspend,
                checksum_next: answer == SuspendAnswer::ChecksumNext,
            }))
        }
        .instrument(span)
        .await
    }

    async fn commit_checkpoint(
        &self,
        request: Request<CheckpointCommit>,
    ) -> Result<Response<CommitAck>, Status> {
        let commit = request.into_inner();
        let span = tracing::info_span!("rpc_commit", phase = commit.phase, step = commit.step);
        self.sessions.check(commit.worker_id, &commit.session)?;
        self.record_commit(commit).instrument(span).await
    }

    async fn status(
        &self,
        _request: Request<StatusRequest>,
    ) -> Result<Response<JobStatus>, Status> {
        let status = async { self.state.lock().await.status(Instant::now()) }
            .instrument(tracing::debug_span!("rpc_status"))
            .await;
        Ok(Response::new(status_to_wire(&status)))
    }

    async fn leave(&self, request: Request<LeaveRequest>) -> Result<Response<LeaveReply>, Status> {
        let request = request.into_inner();
        let span = tracing::info_span!("rpc_leave", worker = request.worker_id);
        self.sessions.check(request.worker_id, &request.session)?;
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
    /// Acts on a worker's report that its part of a generation failed, by its cause: ends
    /// the generation and blames the suspect (the reporter, or the peer it names); for a store
    /// fault, ends it and blames no one; for a corrupt commit, falls back to the one before it
    /// and records that in `job.json` so a restarted coordinator does not pick it again.
    async fn record_failure_report(
        &self,
        request: &AwaitAssignmentRequest,
        failure: &GenerationFailure,
    ) -> Result<(), Status> {
        let (worker, generation, now) =
            (request.worker_id, request.after_generation, Instant::now());
        let reason = failure.reason.as_str();
        let mut state = self.state.lock().await;
        let ended = match &failure.cause {
            FailureCause::Worker => state.generation_failed(worker, generation, reason, None, now),
            FailureCause::Peer { rank } => {
                let rank = u32::try_from(*rank).ok();
                state.generation_failed(worker, generation, reason, rank, now)
            }
            FailureCause::Store => state.store_failed(worker, generation, reason, now),
            FailureCause::CorruptCheckpoint { location } => {
                if !state.checkpoint_corrupt(worker, generation, location, now) {
                    return Ok(());
                }
                let durable = state.durable().clone();
                drop(state);
                self.changed.notify_waiters();
                return write_durable(&self.checkpoints, &durable, &self.durable_version)
                    .await
                    .map_err(|e| {
                        Status::unavailable(format!(
                            "recording the fall-back failed: {}",
                            chain(&e)
                        ))
                    });
            }
        };
        drop(state);
        if ended {
            self.changed.notify_waiters();
        }
        Ok(())
    }

    async fn admit(&self, request: RegisterRequest) -> Result<Response<RegisterReply>, Status> {
        if request.protocol_version != proto::PROTOCOL_VERSION {
            return Err(Status::failed_precondition(format!(
                "protocol version {} refused: this coordinator speaks version {}; run matching builds",
                request.protocol_version,
                proto::PROTOCOL_VERSION
            )));
        }
        if let Some(device) = request.device {
            device_from_wire(device, "register.device").map_err(malformed)?;
        }
        if request.model_config_version != XFactorConfig::SCHEMA_VERSION {
            return Err(Status::failed_precondition(format!(
                "model-config version {} refused: this coordinator uses version {}",
                request.model_config_version,
                XFactorConfig::SCHEMA_VERSION
            )));
        }
        let mut state = self.state.lock().await;
        check_ring_tls(state.plan().config.tls.is_some(), request.ring_tls)?;
        if let Some(expected) = &request.expected_model {
            let differences = differing_fields(&state.plan().model, &XFactorConfig::from(expected));
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
        let session = self.sessions.issue(id)?;
        drop(state);
        self.changed.notify_waiters();
        Ok(Response::new(RegisterReply {
            worker_id: id,
            job_name,
            heartbeat_interval_s: self.heartbeat_interval_s,
            session,
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
                    Err(refusal) => return Err(refused(refusal)),
                    Ok(Some(assignment)) => {
                        let mut wire = Assignment::from(&assignment);
                        self.ring_secrets.fill(&mut wire)?;
                        return Ok(Response::new(wire));
                    }
                    Ok(None) => {}
                }
                if state.tick(Instant::now()) {
                    self.changed.notify_waiters();
                }
            }
            tokio::select! {
                _ = tokio::time::timeout(Duration::from_millis(200), notified) => {}
                () = self.stopping.cancelled() => {
                    return Err(Status::unavailable("the coordinator is stopping; ask again once it is back"));
                }
            }
        }
    }

    /// Waits until every rank's parameter checksum for `commit`'s step is in, or for
    /// [`CHECKSUM_WAIT`]: rank 0 commits right after its own report, and its peers' reports
    /// of the same step may still be on their way. What the wait ends on is decided again
    /// when the commit is recorded, which refuses it when checksums are still missing.
    async fn await_checksums(
        &self,
        worker: u64,
        commit: &Commit,
        generation: u64,
    ) -> Result<(), Status> {
        let deadline = Instant::now() + CHECKSUM_WAIT;
        loop {
            let notified = self.changed.notified();
            let check = self
                .state
                .lock()
                .await
                .check_commit(worker, commit, generation);
            if !matches!(check, Err(Refusal::Unverified { .. })) || Instant::now() >= deadline {
                return Ok(());
            }
            tokio::select! {
                _ = tokio::time::timeout(Duration::from_millis(50), notified) => {}
                () = self.stopping.cancelled() => {
                    return Err(Status::unavailable("the coordinator is stopping; ask again once it is back"));
                }
            }
        }
    }

    /// Writes `steps`, a commit's step and those before it, to the step history before the
    /// commit goes into `job.json`: a coordinator killed between the two would otherwise
    /// resume past steps its history never got, and they would be missing for good.
    async fn write_history(&self, steps: &[crate::job::StepRecord]) -> Result<(), Status> {
        let Some(recorders) = self.recorders.get() else {
            return Ok(());
        };
        let mut recorders = recorders.lock().await;
        recorders.history.append(steps).await.map_err(|e| {
            Status::unavailable(format!(
                "recording the step history before the commit failed: {}",
                chain(&e)
            ))
        })?;
        recorders.board.record_steps(steps);
        Ok(())
    }

    /// Records a verified commit: `job.json` is written first, with the commit in it, and
    /// the job's memory changes only once that write succeeded, so memory never holds a
    /// commit the store does not. The lock on `job.json`'s version is held throughout, so no
    /// other write of it comes between; the job's own lock is never held across the write.
    async fn record_commit(&self, commit: CheckpointCommit) -> Result<Response<CommitAck>, Status> {
        let refuse = |reason: String| {
            tracing::warn!(%reason, "commit refused");
            Ok(Response::new(CommitAck {
                accepted: false,
                reason,
            }))
        };
        let phase = phase_from_wire(commit.phase, "commit.phase").map_err(malformed)?;
        if let Err(check) = verify(&commit.location).await {
            return refuse(chain(&check));
        }
        let (worker, generation) = (commit.worker_id, commit.generation);
        let commit = Commit {
            phase,
            step: commit.step,
            location: commit.location,
        };
        self.await_checksums(worker, &commit, generation).await?;
        let mut version = self.durable_version.lock().await;
        let (after, steps) = {
            let mut state = self.state.lock().await;
            let after = state.durable_after_commit(worker, &commit, generation);
            if let Err(refusal) = &after
                && state.roll_back_refused(refusal, generation, Instant::now())
            {
                self.changed.notify_waiters();
            }
            let steps = match after {
                Ok(_) => state.take_history_through(&commit, generation),
                Err(_) => Vec::new(),
            };
            (after, steps)
        };
        let after = match after {
            Ok(after) => after,
            Err(refusal) => return refuse(refusal.to_string()),
        };
        self.write_history(&steps).await?;
        write_durable_held(&self.checkpoints, &after, &mut version)
            .await
            .map_err(|e| {
                let message = format!("recording the commit failed: {}", chain(&e));
                tracing::error!(%message);
                match e {
                    DurableWriteError::Stale { .. } => Status::failed_precondition(message),
                    _ => Status::unavailable(message),
                }
            })?;
        let mut state = self.state.lock().await;
        if let Err(refusal) = state.commit(worker, commit, generation) {
            // The group ended while the write was in flight: put back what memory holds.
            let durable = state.durable().clone();
            drop(state);
            let restored = write_durable_held(&self.checkpoints, &durable, &mut version).await;
            if let Err(error) = restored {
                tracing::error!(error = %chain(&error), "job.json holds a commit the job refused");
            }
            return refuse(refusal.to_string());
        }
        self.metrics.add(&metrics::COMMITS, &[], 1.0);
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        self.metrics.set(&metrics::LAST_COMMIT_TIMESTAMP, &[], now);
        drop(state);
        drop(version);
        self.changed.notify_waiters();
        Ok(Response::new(CommitAck {
            accepted: true,
            reason: String::new(),
        }))
    }
}

/// Refuses a worker whose ring would not match the job's: with `tls:`, every ring runs over
/// TLS, so a worker must bring its certificate; without, every ring runs on lanes.
fn check_ring_tls(job_tls: bool, worker_ring_tls: bool) -> Result<(), Status> {
    match (job_tls, worker_ring_tls) {
        (true, false) => Err(Status::failed_precondition(
            "this job runs TLS (`tls:` in its YAML), so its ring runs over TLS too: start the worker with --tls-cert and --tls-key beside --tls-ca",
        )),
        (false, true) => Err(Status::failed_precondition(
            "this job runs without TLS (no `tls:` in its YAML), so its ring runs on plain lanes: start the worker without --tls-cert and --tls-key, or give the job `tls:`",
        )),
        _ => Ok(()),
    }
}

/// `key: job vs worker` for every field whose value differs.
fn differing_fields(job: &XFactorConfig, worker: &XFactorConfig) -> Vec<String> {
    let (Ok(serde_json::Value::Object(job)), Ok(serde_json::Value::Object(worker))) =
        (serde_json::to_value(job), serde_json::to_value(worker))
    else {
        return vec![format!("job {job:?} vs worker {worker:?}")];
    };
    job.iter()
        .filter(|(key, value)| worker.get(*key) != Some(value))
        .map(|(key, value)| {
            let theirs = worker
                .get(key)
                .map_or("(absent)".to_string(), |v| v.to_string());
            format!("{key}: job {value} vs worker {theirs}")
        })
        .collect()
}

/// The job's status as the `status` RPC answers it.
fn status_to_wire(status: &crate::job::JobStatus) -> JobStatus {
    JobStatus {
        job_name: status.job_name.clone(),
        phase: phase_to_wire(status.phase) as i32,
        generation: status.generation,
        workers: u32::try_from(status.workers).unwrap_or(u32::MAX),
        step: status.step,
        total_steps: status.total_steps,
        last_commit: status.last_commit.clone().unwrap_or_default(),
        last_loss: status.last_loss,
        restarts: status.restarts,
        job_steps_done: status.job_steps_done,
        job_steps_total: status.job_steps_total,
        group_running: status.group_running,
        worker_list: status
            .worker_list
            .iter()
            .map(|worker| WorkerSummary {
                worker_id: worker.worker_id,
                name: worker.name.clone(),
                device: worker
                    .device
                    .as_ref()
                    .map(proto::convert::device_in_use_to_wire),
                samples_per_s: worker.samples_per_s,
            })
            .collect(),
        store_failing_s: status.store_failing.map(|d| d.as_secs_f64()),
    }
}
