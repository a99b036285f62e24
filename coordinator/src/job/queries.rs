//! What the job state tells operators and the service: status, throughput, curves, and the
//! step records for the history file.

use std::time::{Duration, Instant};

use settings::{DeviceInUse, Phase};
use telemetry::curves::{Curve, CurvePanel};

use super::members::MemberState;
use super::snapshot::{
    COMMITS_SHOWN, CommitView, LOSS_POINTS, StatusSnapshot, TimelineEntry, WorkerView, eta_seconds,
    thinned,
};
use super::{JobState, StepRecord};

/// Where the job stands, for the `status` command and the metrics.
#[derive(Debug, Clone, PartialEq)]
pub struct JobStatus {
    /// The job's name.
    pub job_name: String,
    /// Its phase.
    pub phase: Phase,
    /// Whether a group is running (false: waiting for workers).
    pub group_running: bool,
    /// The newest generation.
    pub generation: u64,
    /// Live workers.
    pub workers: usize,
    /// The step the phase is at.
    pub step: u64,
    /// Steps of the phase (0 outside training).
    pub total_steps: u64,
    /// The phase's newest commit.
    pub last_commit: Option<String>,
    /// Rank 0's newest loss.
    pub last_loss: f32,
    /// Generations abandoned so far.
    pub restarts: u64,
    /// Steps done over both stages.
    pub job_steps_done: u64,
    /// Steps of both stages.
    pub job_steps_total: u64,
    /// The live workers, by id.
    pub worker_list: Vec<WorkerSummary>,
    /// How long the object store has been failing generations, while it is.
    pub store_failing: Option<Duration>,
}

/// One live worker in [`JobStatus`].
#[derive(Debug, Clone, PartialEq)]
pub struct WorkerSummary {
    /// Its id.
    pub worker_id: u64,
    /// Its name.
    pub name: String,
    /// The device it trains on, once a generation resolved it.
    pub device: Option<DeviceInUse>,
    /// Its samples per second in its last step.
    pub samples_per_s: f64,
}

impl JobState {
    /// Step records for the history writer: see [`super::steps::StepLog::take_sealed`].
    pub fn take_history(&mut self, all: bool) -> Vec<StepRecord> {
        self.steps.take_sealed(all)
    }

    /// Step records for the history writer up to the step `commit` saves in `generation`:
    /// see [`super::steps::StepLog::take_through`].
    pub fn take_history_through(
        &mut self,
        commit: &super::Commit,
        generation: u64,
    ) -> Vec<StepRecord> {
        match commit.step.checked_sub(1) {
            Some(step) if commit.phase.is_training() => {
                self.steps.take_through(commit.phase, step, generation)
            }
            _ => Vec::new(),
        }
    }

    /// Takes back the step records an earlier coordinator of this job wrote to the history, so
    /// the report and the curves start from the job's first step: see
    /// [`super::steps::StepLog::restore`].
    pub fn restore_history(&mut self, records: Vec<StepRecord>) {
        self.steps.restore(records);
    }

    /// Progress for the `status` command at `now`.
    pub fn status(&self, now: Instant) -> JobStatus {
        let phase = self.durable.phase;
        let stage1 = self.plan.stage(Phase::Stage1).steps;
        let stage2 = self.plan.stage(Phase::Stage2).steps;
        JobStatus {
            job_name: self.plan.config.job.0.clone(),
            phase,
            group_running: self.group.is_some(),
            generation: self.generation,
            workers: self.members.values().filter(|m| !m.state.is_lost()).count(),
            step: self.current_step,
            total_steps: if phase.is_training() {
                self.plan.stage(phase).steps
            } else {
                0
            },
            last_commit: self
                .durable
                .last_commit
                .as_ref()
                .map(|c| c.location.clone()),
            last_loss: self.last_loss,
            restarts: self.report.restarts,
            job_steps_done: match phase {
                Phase::Stage1 => self.current_step,
                Phase::Stage2 => stage1 + self.current_step,
                Phase::Evaluate | Phase::Finished => stage1 + stage2,
            },
            job_steps_total: stage1 + stage2,
            worker_list: self
                .members
                .iter()
                .filter(|(_, member)| !member.state.is_lost())
                .map(|(&worker_id, member)| WorkerSummary {
                    worker_id,
                    name: member.name.clone(),
                    device: member.device.clone(),
                    samples_per_s: member.samples_per_s,
                })
                .collect(),
            store_failing: self.store_retry.failing_for(now),
        }
    }

