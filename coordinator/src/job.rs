//! The job's state machine: membership, group generations, stage progress and commits.
//!
//! A *generation* is one group of workers with fixed ranks. It ends when its stage ends or when
//! a member is lost (heartbeat silence) or reports trouble; survivors, and any replacement that
//! registered meanwhile, then form the next generation, which resumes from the last committed
//! checkpoint. Nothing here knows about tensors.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use proto::v1::{Assignment, JobStatus, assignment::Action};
use serde::Serialize;
use telemetry::curves::Curve;

use crate::plan::Plan;

/// A registered worker.
#[derive(Debug, Clone)]
struct Member {
    name: String,
    address: String,
    last_seen: Instant,
    lost: bool,
    waiting_after: Option<u64>,
    finished_step: Option<(u32, u64)>,
    samples_per_s: f64,
}

/// The running group.
#[derive(Debug, Clone)]
struct Group {
    generation: u64,
    members: Vec<u64>,
    stage: u32,
}

/// A checkpoint made durable through the coordinator.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Commit {
    /// 1 or 2.
    pub stage: u32,
    /// Steps done when written.
    pub step: u64,
    /// URI prefix of the checkpoint.
    pub location: String,
}

/// What survives a coordinator restart: written to `<checkpoint uri>/job.json` after each commit.
#[derive(Debug, Clone, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct Durable {
    /// Job name, to refuse another job's state.
    pub job: String,
    /// Current stage: 1 and 2 train, 3 evaluates (when the job has an `evaluate` section);
    /// past the last one the job is finished.
    pub stage: u32,
    /// Newest commit of the current stage.
    pub last_commit: Option<Commit>,
    /// Stage 1's final checkpoint, once there is one.
    pub stage1_final: Option<String>,
    /// Stage 2's final checkpoint, once there is one (what the evaluation stage evaluates).
    #[serde(default)]
    pub stage2_final: Option<String>,
    /// Where the evaluation report was committed.
    #[serde(default)]
    pub evaluation: Option<String>,
}

/// The stage number of the evaluation that follows stage 2.
pub const EVALUATE_STAGE: u32 = 3;

/// One finished step as reported by every rank.
#[derive(Debug, Clone, Default, Serialize)]
pub struct StepRecord {
    /// Stage.
    pub stage: u32,
    /// Step.
    pub step: u64,
    /// Generation that ran it (a step re-run after a loss appears twice).
    pub generation: u64,
    /// Loss of the global batch (as rank 0 saw it).
    pub loss: f32,
    /// Learning rate.
    pub learning_rate: f64,
    /// Parameter checksum by rank, where computed.
    pub checksums: BTreeMap<u32, u32>,
    /// Wall time of the step: the slowest rank's.
    pub step_s: f64,
    /// Time of the step's all-reduce: the slowest rank's.
    pub allreduce_s: f64,
}

/// The job report written when the job ends.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Report {
    /// Job name.
    pub job: String,
    /// "finished" or "failed: ...".
    pub outcome: String,
    /// Every commit in order.
    pub commits: Vec<Commit>,
    /// Stage 1's final checkpoint.
    pub stage1_final: Option<String>,
    /// Where the evaluation report was committed (its `report.json`, `report.md`, PNGs).
    pub evaluation: Option<String>,
    /// Every step report.
    pub steps: Vec<StepRecord>,
    /// Steps whose ranks disagreed on the checksum.
    pub checksum_mismatches: Vec<String>,
    /// Generations abandoned because a worker was lost or failed.
    pub restarts: u64,
    /// Every generation: its group and where it started from.
    pub generations: Vec<GenerationStart>,
}

/// How one generation started.
#[derive(Debug, Clone, Default, Serialize)]
pub struct GenerationStart {
    /// The generation.
    pub generation: u64,
    /// Its stage.
    pub stage: u32,
    /// Ranks.
    pub world_size: usize,
    /// Committed checkpoint it resumed from (empty: the stage's start).
    pub resume_from: String,
    /// Weights it started from (stage 2's start: stage 1's final checkpoint).
    pub init_weights_from: String,
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
}

