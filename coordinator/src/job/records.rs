//! What the job remembers and reports: commits, the durable state written to `job.json`, and
//! the per-step and per-generation records of the report.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use settings::Phase;

/// A checkpoint made durable through the coordinator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Commit {
    /// The phase that wrote it (a training stage, or the evaluation's report).
    #[serde(rename = "stage", with = "settings::phase::as_number")]
    pub phase: Phase,
    /// Steps done when written.
    pub step: u64,
    /// URI prefix of the checkpoint.
    pub location: String,
}

/// What survives a coordinator restart: written to `<checkpoint uri>/job.json` after each commit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Durable {
    /// Job name, to refuse another job's state.
    pub job: String,
    /// Current phase (written as its number, as job states always were).
    #[serde(rename = "stage", with = "settings::phase::as_number")]
    pub phase: Phase,
    /// Newest commit of the current phase.
    pub last_commit: Option<Commit>,
    /// The commits of the current phase before `last_commit`, newest last (at most
    /// [`Durable::FALLBACKS`]): where the phase resumes when the newest proves corrupt.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub earlier_commits: Vec<Commit>,
    /// Stage 1's final checkpoint, once there is one.
    pub stage1_final: Option<String>,
    /// Stage 2's final checkpoint, once there is one (what the evaluation stage evaluates).
    #[serde(default)]
    pub stage2_final: Option<String>,
    /// Where the evaluation report was committed.
    #[serde(default)]
    pub evaluation: Option<String>,
    /// Why the job stopped short, when it did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<String>,
}

impl Durable {
    /// Commits kept to fall back on behind the newest.
    pub const FALLBACKS: usize = 2;

    /// Makes `commit` the newest, keeping the one it replaces to fall back on.
    pub fn push_commit(&mut self, commit: Commit) {
        if let Some(previous) = self.last_commit.replace(commit) {
            self.earlier_commits.push(previous);
            let excess = self.earlier_commits.len().saturating_sub(Self::FALLBACKS);
            self.earlier_commits.drain(..excess);
        }
    }

    /// Records `commit` of the current phase. When it is the phase's last step
    /// (`phase_steps`), the phase ends: its final checkpoint is kept where the next phase
    /// looks for it, and the job moves to `next_phase`. Returns whether the phase ended.
    pub fn record_commit(&mut self, commit: Commit, phase_steps: u64, next_phase: Phase) -> bool {
        self.push_commit(commit.clone());
        if commit.step < phase_steps {
            return false;
        }
        self.phase = next_phase;
        match commit.phase {
            Phase::Stage1 => {
                self.stage1_final = Some(commit.location);
                self.last_commit = None;
                self.earlier_commits.clear();
            }
            Phase::Stage2 => self.stage2_final = Some(commit.location),
            Phase::Evaluate | Phase::Finished => self.evaluation = Some(commit.location),
        }
        true
    }

    /// Drops the newest commit (found corrupt) for the one before it, if any; returns the
    /// commit dropped.
    pub fn fall_back(&mut self) -> Option<Commit> {
        let dropped = self.last_commit.take();
        self.last_commit = self.earlier_commits.pop();
        dropped
    }

    /// A job that has done nothing yet.
    pub fn new(job: String) -> Self {
        Self {
            job,
            phase: Phase::Stage1,
            last_commit: None,
            earlier_commits: Vec::new(),
            stage1_final: None,
            stage2_final: None,
            evaluation: None,
            failure: None,
        }
    }
}

/// One finished step as reported by every rank; read back from the store's step history when a
/// coordinator restarts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepRecord {
    /// The training stage.
    #[serde(rename = "stage", with = "settings::phase::as_number")]
    pub phase: Phase,
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
    /// The L1 term of the loss (as rank 0 saw it).
    pub l1: f32,
    /// The LPIPS term before its weight, where the stage has one.
    pub lpips: Option<f32>,
    /// Global gradient norm before clipping.
    pub grad_norm: f64,
    /// False when the update was skipped for an exploding gradient norm.
    pub applied: bool,
    /// Time the step waited for data: the slowest rank's.
    pub data_wait_s: f64,
    /// Samples per second of the whole group: the ranks' rates summed.
    pub samples_per_s: f64,
    /// Ranks of the generation that ran it.
    pub world_size: usize,
}

impl StepRecord {
    /// A record with nothing reported yet.
    pub fn new(phase: Phase, step: u64, generation: u64) -> Self {
        Self {
            phase,
            step,
            generation,
            loss: 0.0,
            learning_rate: 0.0,
            checksums: BTreeMap::new(),
            step_s: 0.0,
            allreduce_s: 0.0,
            l1: 0.0,
            lpips: None,
            grad_norm: 0.0,
            applied: true,
            data_wait_s: 0.0,
            samples_per_s: 0.0,
            world_size: 0,
        }
    }
}

/// The job report written when the job ends.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Report {
    /// Job name.
    pub job: String,
    /// "finished" or "stopped in ...".
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
    /// Commits found corrupt and dropped for the one before them.
    pub fallbacks: Vec<String>,
    /// Every generation: its group and where it started from.
    pub generations: Vec<GenerationStart>,
    /// Every generation that ended before its stage did: when, and why.
    pub generation_ends: Vec<GenerationEnd>,
    /// Workers blamed for a failed generation and sent to sit out a back-off.
    pub exclusions: Vec<Exclusion>,
    /// Frames skipped (corrupt, missing or unreadable) over the whole job.
    pub skipped_frames: u64,
    /// The newest of them, `dataset path: why`.
    pub skipped_examples: Vec<String>,
}

/// A worker blamed for a failed generation.
#[derive(Debug, Clone, Serialize)]
pub struct Exclusion {
    /// Its name.
    pub worker: String,
    /// Its collective address, by which it is known across registrations.
    pub address: String,
    /// Failures it has been blamed for so far.
    pub failures: u32,
    /// How long it sits out.
    pub seconds: f64,
}

/// How one generation ended before its stage did.
#[derive(Debug, Clone, Serialize)]
pub struct GenerationEnd {
    /// The generation.
    pub generation: u64,
    /// Its phase.
    #[serde(rename = "stage", with = "settings::phase::as_number")]
    pub phase: Phase,
    /// The step the job stood at.
    pub step: u64,
    /// Why it ended.
    pub reason: String,
}

/// How one generation started.
#[derive(Debug, Clone, Serialize)]
pub struct GenerationStart {
    /// The generation.
    pub generation: u64,
    /// Its phase.
    #[serde(rename = "stage", with = "settings::phase::as_number")]
    pub phase: Phase,
    /// Ranks.
    pub world_size: usize,
    /// Committed checkpoint it resumed from (empty: the stage's start).
    pub resume_from: String,
    /// Weights it started from (stage 2's start: stage 1's final checkpoint).
    pub init_weights_from: String,
}
