//! When and what rank 0 commits, and the commits themselves: a checkpoint uploaded in the
//! background (retried with back-off, `COMMIT.json` last), then the coordinator asked to
//! commit it. Rank 0 trains on meanwhile, so a slow store never holds its peers in the
//! all-reduce; the last commit of a stage (or of a suspension) is waited for.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use proto::convert::phase_to_wire;
use proto::v1::CheckpointCommit;
use settings::Phase;
use settings::commit::CommitManifest;
use tokio::runtime::Runtime;

use crate::checkpoints::{self, TransferError};
use crate::metrics;
use crate::progress::Progress;
use crate::session::Client;

/// Tries of a checkpoint upload before the commit fails (pauses of 1 s, 2 s between).
pub const UPLOAD_ATTEMPTS: u32 = 3;

/// What rank 0 does with the state after a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CommitDecision {
    /// No commit is due (or this is not rank 0).
    Nothing,
    /// A commit is due but the previous one still uploads: this step's is skipped, and the
    /// next due step commits instead. Committed work is never lost, only committed later.
    SkipWhilePreviousUploads,
    /// Commit this step: after waiting for the previous upload when `wait_previous`, and
    /// waiting for this one when `wait_this` (the stage's last step, or a suspension).
    Commit {
        /// The previous commit must land first.
        wait_previous: bool,
        /// Nothing may go on until this commit has landed.
        wait_this: bool,
    },
}

/// The commit schedule of a stage: every `every` steps, after the last, and when the
/// coordinator suspends the job.
#[derive(Debug, Clone, Copy)]
pub struct CommitSchedule {
    /// Commits are due every this many steps.
    pub every: u64,
    /// The stage's last step.
    pub total_steps: u64,
}

impl CommitSchedule {
    /// What rank `rank` does after finishing step `done`, with a commit in flight or not.
    pub fn decide(&self, rank: usize, done: u64, suspend: bool, in_flight: bool) -> CommitDecision {
        let last = done == self.total_steps || suspend;
        let due = done.is_multiple_of(self.every.max(1)) || last;
        match (rank, due, in_flight, last) {
            (0, true, true, false) => CommitDecision::SkipWhilePreviousUploads,
            (0, true, _, _) => CommitDecision::Commit {
                wait_previous: in_flight,
                wait_this: last,
            },
            _ => CommitDecision::Nothing,
        }
    }
}

/// Why a commit did not land.
#[derive(Debug, thiserror::Error)]
pub enum CommitError {
    /// The checkpoint could not be read from scratch space or uploaded.
    #[error("uploading the checkpoint to {location} failed after {attempts} attempt(s)")]
    Upload {
        /// Where it was going.
        location: String,
        /// Attempts made.
        attempts: u32,
        /// The last attempt's error.
        #[source]
        source: TransferError,
    },
    /// The coordinator did not answer the commit.
    #[error("commit of {location} failed: {reason}")]
    Unanswered {
        /// The checkpoint.
        location: String,
        /// The RPC's status.
        reason: String,
    },
    /// The coordinator refused it (the generation ended meanwhile, say).
    #[error("commit of {location} refused: {reason}")]
    Refused {
        /// The checkpoint.
        location: String,
        /// The coordinator's reason.
        reason: String,
    },
    /// The background task ended without a result (the runtime is shutting down).
    #[error("the commit of {location} did not run to its end")]
    Interrupted {
        /// The checkpoint.
        location: String,
        /// Why the task ended.
        #[source]
        source: tokio::task::JoinError,
    },
}

/// What one commit uploads and where.
pub struct CommitRequest<'a> {
    /// The files to upload; read into memory when the commit starts, so the directory may be
    /// reused at once.
    pub dir: &'a Path,
    /// The URI prefix they go under.
    pub location: String,
    /// The phase that wrote them.
    pub phase: Phase,
    /// Steps done.
    pub step: u64,
    /// The generation committing.
    pub generation: u64,
}

/// A commit in flight on the worker's runtime. Dropped unfinished (its generation failed),
/// the upload is abandoned: without `COMMIT.json` and never committed, what it wrote is not a
/// checkpoint.
pub struct InFlightCommit {
    /// Where it goes.
    pub location: String,
    /// The step it saves.
    pub step: u64,
    task: tokio::task::JoinHandle<Result<(), CommitError>>,
}

impl InFlightCommit {
    /// Reads `request.dir` and starts uploading and committing it in the background.
    pub fn start(
        runtime: &Runtime,
        client: &Client,
        progress: &Progress,
        request: CommitRequest<'_>,
    ) -> Result<Self, CommitError> {
        let location = request.location;
        let files = checkpoints::read_files(request.dir).map_err(|source| CommitError::Upload {
            location: location.clone(),
            attempts: 0,
            source,
        })?;
        tracing::info!(%location, step = request.step, "uploading checkpoint");
        let commit = CheckpointCommit {
            worker_id: progress.worker_id(),
            generation: request.generation,
            phase: phase_to_wire(request.phase) as i32,
            step: request.step,
            location: location.clone(),
            session: progress.session(),
        };
        let manifest = CommitManifest {
            phase: request.phase,
            step: request.step,
            files: Vec::new(),
        };
        let task = runtime.spawn(upload_and_commit(
            client.clone(),
            Arc::clone(&progress.metrics),
            files,
            manifest,
            commit,
        ));
        Ok(Self {
            location,
            step: request.step,
            task,
        })
    }