/// The coordinator's whole state.
pub struct JobState {
    plan: Plan,
    timing: Timing,
    members: BTreeMap<u64, Member>,
    /// The generation number before this coordinator formed its first group.
    first_generation: u64,
    next_worker: u64,
    generation: u64,
    group: Option<Group>,
    durable: Durable,
    assignments: BTreeMap<u64, Assignment>,
    first_registration: Option<Instant>,
    lost_at: Option<Instant>,
    report: Report,
    current_step: u64,
    last_loss: f32,
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

impl JobState {
    /// A job at its start, or where `durable` (read back after a coordinator restart) left it.
    pub fn new(plan: Plan, timing: Timing, durable: Option<Durable>) -> Self {
        let base = incarnation_base();
        let durable = durable.map(|mut durable| {
            if durable.stage == EVALUATE_STAGE && durable.stage2_final.is_none() {
                tracing::warn!(
                    "the saved job state finished stage 2 before evaluation existed; nothing to evaluate"
                );
                durable.stage = EVALUATE_STAGE + 1;
            }
            durable
        });
        let job = plan.config.job.0.clone();
        let durable = durable.unwrap_or(Durable {
            job: job.clone(),
            stage: 1,
            last_commit: None,
            stage1_final: None,
            stage2_final: None,
            evaluation: None,
        });
        Self {
            plan,
            timing,
            members: BTreeMap::new(),
            next_worker: base + 1,
            generation: base,
            first_generation: base,
            group: None,
            assignments: BTreeMap::new(),
            first_registration: None,
            lost_at: None,
            report: Report {
                job,
                stage1_final: durable.stage1_final.clone(),
                evaluation: durable.evaluation.clone(),
                ..Report::default()
            },
            durable,
            current_step: 0,
            last_loss: f32::NAN,
        }
    }

    /// The plan being run.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// Whether both stages (and the evaluation, when the job has one) are done.
    pub fn finished(&self) -> bool {
        self.durable.stage > self.final_stage()
    }

    fn final_stage(&self) -> u32 {
        if self.plan.config.evaluate.is_some() {
            EVALUATE_STAGE
        } else {
            2
        }
    }

    /// Steps of `stage`; the evaluation counts as one.
    fn stage_steps(&self, stage: u32) -> u64 {
        if stage == EVALUATE_STAGE {
            1
        } else {
            self.plan.stage(stage).steps
        }
    }

    /// State to persist after a commit.
    pub fn durable(&self) -> &Durable {
        &self.durable
    }

    /// The report so far.
    pub fn report(&self) -> Report {
        let mut report = self.report.clone();
        report.outcome = if self.finished() {
            "finished".into()
        } else {
            format!("stopped in stage {}", self.durable.stage)
        };
        report
    }

    /// Adds a worker; returns its id.
    pub fn register(&mut self, name: String, address: String, now: Instant) -> u64 {
        let id = self.next_worker;
        self.next_worker += 1;
        self.first_registration.get_or_insert(now);
        tracing::info!(worker = id, %name, %address, "worker registered");
        self.members.insert(
            id,
            Member {
                name,
                address,
                last_seen: now,
                lost: false,
                waiting_after: None,
                finished_step: None,
                samples_per_s: 0.0,
            },
        );
        id
    }