    /// Samples per second of the running group: its members' last reports summed.
    pub fn group_throughput(&self) -> f64 {
        self.group.as_ref().map_or(0.0, |group| {
            group
                .members
                .iter()
                .filter_map(|m| self.members.get(m))
                .map(|m| m.samples_per_s)
                .sum()
        })
    }

    /// Whether `worker` is rank 0 of the running group (its reports carry the job's loss).
    pub fn is_rank0(&self, worker: u64) -> bool {
        self.group
            .as_ref()
            .is_some_and(|g| g.members.first() == Some(&worker))
    }

    /// Ids of the registered workers whose heartbeats are on time.
    pub fn live_workers(&self) -> Vec<u64> {
        self.members
            .iter()
            .filter(|(_, m)| !m.state.is_lost())
            .map(|(&id, _)| id)
            .collect()
    }

    /// Checksum disagreements so far.
    pub fn mismatches(&self) -> usize {
        self.report.checksum_mismatches.len()
    }

    /// Workers blamed and sent to sit out so far.
    pub fn exclusions(&self) -> usize {
        self.report.exclusions.len()
    }

    /// The curves of `phase` as recorded by this coordinator: one row per step, thinned to
    /// evenly spaced steps past [`super::steps::CURVE_POINTS`] (the last run of a step that
    /// was re-run after a restart): the loss and its terms on a logarithmic axis, the learning
    /// rate, the gradient norm.
    pub fn curve(&self, phase: Phase) -> Curve {
        let rows = self.steps.curve(phase).into_iter().map(|(step, row)| {
            let lpips = row.lpips.map_or(f64::NAN, f64::from);
            (
                step,
                vec![
                    f64::from(row.loss),
                    row.learning_rate,
                    f64::from(row.l1),
                    lpips,
                    row.grad_norm,
                ],
            )
        });
        let panel = |title: &str, y_label: &str, log_y: bool, columns: &[&str]| CurvePanel {
            title: title.into(),
            y_label: y_label.into(),
            log_y,
            columns: columns.iter().map(|c| (*c).to_string()).collect(),
        };
        Curve {
            title: format!("{}: {phase}", self.plan.config.job.0),
            columns: ["loss", "learning_rate", "l1", "lpips", "grad_norm"]
                .map(String::from)
                .to_vec(),
            rows: rows.collect(),
            panels: vec![
                panel(
                    "Training loss and its terms",
                    "loss",
                    true,
                    &["l1", "lpips", "loss"],
                ),
                panel(
                    "Learning rate (warm-up, then cosine)",
                    "learning rate",
                    false,
                    &["learning_rate"],
                ),
                panel(
                    "Gradient norm before clipping",
                    "global L2 norm",
                    true,
                    &["grad_norm"],
                ),
            ],
        }
    }
}

/// Step times the ETA averages: the newest of the running phase.
const ETA_STEPS: usize = 50;

