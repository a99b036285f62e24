//! The job's state machine: membership, group generations, phase progress and commits. It is
//! pure: every method takes the time as an argument and returns what changed, so the service
//! drives it and the unit tests replay any schedule of events.
//!
//! A *generation* is one group of workers with fixed ranks. It ends when its stage ends or when
//! a member is lost (heartbeat silence) or reports trouble; survivors, and any replacement that
//! registered meanwhile, then form the next generation, which resumes from the last committed
//! checkpoint. Nothing here knows about tensors.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::time::{Duration, Instant};

use settings::work::{Activity, Assignment, StepReport};
use settings::{DeviceInUse, Phase};

use crate::plan::Plan;
use faults::StoreRetry;
use members::Member;

mod assignments;
mod faults;
mod forming;
mod members;
mod queries;
mod records;
pub mod snapshot;
mod steps;
mod suspension;
#[cfg(test)]
mod tests;
mod verified;

pub use queries::{JobStatus, WorkerSummary};
pub use records::{Commit, Durable, GenerationEnd, GenerationStart, Report, StepRecord};
pub use suspension::SuspendAnswer;

/// How many skipped-frame examples the report keeps.
const SKIPPED_EXAMPLES: usize = 8;

/// A worker's record of failures, kept by its collective address so it survives the worker
/// registering again under a new id.
#[derive(Debug, Clone, Default)]
struct Penalty {
    /// Generations this worker was blamed for.
    failures: u32,
    /// Times its parameters were the odd ones out among the replicas.
    divergences: u32,
    /// Not picked into a group before this.
    excluded_until: Option<Instant>,
}

/// The running group.
#[derive(Debug, Clone)]
struct Group {
    generation: u64,
    members: Vec<u64>,
    phase: Phase,
}

/// Liveness and grouping settings.
#[derive(Debug, Clone)]
pub struct Timing {
    /// Silence after which a worker is lost.
    pub heartbeat_timeout: Duration,
    /// Wait for `expected` this long before starting with `minimum`.
    pub quorum_timeout: Duration,
    /// Wait this long for a replacement after a loss.
    pub regroup_grace: Duration,
    /// A member that makes no progress this long while its peers wait for it in the
    /// all-reduce is removed from the group.
    pub stall_timeout: Duration,
    /// A blamed worker sits out this long, doubled for each further failure (at most an hour).
    pub exclusion: Duration,
}

/// Why the state machine refused a worker's request; the service maps each to a gRPC status.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    /// The worker id was never handed out by this coordinator.
    #[error("unknown worker {0}: register first")]
    UnknownWorker(u64),
    /// The worker was declared lost (silence or leave) and must register again.
    #[error("worker {0} was declared lost after missing heartbeats: register again")]
    LostWorker(u64),
    /// The request belongs to a generation that has ended.
    #[error("generation {0} is no longer current; commit refused")]
    StaleGeneration(u64),
    /// The worker is not a member of the running group.
    #[error("worker {0} is not in the current group")]
    NotInGroup(u64),
    /// The commit is for another phase than the job's.
    #[error("commit for {commit} while the job is in {job}")]
    WrongPhase {
        /// The commit's phase.
        commit: Phase,
        /// The job's.
        job: Phase,
    },
    /// Not every rank's parameter checksum for the committed step has arrived (see
    /// `verified.rs`).
    #[error(
        "commit of {phase} step {step} not verified: no parameter checksum from rank(s) {missing:?}"
    )]
    Unverified {
        /// The commit's phase.
        phase: Phase,
        /// Steps done at the commit.
        step: u64,
        /// The ranks whose checksums are missing.
        missing: Vec<u32>,
    },
    /// The ranks' parameter checksums for the committed step disagree: a replica diverged,
    /// and the group rolls back to the last commit.
    #[error(
        "commit of {phase} step {step} refused: the replicas' parameter checksums differ {checksums:08x?}"
    )]
    ChecksumsDiffer {
        /// The commit's phase.
        phase: Phase,
        /// Steps done at the commit.
        step: u64,
        /// Each rank's checksum.
        checksums: BTreeMap<u32, u32>,
    },
}

/// The coordinator's whole state.
pub struct JobState {
    plan: Plan,
    timing: Timing,
    members: BTreeMap<u64, Member>,
    penalties: HashMap<String, Penalty>,
    /// The generation number before this coordinator formed its first group.
    first_generation: u64,
    next_worker: u64,
    generation: u64,
    group: Option<Group>,
    durable: Durable,
    assignments: BTreeMap<u64, Assignment>,
    first_registration: Option<Instant>,
    lost_at: Option<Instant>,
    /// The object store's back-off after generations that failed on it.
    store_retry: StoreRetry,
    report: Report,
    /// Frames skipped by each worker in each generation (its reports carry a running count).
    skipped: HashMap<(u64, u64), u64>,
    /// Step records: found by index, the newest in memory, the rest handed to the history.
    steps: steps::StepLog,
    /// A generation whose replicas' checksums disagreed, with the members whose checksum
    /// was the odd one out (empty when no majority names one).
    divergence: Option<(u64, Vec<u64>)>,
    /// The time of the last tick, for decisions outside it (who may join at a commit).
    last_tick: Option<Instant>,
    current_step: u64,
    last_loss: f32,
    /// A requested suspension: its step and who has heard it.
    suspension: suspension::Suspension,
}