    /// Records a heartbeat. Returns `(known, generation_current)`.
    pub fn heartbeat(&mut self, worker: u64, generation: u64, now: Instant) -> (bool, bool) {
        match self.members.get_mut(&worker) {
            Some(member) if !member.lost => {
                member.last_seen = now;
                (true, self.is_current(generation))
            }
            _ => (false, false),
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
    ) -> Result<Option<Assignment>, String> {
        let Some(member) = self.members.get_mut(&worker) else {
            return Err(format!("unknown worker {worker}: register first"));
        };
        if member.lost {
            return Err(format!(
                "worker {worker} was declared lost after missing heartbeats: register again"
            ));
        }
        member.last_seen = now;
        member.waiting_after = Some(after);
        if let Some(assignment) = self.assignments.get(&worker)
            && assignment.generation > after
        {
            let assignment = assignment.clone();
            self.assignments.remove(&worker);
            if let Some(member) = self.members.get_mut(&worker) {
                member.waiting_after = None;
            }
            return Ok(Some(assignment));
        }
        if self.finished() {
            return Ok(Some(Assignment {
                action: Action::Finish as i32,
                generation: self.generation,
                ..Assignment::default()
            }));
        }
        Ok(None)
    }

    /// Records a finished step; returns whether the generation is still current.
    pub fn report_step(&mut self, worker: u64, report: &proto::v1::StepReport) -> bool {
        let current = self.is_current(report.generation);
        let Some(group) = self.group.clone().filter(|_| current) else {
            return false;
        };
        let Some(rank) = group.members.iter().position(|&m| m == worker) else {
            return false;
        };
        if let Some(member) = self.members.get_mut(&worker) {
            member.finished_step = Some((report.stage, report.step));
            member.samples_per_s = report.samples_per_s;
        }
        let loss = report.loss.unwrap_or_default();
        self.current_step = report.step + 1;
        let index = self.report.steps.iter().position(|r| {
            r.stage == report.stage && r.step == report.step && r.generation == report.generation
        });
        let record = match index {
            Some(i) => &mut self.report.steps[i],
            None => {
                self.report.steps.push(StepRecord {
                    stage: report.stage,
                    step: report.step,
                    generation: report.generation,
                    ..StepRecord::default()
                });
                let last = self.report.steps.len() - 1;
                &mut self.report.steps[last]
            }
        };
        record.step_s = record.step_s.max(report.step_s);
        record.allreduce_s = record.allreduce_s.max(report.allreduce_s);
        if rank == 0 {
            record.loss = loss.total;
            record.learning_rate = loss.learning_rate;
            self.last_loss = loss.total;
        }
        if report.checksum_computed {
            record
                .checksums
                .insert(rank as u32, report.parameter_checksum);
            let distinct: std::collections::BTreeSet<u32> =
                record.checksums.values().copied().collect();
            if distinct.len() > 1 {
                let message = format!(
                    "stage {} step {} generation {}: parameter checksums differ across ranks: {:?}",
                    report.stage, report.step, report.generation, record.checksums
                );
                tracing::error!("{message}");
                self.report.checksum_mismatches.push(message);
            }
        }
        true
    }

    /// Accepts a verified checkpoint commit from the current group; returns whether the stage
    /// ended with it.
    pub fn commit(&mut self, worker: u64, commit: Commit, generation: u64) -> Result<bool, String> {
        if !self.is_current(generation) {
            return Err(format!(
                "generation {generation} is no longer current; commit refused"
            ));
        }
        if !self
            .group
            .as_ref()
            .is_some_and(|g| g.members.contains(&worker))
        {
            return Err(format!("worker {worker} is not in the current group"));
        }
        if commit.stage != self.durable.stage {
            return Err(format!(
                "commit for stage {} while the job is in stage {}",
                commit.stage, self.durable.stage
            ));
        }
        tracing::info!(stage = commit.stage, step = commit.step, location = %commit.location, "checkpoint committed");
        self.report.commits.push(commit.clone());
        self.durable.last_commit = Some(commit.clone());
        let total = self.stage_steps(commit.stage);
        if commit.step < total {
            return Ok(false);
        }
        self.group = None;
        self.lost_at = None;
        match commit.stage {
            1 => {
                self.durable.stage1_final = Some(commit.location.clone());
                self.report.stage1_final = Some(commit.location);
                self.durable.stage = 2;
                self.durable.last_commit = None;
                tracing::info!("stage 1 finished; stage 2 starts from its final weights");
            }
            2 => {
                self.durable.stage2_final = Some(commit.location);
                self.durable.stage = 3;
                if self.finished() {
                    tracing::info!("stage 2 finished; the job is done");
                } else {
                    tracing::info!("stage 2 finished; one worker evaluates its final weights");
                }
            }
            _ => {
                self.durable.evaluation = Some(commit.location.clone());
                self.report.evaluation = Some(commit.location);
                self.durable.stage = EVALUATE_STAGE + 1;
                tracing::info!("evaluation committed; the job is done");
            }
        }
        self.current_step = 0;
        Ok(true)
    }

    /// Declares silent workers lost, abandons broken generations and forms new ones. Returns
    /// true when something changed that waiters should see.
    pub fn tick(&mut self, now: Instant) -> bool {
        let mut changed = false;
        for (id, member) in self.members.iter_mut() {
            if !member.lost && now.duration_since(member.last_seen) > self.timing.heartbeat_timeout
            {
                member.lost = true;
                tracing::warn!(worker = id, name = %member.name, "worker lost: no heartbeat");
                changed = true;
            }
        }
        if let Some(group) = &self.group {
            let lost = group
                .members
                .iter()
                .any(|m| self.members.get(m).is_none_or(|m| m.lost));
            let total = self.stage_steps(group.stage);
            let troubled = group.members.iter().any(|m| {
                self.members.get(m).is_some_and(|member| {
                    member.waiting_after == Some(group.generation)
                        && member.finished_step != Some((group.stage, total - 1))
                })
            });
            if lost || troubled {
                tracing::warn!(
                    generation = group.generation,
                    lost,
                    troubled,
                    "abandoning generation; the group re-forms from the last commit"
                );
                self.group = None;
                self.report.restarts += 1;
                self.lost_at = Some(now);
                changed = true;
            }
        }
        if self.group.is_none() && !self.finished() {
            changed |= self.try_form(now);
        }
        changed
    }

    fn try_form(&mut self, now: Instant) -> bool {
        let settings = &self.plan.config.workers;
        let (expected, minimum) = (settings.expected.0 as usize, settings.minimum.0 as usize);
        let alive: Vec<u64> = self
            .members
            .iter()
            .filter(|(_, m)| !m.lost)
            .map(|(&id, _)| id)
            .collect();
        let waiting: Vec<u64> = alive
            .iter()
            .copied()
            .filter(|id| self.members[id].waiting_after.is_some())
            .collect();
        let ready = if self.generation == self.first_generation {
            waiting.len() >= expected
                || (waiting.len() >= minimum
                    && self
                        .first_registration
                        .is_some_and(|t| now.duration_since(t) >= self.timing.quorum_timeout))
        } else {
            let all_in = waiting.len() == alive.len() || waiting.len() >= expected;
            let grace_over = self
                .lost_at
                .is_none_or(|t| now.duration_since(t) >= self.timing.regroup_grace);
            waiting.len() >= minimum && all_in && (grace_over || waiting.len() >= expected)
        };
        if !ready {
            return false;
        }
        let stage = self.durable.stage;
        let size = if stage == EVALUATE_STAGE { 1 } else { expected };
        let members: Vec<u64> = waiting.into_iter().take(size).collect();
        self.generation += 1;
        let group = Group {
            generation: self.generation,
            members: members.clone(),
            stage,
        };
        let peers: Vec<String> = members
            .iter()
            .map(|m| self.members[m].address.clone())
            .collect();
        tracing::info!(
            generation = self.generation,
            stage,
            world_size = members.len(),
            resume = ?self.durable.last_commit.as_ref().map(|c| c.step),
            "group formed"
        );
        for (rank, &worker) in members.iter().enumerate() {
            let assignment = self.assignment(stage, rank, &peers);
            if rank == 0 {
                self.report.generations.push(GenerationStart {
                    generation: self.generation,
                    stage,
                    world_size: members.len(),
                    resume_from: assignment.resume_from.clone(),
                    init_weights_from: assignment.init_weights_from.clone(),
                });
            }
            self.assignments.insert(worker, assignment);
            if let Some(member) = self.members.get_mut(&worker) {
                member.finished_step = None;
            }
        }
        self.group = Some(group);
        true
    }

    fn assignment(&self, stage: u32, rank: usize, peers: &[String]) -> Assignment {
        if stage == EVALUATE_STAGE {
            return self.evaluation_assignment(peers);
        }
        let plan = self.plan.stage(stage);
        let config = &self.plan.config;
        let resume = self
            .durable
            .last_commit
            .as_ref()
            .filter(|c| c.stage == stage)
            .map(|c| c.location.clone())
            .unwrap_or_default();
        let init = if stage == 2 && resume.is_empty() {
            self.durable.stage1_final.clone().unwrap_or_default()
        } else {
            String::new()
        };
        Assignment {
            action: Action::Train as i32,
            generation: self.generation,
            rank: rank as u32,
            world_size: peers.len() as u32,
            peers: peers.to_vec(),
            stage,
            total_steps: plan.steps,
            resume_from: resume,
            init_weights_from: init,
            checkpoint_prefix: format!(
                "{}/stage{stage}",
                config.checkpoint.uri.0.trim_end_matches('/')
            ),
            checkpoint_every: config.checkpoint.every.0,
            model_config_json: serde_json::to_string(&self.plan.model).unwrap_or_default(),
            train_config_json: serde_json::to_string(&plan.train).unwrap_or_default(),
            data_json: serde_json::to_string(&plan.data).unwrap_or_default(),
            checksum_every: config.workers.checksum_every.0,
            lpips_weights: plan.lpips_weights.clone().unwrap_or_default(),
            device: config.workers.device.name().into(),
            evaluation_json: String::new(),
        }
    }

    /// The evaluation of stage 2's final weights, for the one worker of the group.
    fn evaluation_assignment(&self, peers: &[String]) -> Assignment {
        let config = &self.plan.config;
        Assignment {
            action: Action::Evaluate as i32,
            generation: self.generation,
            rank: 0,
            world_size: 1,
            peers: peers.to_vec(),
            stage: EVALUATE_STAGE,
            total_steps: 1,
            init_weights_from: self.durable.stage2_final.clone().unwrap_or_default(),
            checkpoint_prefix: format!(
                "{}/evaluation",
                config.checkpoint.uri.0.trim_end_matches('/')
            ),
            model_config_json: serde_json::to_string(&self.plan.model).unwrap_or_default(),
            evaluation_json: serde_json::to_string(&config.evaluate).unwrap_or_default(),
            device: config.workers.device.name().into(),
            ..Assignment::default()
        }
    }

    /// Progress for the `status` command.
    pub fn status(&self) -> JobStatus {
        let stage = self.durable.stage;
        JobStatus {
            job_name: self.plan.config.job.0.clone(),
            phase: match (stage, &self.group) {
                _ if self.finished() => "finished".into(),
                (EVALUATE_STAGE, Some(_)) => "evaluate".into(),
                (EVALUATE_STAGE, None) => "evaluate (waiting for a worker)".into(),
                (s, Some(_)) => format!("stage{s}"),
                (s, None) => format!("stage{s} (waiting for workers)"),
            },
            generation: self.generation,
            workers: self.members.values().filter(|m| !m.lost).count() as u32,
            step: self.current_step,
            total_steps: if stage <= 2 {
                self.plan.stage(stage).steps
            } else {
                0
            },
            last_commit: self
                .durable
                .last_commit
                .as_ref()
                .map(|c| c.location.clone())
                .unwrap_or_default(),
            last_loss: self.last_loss,
            restarts: self.report.restarts,
            job_steps_done: match stage {
                1 => self.current_step,
                2 => self.plan.stage(1).steps + self.current_step,
                _ => self.plan.stage(1).steps + self.plan.stage(2).steps,
            },
            job_steps_total: self.plan.stage(1).steps + self.plan.stage(2).steps,
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
            .filter(|(_, m)| !m.lost)
            .map(|(&id, _)| id)
            .collect()
    }

    /// Checksum disagreements so far.
    pub fn mismatches(&self) -> usize {
        self.report.checksum_mismatches.len()
    }

    /// A worker said it is leaving (it shuts down between steps): it is treated as lost at
    /// once, so its group re-forms without waiting for its heartbeats to time out. Returns
    /// whether the worker was known.
    pub fn leave(&mut self, worker: u64, reason: &str) -> bool {
        match self.members.get_mut(&worker) {
            Some(member) if !member.lost => {
                member.lost = true;
                tracing::warn!(worker, name = %member.name, %reason, "worker left");
                true
            }
            _ => false,
        }
    }

    /// The loss curve of `stage` as recorded by this coordinator: one row per step (the last
    /// run of a step that was re-run after a restart), with loss and learning rate.
    pub fn curve(&self, stage: u32) -> Curve {
        let mut rows: BTreeMap<u64, Vec<f64>> = BTreeMap::new();
        for record in self.report.steps.iter().filter(|r| r.stage == stage) {
            rows.insert(
                record.step,
                vec![f64::from(record.loss), record.learning_rate],
            );
        }
        Curve {
            columns: vec!["loss".into(), "learning_rate".into()],
            rows: rows.into_iter().collect(),
        }
    }
}