impl JobState {
    /// The job at a glance at `now`, for the status page and `/api/status`.
    pub fn snapshot(&self, now: Instant) -> StatusSnapshot {
        let status = self.status(now);
        let phase = self.durable.phase;
        let recent: Vec<f64> = self
            .steps
            .retained()
            .iter()
            .rev()
            .filter(|record| record.phase == phase)
            .take(ETA_STEPS)
            .map(|record| record.step_s)
            .collect();
        let stage2_steps_left = if phase == Phase::Stage1 {
            self.plan.stage(Phase::Stage2).steps
        } else {
            0
        };
        let eta_s = phase.is_training().then(|| {
            let left = status.total_steps.saturating_sub(status.step) + stage2_steps_left;
            eta_seconds(left, &recent)
        });
        StatusSnapshot {
            job: status.job_name.clone(),
            phase: phase.to_string(),
            state: self.state_line(),
            generation: status.generation,
            step: status.step,
            stage_steps: status.total_steps,
            job_steps_done: status.job_steps_done,
            job_steps_total: status.job_steps_total,
            eta_s: eta_s.flatten(),
            last_loss: status.last_loss,
            samples_per_s: self.group_throughput(),
            store_failing_s: status.store_failing.map(|d| d.as_secs_f64()),
            workers: self.worker_views(now),
            timeline: self.timeline(),
            faults: self
                .report
                .exclusions
                .iter()
                .map(|e| {
                    format!(
                        "{} ({}) blamed, failure {}: sits out {:.0} s",
                        e.worker, e.address, e.failures, e.seconds
                    )
                })
                .chain(self.report.checksum_mismatches.iter().cloned())
                .chain(
                    self.report
                        .fallbacks
                        .iter()
                        .map(|l| format!("commit {l} found corrupt: fell back")),
                )
                .collect(),
            commits: self
                .report
                .commits
                .iter()
                .rev()
                .take(COMMITS_SHOWN)
                .map(|c| CommitView {
                    phase: c.phase.to_string(),
                    step: c.step,
                    location: c.location.clone(),
                })
                .collect(),
            loss: self.loss_points(),
            evaluation: self.report.evaluation.clone(),
        }
    }

    /// Running, waiting, finished or failed, in a few words.
    fn state_line(&self) -> String {
        match (&self.durable.failure, self.finished(), &self.group) {
            (Some(failure), _, _) => format!("failed: {failure}"),
            (None, true, _) => "finished".into(),
            (None, false, Some(_)) => "running".into(),
            (None, false, None) => "waiting for workers".into(),
        }
    }

    fn worker_views(&self, now: Instant) -> Vec<WorkerView> {
        self.members
            .iter()
            .map(|(&id, member)| WorkerView {
                id,
                name: member.name.clone(),
                device: member
                    .device
                    .as_ref()
                    .map_or("-".into(), |d| d.name.clone()),
                samples_per_s: member.samples_per_s,
                heartbeat_age_s: now
                    .saturating_duration_since(member.last_seen)
                    .as_secs_f64(),
                state: match member.state {
                    MemberState::Working(progress) => {
                        format!("{:?} step {}", progress.activity, progress.step).to_lowercase()
                    }
                    MemberState::Waiting { .. } => "waiting for work".into(),
                    MemberState::Lost => "lost".into(),
                },
                faults: self
                    .report
                    .exclusions
                    .iter()
                    .filter(|e| e.address == member.address)
                    .map(|e| e.failures)
                    .max()
                    .unwrap_or(0),
            })
            .collect()
    }

    /// Generations' starts and ends, oldest first.
    fn timeline(&self) -> Vec<TimelineEntry> {
        let starts = self.report.generations.iter().map(|g| {
            let from = match (g.resume_from.as_str(), g.init_weights_from.as_str()) {
                ("", "") => "the stage's start".to_string(),
                ("", weights) => format!("the weights of {weights}"),
                (commit, _) => commit.to_string(),
            };
            let event = format!("{} on {} ranks from {from}", g.phase, g.world_size);
            ((g.generation, 0), event)
        });
        let ends = self.report.generation_ends.iter().map(|e| {
            let event = format!("ended at step {}: {}", e.step, e.reason);
            ((e.generation, 1), event)
        });
        let mut entries: Vec<_> = starts.chain(ends).collect();
        entries.sort_by_key(|(order, _)| *order);
        entries
            .into_iter()
            .map(|((generation, _), event)| TimelineEntry { generation, event })
            .collect()
    }

    /// The loss over both stages, stage 2's steps counted after stage 1's, thinned.
    fn loss_points(&self) -> Vec<(u64, f32)> {
        let stage1_steps = self.plan.stage(Phase::Stage1).steps;
        let points: Vec<(u64, f32)> = [(Phase::Stage1, 0), (Phase::Stage2, stage1_steps)]
            .into_iter()
            .flat_map(|(phase, offset)| {
                self.steps
                    .curve(phase)
                    .into_iter()
                    .map(move |(step, row)| (offset + step, row.loss))
            })
            .collect();
        thinned(&points, LOSS_POINTS)
    }
}