/// Where this coordinator's worker ids and generation numbers start: its start time in
/// microseconds since the epoch. Both grow by one per registration or re-formation, far slower
/// than the clock, so a restarted coordinator never hands out an id or a generation that the
/// workers of its predecessor still hold: a stale heartbeat cannot pass for a new member, and
/// a stale collective inbox cannot be taken for a new generation's.
fn incarnation_base() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

/// The phase a job read back as `durable` resumes in under `plan`: a YAML that stops after
/// stage 1 sets saved stage-2 progress aside; a state saved before evaluation existed (stage 2
/// done, no final weights recorded) has nothing to evaluate; without an evaluation section
/// the job is finished once training is.
fn resumed_phase(plan: &Plan, durable: &Durable) -> Phase {
    let after_training = plan.after_training();
    match durable.phase {
        Phase::Stage2 if !plan.trains(Phase::Stage2) => {
            tracing::warn!(
                "the job now stops after stage 1 (stop_after); its stage-2 progress is set aside"
            );
            after_training
        }
        Phase::Evaluate if plan.trains(Phase::Stage2) && durable.stage2_final.is_none() => {
            tracing::warn!(
                "the saved job state finished stage 2 before evaluation existed; nothing to evaluate"
            );
            Phase::Finished
        }
        Phase::Evaluate => after_training,
        phase => phase,
    }
}

impl JobState {
    /// A job at its start, or where `durable` (read back after a coordinator restart) left it.
    pub fn new(plan: Plan, timing: Timing, durable: Option<Durable>) -> Self {
        Self::starting_at(plan, timing, durable, incarnation_base())
    }

    /// As [`JobState::new`], with ids and generations counted from `base`.
    fn starting_at(plan: Plan, timing: Timing, durable: Option<Durable>, base: u64) -> Self {
        let job = plan.config.job.0.clone();
        let mut durable = durable.unwrap_or_else(|| Durable::new(job.clone()));
        durable.phase = resumed_phase(&plan, &durable);
        Self {
            timing,
            members: BTreeMap::new(),
            penalties: HashMap::new(),
            next_worker: base + 1,
            generation: base,
            first_generation: base,
            group: None,
            assignments: BTreeMap::new(),
            first_registration: None,
            lost_at: None,
            store_retry: StoreRetry::default(),
            report: Report {
                job,
                stage1_final: durable.stage1_final.clone(),
                evaluation: durable.evaluation.clone(),
                ..Report::default()
            },
            steps: steps::StepLog::default(),
            divergence: None,
            last_tick: None,
            skipped: HashMap::new(),
            durable,
            plan,
            current_step: 0,
            last_loss: f32::NAN,
            suspension: suspension::Suspension::default(),
        }
    }

    /// The plan being run.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The job's phase.
    pub fn phase(&self) -> Phase {
        self.durable.phase
    }

    /// Whether both stages (and the evaluation, when the job has one) are done.
    pub fn finished(&self) -> bool {
        self.durable.phase == Phase::Finished
    }

    /// The phase after `phase` in this job.
    fn next_phase(&self, phase: Phase) -> Phase {
        match phase {
            Phase::Stage1 if self.plan.trains(Phase::Stage2) => Phase::Stage2,
            Phase::Stage1 | Phase::Stage2 => self.plan.after_training(),
            Phase::Evaluate | Phase::Finished => Phase::Finished,
        }
    }

    /// Steps of `phase`; the evaluation counts as one.
    fn phase_steps(&self, phase: Phase) -> u64 {
        if phase.is_training() {
            self.plan.stage(phase).steps
        } else {
            1
        }
    }

    /// State to persist after a commit.
    pub fn durable(&self) -> &Durable {
        &self.durable
    }

    /// The report so far.
    pub fn report(&self) -> Report {
        let mut report = self.report.clone();
        report.steps = self.steps.retained().to_vec();
        report.outcome = match (&self.durable.failure, self.finished()) {
            (Some(failure), _) => format!("failed: {failure}"),
            (None, true) => "finished".into(),
            (None, false) => format!("stopped in {}", self.durable.phase),
        };
        report
    }