    /// Whether it has ended, committed or failed.
    pub fn is_finished(&self) -> bool {
        self.task.is_finished()
    }

    /// Blocks until it ends; fails when the upload kept failing or the coordinator did not
    /// take the commit. The caller's generation then fails, which it reports, so the group
    /// re-forms from the last commit.
    pub fn wait(mut self, runtime: &Runtime) -> Result<(), CommitError> {
        let location = self.location.clone();
        runtime
            .block_on(&mut self.task)
            .map_err(|source| CommitError::Interrupted { location, source })?
    }
}

impl Drop for InFlightCommit {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Uploads `request.dir` and asks the coordinator to commit it, waiting for both.
pub fn commit(
    runtime: &Runtime,
    client: &Client,
    progress: &Progress,
    request: CommitRequest<'_>,
) -> Result<(), CommitError> {
    InFlightCommit::start(runtime, client, progress, request)?.wait(runtime)
}

async fn upload_and_commit(
    mut client: Client,
    registry: Arc<telemetry::Registry>,
    files: Vec<(String, Vec<u8>)>,
    manifest: CommitManifest,
    commit: CheckpointCommit,
) -> Result<(), CommitError> {
    let started = Instant::now();
    let location = commit.location.clone();
    upload_with_retries(&files, &location, manifest).await?;
    registry.observe(
        &metrics::CHECKPOINT_UPLOAD,
        &[],
        started.elapsed().as_secs_f64(),
    );
    let ack = client
        .commit_checkpoint(commit)
        .await
        .map_err(|status| CommitError::Unanswered {
            location: location.clone(),
            reason: status.message().to_string(),
        })?
        .into_inner();
    if !ack.accepted {
        return Err(CommitError::Refused {
            location,
            reason: ack.reason,
        });
    }
    tracing::info!(%location, "committed");
    Ok(())
}

async fn upload_with_retries(
    files: &[(String, Vec<u8>)],
    location: &str,
    manifest: CommitManifest,
) -> Result<(), CommitError> {
    let mut attempt = 1;
    loop {
        match checkpoints::upload(files, location, manifest.clone()).await {
            Ok(()) => return Ok(()),
            Err(source) if attempt >= UPLOAD_ATTEMPTS => {
                return Err(CommitError::Upload {
                    location: location.to_string(),
                    attempts: attempt,
                    source,
                });
            }
            Err(error) => {
                let pause = Duration::from_secs(1 << (attempt - 1));
                tracing::warn!(%location, attempt, error = %telemetry::logging::chain(&error), "checkpoint upload failed; retrying in {} s", pause.as_secs());
                tokio::time::sleep(pause).await;
                attempt += 1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCHEDULE: CommitSchedule = CommitSchedule {
        every: 5,
        total_steps: 12,
    };

    #[test]
    fn only_rank_0_commits() {
        for done in [5, 10, 12] {
            assert_eq!(
                SCHEDULE.decide(1, done, false, false),
                CommitDecision::Nothing
            );
            assert_eq!(
                SCHEDULE.decide(1, done, true, false),
                CommitDecision::Nothing
            );
        }
    }

    #[test]
    fn commits_fall_every_n_steps_and_after_the_last() {
        let due: Vec<u64> = (1..=12)
            .filter(|&done| SCHEDULE.decide(0, done, false, false) != CommitDecision::Nothing)
            .collect();
        assert_eq!(due, [5, 10, 12]);
        assert_eq!(
            SCHEDULE.decide(0, 5, false, false),
            CommitDecision::Commit {
                wait_previous: false,
                wait_this: false
            }
        );
        assert_eq!(
            SCHEDULE.decide(0, 12, false, false),
            CommitDecision::Commit {
                wait_previous: false,
                wait_this: true
            }
        );
    }

    #[test]
    fn a_slow_upload_skips_a_middle_commit_but_never_the_last() {
        assert_eq!(
            SCHEDULE.decide(0, 10, false, true),
            CommitDecision::SkipWhilePreviousUploads
        );
        assert_eq!(
            SCHEDULE.decide(0, 12, false, true),
            CommitDecision::Commit {
                wait_previous: true,
                wait_this: true
            }
        );
    }

    #[test]
    fn a_suspension_commits_the_step_it_is_on_and_waits() {
        assert_eq!(
            SCHEDULE.decide(0, 7, true, false),
            CommitDecision::Commit {
                wait_previous: false,
                wait_this: true
            }
        );
        assert_eq!(
            SCHEDULE.decide(0, 7, true, true),
            CommitDecision::Commit {
                wait_previous: true,
                wait_this: true
            }
        );
    }
}
