//! Every phase transition of the job, driven through the pure state machine with a hand-held
//! clock: forming groups, commits within and at the end of each phase, the evaluation, losses
//! and re-formation, refusals, and resuming from a saved state.
//!
//! This module holds the harness the tests share (a small job's plan, two registered workers on
//! one clock, readers of an assignment's work); the tests are grouped by what they exercise.

use std::time::{Duration, Instant};

use settings::work::{EvaluateWork, StepLoss, StepReport, TrainStart, TrainWork, Work};

use super::*;
use crate::config::ClusterConfig;

mod integrity;
mod membership;
mod phases;

/// Where the unit job's worker ids and generations start, so tests can name them.
const BASE: u64 = 1000;

/// The unit job's plan, with or without an evaluation stage.
fn plan(evaluate: bool) -> Plan {
    plan_with(if evaluate { "evaluate: {}\n" } else { "" })
}

/// The unit job's plan with `extra` top-level YAML.
fn plan_with(extra: &str) -> Plan {
    plan_of("{expected: 2, minimum: 1, regroup_grace_s: 1}", extra)
}

/// The unit job's plan with its `workers:` section and `extra` top-level YAML.
fn plan_of(workers: &str, extra: &str) -> Plan {
    let yaml = format!(
        "job: unit
auth: {{token: t}}
model: {{preset: tiny}}
data:
  generated: {{scenes: 1, trajectories: 1, frames: 6}}
stage1: {{steps: 4, global_batch: 6, micro_batch: 1, lpips_weight: 0}}
stage2: {{steps: 2, global_batch: 6, micro_batch: 1, lpips_weight: 0}}
checkpoint: {{uri: /tmp/unit-ckpt, every: 2}}
workers: {workers}
{extra}"
    );
    let config = ClusterConfig::from_yaml(&yaml, "unit.yaml").unwrap();
    tokio::runtime::Builder::new_current_thread()
        .build()
        .unwrap()
        .block_on(Plan::build(config))
        .unwrap()
}

/// Liveness settings short enough that a test crosses them with a few clock steps.
fn timing() -> Timing {
    Timing {
        heartbeat_timeout: Duration::from_secs(5),
        quorum_timeout: Duration::from_secs(60),
        regroup_grace: Duration::from_secs(1),
        stall_timeout: Duration::from_secs(10),
        exclusion: Duration::from_secs(30),
    }
}

/// A job state, the clock the test moves by hand, and the workers that take part.
struct Run {
    state: JobState,
    now: Instant,
    workers: Vec<u64>,
}

impl Run {
    fn new(evaluate: bool, durable: Option<Durable>) -> Self {
        Self::of(plan(evaluate), durable)
    }

    fn of(plan: Plan, durable: Option<Durable>) -> Self {
        let now = Instant::now();
        let mut state = JobState::starting_at(plan, timing(), durable, BASE);
        let workers = (0..2)
            .map(|i| state.register(format!("w{i}"), format!("127.0.0.1:{}", 7000 + i), now))
            .collect();
        Self {
            state,
            now,
            workers,
        }
    }

    /// Every live worker asks for work after `after`; the state ticks; returns what each got.
    fn assign(&mut self, after: u64) -> Vec<Option<Assignment>> {
        let mut got = Vec::new();
        for &worker in &self.workers {
            if let Ok(first) = self.state.request_assignment(worker, after, self.now) {
                got.push(first);
            }
        }
        self.state.tick(self.now);
        for (slot, &worker) in got.iter_mut().zip(&self.workers) {
            if slot.is_none() {
                *slot = self
                    .state
                    .request_assignment(worker, after, self.now)
                    .unwrap();
            }
        }
        got
    }

    /// `worker` commits `step` of `phase`, after every member of the group sent the same
    /// checksum for it (a training commit is taken only then: `verified.rs`).
    fn commit(&mut self, worker: u64, phase: Phase, step: u64, generation: u64) -> bool {
        if phase.is_training() {
            self.vouch(phase, step, generation);
        }
        let commit = Commit {
            phase,
            step,
            location: format!("mem://{phase}/{step}"),
        };
        self.state.commit(worker, commit, generation).unwrap()
    }

    /// Every member of `generation`'s group reports the same parameter checksum for the step
    /// that ends with `done` steps done.
    fn vouch(&mut self, phase: Phase, done: u64, generation: u64) {
        let members = self
            .state
            .group
            .as_ref()
            .map_or(Vec::new(), |g| g.members.clone());
        for worker in members {
            let report = StepReport {
                generation,
                step: done - 1,
                checksum: Some(7),
                ..StepReport::default()
            };
            self.state.report_step(worker, phase, &report);
        }
    }

    fn step(&mut self, worker: u64, phase: Phase, step: u64, generation: u64) -> bool {
        let report = StepReport {
            generation,
            step,
            loss: Some(StepLoss {
                total: 0.5,
                ..StepLoss::default()
            }),
            ..StepReport::default()
        };
        self.state.report_step(worker, phase, &report)
    }

    /// Every worker reports each of `steps` of `phase` in `generation`; each report must be
    /// accepted.
    fn all_step(&mut self, phase: Phase, steps: std::ops::Range<u64>, generation: u64) {
        for step in steps {
            for worker in self.workers.clone() {
                assert!(
                    self.step(worker, phase, step, generation),
                    "step {step} refused"
                );
            }
        }
    }
}

/// The training work of `assignment`; panics naming what came instead.
fn train(assignment: &Option<Assignment>) -> &TrainWork {
    match assignment.as_ref().map(|a| &a.work) {
        Some(Work::Train(train)) => train,
        other => panic!("expected a training assignment, got {other:?}"),
    }
}

/// The evaluation work of `assignment`; panics naming what came instead.
fn evaluation(assignment: &Option<Assignment>) -> &EvaluateWork {
    match assignment.as_ref().map(|a| &a.work) {
        Some(Work::Evaluate(evaluate)) => evaluate,
        other => panic!("expected an evaluation, got {other:?}"),
    }
}