    /// Adds a worker; returns its id.
    pub fn register(&mut self, name: String, address: String, now: Instant) -> u64 {
        let id = self.next_worker;
        self.next_worker += 1;
        self.first_registration.get_or_insert(now);
        tracing::info!(worker = id, %name, %address, "worker registered");
        self.members.insert(id, Member::new(name, address, now));
        id
    }

    /// Records a sign of life; with `progress` (what the worker is doing at which step), the
    /// time it last moved on. Returns `(known, generation_current)`.
    pub fn heartbeat(
        &mut self,
        worker: u64,
        generation: u64,
        progress: Option<(Activity, u64)>,
        now: Instant,
    ) -> (bool, bool) {
        match self.members.get_mut(&worker) {
            Some(member) if !member.state.is_lost() => {
                member.last_seen = now;
                if let Some((activity, step)) = progress {
                    member.state.heard(activity, step, now);
                }
                (true, self.is_current(generation))
            }
            _ => (false, false),
        }
    }

    /// Records the device a worker said it trains on, for `status`.
    pub fn record_device(&mut self, worker: u64, device: DeviceInUse) {
        if let Some(member) = self.members.get_mut(&worker)
            && member.device.as_ref() != Some(&device)
        {
            tracing::info!(
                worker,
                backend = %device.backend,
                device = %device.name,
                replicas = device.replicas,
                "worker device"
            );
            member.device = Some(device);
        }
    }

    fn is_current(&self, generation: u64) -> bool {
        self.group
            .as_ref()
            .is_some_and(|g| g.generation == generation)
    }

    /// The worker asks for its next assignment; returns it when ready.
    pub fn request_assignment(
        &mut self,
        worker: u64,
        after: u64,
        now: Instant,
    ) -> Result<Option<Assignment>, Refusal> {
        let member = self
            .members
            .get_mut(&worker)
            .ok_or(Refusal::UnknownWorker(worker))?;
        if member.state.is_lost() {
            return Err(Refusal::LostWorker(worker));
        }
        member.last_seen = now;
        member.state.asks_after(after);
        if self
            .assignments
            .get(&worker)
            .is_some_and(|a| a.generation > after)
        {
            member.state.assigned();
            return Ok(self.assignments.remove(&worker));
        }
        if self.finished() {
            return Ok(Some(assignments::finish(self.generation)));
        }
        Ok(None)
    }

    /// Records a finished step of `phase`; returns whether the generation is still current.
    pub fn report_step(&mut self, worker: u64, phase: Phase, report: &StepReport) -> bool {
        let Some(group) = self
            .group
            .as_ref()
            .filter(|g| g.generation == report.generation)
        else {
            return false;
        };
        let Some(rank) = group.members.iter().position(|&m| m == worker) else {
            return false;
        };
        let world_size = group.members.len();
        if let Some(member) = self.members.get_mut(&worker) {
            member.state.finished(phase, report.step);
            member.samples_per_s = report.samples_per_s;
        }
        let loss = report.loss.unwrap_or_default();
        self.current_step = report.step + 1;
        self.store_retry.progressed(self.current_step);
        self.count_skipped(worker, report);
        let record = self.steps.record(phase, report.step, report.generation);
        record.step_s = record.step_s.max(report.step_s);
        record.allreduce_s = record.allreduce_s.max(report.allreduce_s);
        record.data_wait_s = record.data_wait_s.max(report.data_wait_s);
        record.samples_per_s += report.samples_per_s;
        record.world_size = world_size;
        if rank == 0 {
            record.loss = loss.total;
            record.learning_rate = loss.learning_rate;
            record.l1 = loss.l1;
            record.lpips = loss.lpips;
            record.grad_norm = loss.grad_norm;
            record.applied = loss.applied;
            self.last_loss = loss.total;
        }
        if let Some(checksum) = report.checksum {
            record.checksums.insert(rank as u32, checksum);
            let distinct: BTreeSet<u32> = record.checksums.values().copied().collect();
            if distinct.len() > 1 {
                let message = format!(
                    "{phase} step {} generation {}: parameter checksums differ across ranks: {:?}",
                    report.step, report.generation, record.checksums
                );
                tracing::error!("{message}");
                self.report.checksum_mismatches.push(message);
                let odd = faults::odd_ranks(&record.checksums);
                let members = self.group.as_ref().map_or(&[][..], |g| &g.members[..]);
                let odd = odd.iter().filter_map(|&r| members.get(r as usize)).copied();
                self.divergence = Some((report.generation, odd.collect()));
            }
        }
        true
    }

    /// `job.json` as it will read once `commit` is recorded, without recording it: the
    /// service writes this first and calls [`JobState::commit`] only when the write
    /// succeeded, so memory never holds a commit the store does not.
    pub fn durable_after_commit(
        &self,
        worker: u64,
        commit: &Commit,
        generation: u64,
    ) -> Result<Durable, Refusal> {
        self.check_commit(worker, commit, generation)?;
        let mut durable = self.durable.clone();
        durable.record_commit(
            commit.clone(),
            self.phase_steps(commit.phase),
            self.next_phase(commit.phase),
        );
        Ok(durable)
    }

    /// Why `worker` may not commit `commit` in `generation`, if it may not: a stale
    /// generation, a stranger, another phase, or parameters not every replica vouched for.
    pub(crate) fn check_commit(
        &self,
        worker: u64,
        commit: &Commit,
        generation: u64,
    ) -> Result<(), Refusal> {
        let Some(group) = self.group.as_ref().filter(|g| g.generation == generation) else {
            return Err(Refusal::StaleGeneration(generation));
        };
        if !group.members.contains(&worker) {
            return Err(Refusal::NotInGroup(worker));
        }
        if commit.phase != self.durable.phase {
            return Err(Refusal::WrongPhase {
                commit: commit.phase,
                job: self.durable.phase,
            });
        }
        self.check_verified(commit, generation, group.members.len())
    }

    /// Accepts a verified checkpoint commit from the current group; returns whether its phase
    /// ended with it.
    pub fn commit(
        &mut self,
        worker: u64,
        commit: Commit,
        generation: u64,
    ) -> Result<bool, Refusal> {
        self.check_commit(worker, &commit, generation)?;
        tracing::info!(phase = %commit.phase, step = commit.step, location = %commit.location, "checkpoint committed");
        self.report.commits.push(commit.clone());
        self.store_retry = StoreRetry::default();
        let (steps, next) = (
            self.phase_steps(commit.phase),
            self.next_phase(commit.phase),
        );
        if !self.durable.record_commit(commit.clone(), steps, next) {
            self.grow_at_commit(commit.step);
            return Ok(false);
        }
        self.group = None;
        self.lost_at = None;
        match commit.phase {
            Phase::Stage1 => {
                self.report.stage1_final = Some(commit.location);
                match self.durable.phase {
                    Phase::Stage2 => {
                        tracing::info!("stage 1 finished; stage 2 starts from its final weights")
                    }
                    Phase::Evaluate => tracing::info!(
                        "stage 1 finished, the last stage of this job; one worker evaluates its final weights"
                    ),
                    _ => tracing::info!(
                        "stage 1 finished, the last stage of this job; the job is done"
                    ),
                }
            }
            Phase::Stage2 if self.finished() => {
                tracing::info!("stage 2 finished; the job is done");
            }
            Phase::Stage2 => {
                tracing::info!("stage 2 finished; one worker evaluates the final weights");
            }
            Phase::Evaluate | Phase::Finished => {
                self.report.evaluation = Some(commit.location);
                tracing::info!("evaluation committed; the job is done");
            }
        }
        self.current_step = 0;
        Ok(true)
    }

    /// Declares silent workers lost, abandons broken generations and forms new ones. Returns
    /// true when something changed that waiters should see.
    pub fn tick(&mut self, now: Instant) -> bool {
        self.last_tick = Some(now);
        let mut changed = false;
        for (id, member) in self.members.iter_mut() {
            if !member.state.is_lost()
                && now.duration_since(member.last_seen) > self.timing.heartbeat_timeout
            {
                member.state.lose();
                tracing::warn!(worker = id, name = %member.name, "worker lost: no heartbeat");
                changed = true;
            }
        }
        changed |= self.remove_stalled(now);
        changed |= self.roll_back_divergence(now);
        if let Some(group) = &self.group {
            let lost = group
                .members
                .iter()
                .any(|m| self.members.get(m).is_none_or(|m| m.state.is_lost()));
            let last_step = self.phase_steps(group.phase) - 1;
            let troubled = group.members.iter().any(|m| {
                self.members.get(m).is_some_and(|member| {
                    member
                        .state
                        .gave_up(group.generation, (group.phase, last_step))
                })
            });
            if lost || troubled {
                tracing::warn!(
                    generation = group.generation,
                    lost,
                    troubled,
                    "abandoning generation; the group re-forms from the last commit"
                );
                let reason = if lost {
                    "a worker was lost (silent, left, stalled or blamed)"
                } else {
                    "a worker gave up on its step"
                };
                self.end_generation(now, reason.into());
                changed = true;
            }
        }
        if self.group.is_none() && !self.finished() {
            changed |= self.try_form(now);
        }
        changed
    }

    /// A worker said it is leaving (it shuts down between steps): it is treated as lost at
    /// once, so its group re-forms without waiting for its heartbeats to time out. Returns
    /// whether the worker was known.
    pub fn leave(&mut self, worker: u64, reason: &str) -> bool {
        let Some(member) = self.members.get_mut(&worker) else {
            return false;
        };
        let left = member.state.lose();
        if left {
            tracing::warn!(worker, name = %member.name, %reason, "worker left");
        }
        left
    }
}
