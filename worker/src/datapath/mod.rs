//! The data path of one worker: everything between its replicas' backward passes and their
//! next step, as one object with a visible life per step (as PyTorch DDP's `Reducer` is one):
//!
//! 1. **compute**: every replica's forward and backward pass on a thread of its own (its own
//!    device stream), each writing its gradients into its own flat buffer, kept from step to
//!    step; no replica waits for another's compute.
//! 2. **reduce locally**: the first replica's buffer is the host's sum; each other replica's
//!    is added into it as soon as that replica (and those before it) finished, while the
//!    others still compute. The loss terms ride at the end of the same buffer.
//! 3. **ring**: the sum is all-reduced in place across hosts ([`crate::collective::Ring`]).
//! 4. **apply**: every replica applies the same sum, side by side.
//! 5. **check**: when due, every replica hashes its parameters in bulk; they must agree.
//!
//! What overlaps what: replicas overlap each other in 1, 4 and 5, and 2 overlaps the replicas
//! still in 1. burn's backward pass returns all gradients at once, so the ring cannot start
//! before the last replica's backward pass ends; and AdamW clips by the global norm of the
//! whole sum, so no parameter can be updated before the ring's last chunk arrives. Within the
//! ring, chunks of consecutive ring steps overlap (it forwards each chunk once reduced).

mod replicas;

use std::sync::mpsc;
use std::time::Instant;

use data::BatchSource;
use proto::v1::Activity;
use settings::work::ChecksumEvery;
use tokio::runtime::Runtime;
use trainer_core::trainer::{SliceLoss, StepMetrics};

pub use replicas::{Applied, Computed, Replica, ReplicaError, ReplicaModel};

use crate::collective::{CollectiveError, Ring};
use crate::progress::Progress;

/// Values appended to the gradients: the loss, its L1 and its LPIPS term.
const LOSS_VALUES: usize = 3;

/// What one step measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepFigures {
    /// The optimizer's figures (of the first replica; all replicas apply the same update).
    pub metrics: StepMetrics,
    /// The L1 term of the global batch's loss.
    pub l1: f32,
    /// The LPIPS term (NaN when the stage trains without it).
    pub lpips: f32,
    /// Seconds in the ring all-reduce.
    pub allreduce_s: f64,
    /// Bytes of the all-reduced buffer.
    pub reduced_bytes: usize,
    /// The replicas' parameter checksum after the update, when one was due.
    pub checksum: Option<u32>,
    /// Where the step's time went.
    pub phases: PhaseTimes,
}

/// Seconds of each phase of a step, in the order they run.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PhaseTimes {
    /// Until the last replica's gradients were in the host's sum (compute, copy and the
    /// local reduction overlapping it).
    pub compute_s: f64,
    /// The longest a replica spent copying its gradients into its flat buffer (part of
    /// `compute_s`).
    pub copy_s: f64,
    /// Adding replicas' buffers into the sum (part of `compute_s`, overlapping the replicas
    /// still computing).
    pub local_reduce_s: f64,
    /// The ring all-reduce.
    pub ring_s: f64,
    /// Every replica's update, side by side (the upload and the optimizer).
    pub apply_s: f64,
    /// The longest a replica spent copying the sum to its device (part of `apply_s`).
    pub upload_s: f64,
    /// Every replica's parameter checksum, side by side (0 when none was due).
    pub checksum_s: f64,
}

/// Why a step failed. The model was not touched when it failed before the update.
#[derive(Debug, thiserror::Error)]
pub enum StepError {
    /// A replica's forward or backward pass failed (its data, its device).
    #[error("gradients of step {step}")]
    Gradients {
        /// The step.
        step: u64,
        /// What failed.
        #[source]
        source: ReplicaError,
    },
    /// The ring all-reduce failed; the error names the peer at fault, if any.
    #[error("all-reduce of step {step}")]
    AllReduce {
        /// The step.
        step: u64,
        /// What failed.
        #[source]
        source: CollectiveError,
    },
    /// The worker has no replica to step (it was given no device).
    #[error("no model replica to step: the worker drives no device")]
    NoReplicas,
    /// The summed buffer did not fit a replica's model (replicas of different models).
    #[error("the reduced gradients of step {step} do not fit the model")]
    Apply {
        /// The step.
        step: u64,
        /// The mismatch.
        #[source]
        source: ReplicaError,
    },
    /// The replicas received the same sum but their parameters differ: a faulty device. The
    /// generation fails and re-forms from the last commit.
    #[error(
        "this worker's replicas diverged after step {step}: parameter checksums {checksums:08x?}"
    )]
    ReplicasDiverged {
        /// The step just applied.
        step: u64,
        /// Each replica's checksum.
        checksums: Vec<u32>,
    },
}

/// When the parameter checksum is due: every `every` steps, at every step the commit schedule
/// commits (`commit_every`, and the stage's last), so that the coordinator can verify every
/// commit against every replica's checksum (`coordinator/src/job/verified.rs`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChecksumPlan {
    /// The interval, or `auto` from the model's size.
    pub every: ChecksumEvery,
    /// The commit interval (`checkpoint.every`).
    pub commit_every: u64,
    /// The stage's last step (counted from 1).
    pub total_steps: u64,
}

impl ChecksumPlan {
    /// Whether the checksum is due after step `done` (counted from 1) of a model of
    /// `parameters` values.
    pub fn due(&self, done: u64, parameters: usize) -> bool {
        done.is_multiple_of(self.every.steps(parameters))
            || done.is_multiple_of(self.commit_every.max(1))
            || done == self.total_steps
    }
}

/// The data path of a worker's generation: its ring, its flat buffers (allocated at the
/// first step and reused), and when to check the replicas' parameters.
pub struct DataPath {
    ring: Option<Ring>,
    checksums: ChecksumPlan,
    /// The host's sum of the replicas' gradients, loss terms at its end: the first replica's
    /// flat buffer.
    sum: Vec<f32>,
    /// One flat buffer for each further replica, each as long as `sum`.
    staging: Vec<Vec<f32>>,
    /// The next step hashes the parameters whatever the plan says (a suspension's step, which
    /// rank 0 commits).
    checksum_next: bool,
    /// Fault drill: from this step on, the reduced gradients are perturbed.
    diverge_from_step: Option<u64>,
}

impl DataPath {
    /// The data path through `ring`; `diverge_from_step` arms the silent-accelerator drill.
    pub fn new(ring: Ring, checksums: ChecksumPlan, diverge_from_step: Option<u64>) -> Self {
        Self {
            ring: Some(ring),
            checksums,
            sum: Vec::new(),
            staging: Vec::new(),
            checksum_next: false,
            diverge_from_step,
        }
    }

    /// Makes the next step hash the parameters: the coordinator gave notice that it is the
    /// suspension's step, which rank 0 commits and the coordinator verifies.
    pub fn checksum_next_step(&mut self) {
        self.checksum_next = true;
    }

    /// One optimizer step on every replica; they must all be at the same step. `progress`
    /// tells the heartbeats what the worker is doing (computing, then in the all-reduce),
    /// which is how the coordinator tells a stuck worker from one waiting for it.
    pub fn step<R: ReplicaModel>(
        &mut self,
        runtime: &Runtime,
        replicas: &mut [R],
        source: &dyn BatchSource,
        progress: &Progress,
    ) -> Result<StepFigures, StepError> {
        let first = replicas.first().ok_or(StepError::NoReplicas)?;
        let step = first.step();
        self.size_buffers(first.parameter_count() + LOSS_VALUES, replicas.len());
        progress.doing(Activity::Computing);
        let mut phases = self.compute(replicas, source, step)?;
        progress.doing(Activity::Allreduce);
        phases.ring_s = self.ring(runtime, step)?;
        let parameters = self.sum.len() - LOSS_VALUES;
        let [loss, l1, lpips] = [0, 1, 2].map(|i| self.sum[parameters + i]);
        self.drill(step);
        let applying = Instant::now();
        let applied = apply_all(replicas, &self.sum[..parameters], loss)
            .map_err(|source| StepError::Apply { step, source })?;
        let metrics = applied.first().ok_or(StepError::NoReplicas)?.metrics;
        phases.apply_s = applying.elapsed().as_secs_f64();
        phases.upload_s = applied.iter().map(|a| a.upload_s).fold(0.0, f64::max);
        let checking = Instant::now();
        let due = std::mem::take(&mut self.checksum_next);
        let checksum = if due || self.checksums.due(step + 1, parameters) {
            Some(checksum_all(replicas, step)?)
        } else {
            None
        };
        phases.checksum_s = checksum.map_or(0.0, |_| checking.elapsed().as_secs_f64());
        Ok(StepFigures {
            metrics,
            l1,
            lpips,
            allreduce_s: phases.ring_s,
            reduced_bytes: self.sum.len() * std::mem::size_of::<f32>(),
            checksum,
            phases,
        })
    }

    /// Allocates the flat buffers once, for `len` values and `replicas` replicas.
    fn size_buffers(&mut self, len: usize, replicas: usize) {
        if self.sum.len() != len {
            self.sum = vec![0.0; len];
            self.staging.clear();
        }
        let others = replicas.saturating_sub(1);
        self.staging.resize_with(others, || vec![0.0; len]);
    }

    /// Phases 1 and 2: every replica's gradients on its own thread, each added into the sum
    /// once it and every replica before it have arrived: the additions overlap the replicas
    /// still computing, and their order (so the sum's rounding) does not depend on which
    /// replica finished first.
    fn compute<R: ReplicaModel>(
        &mut self,
        replicas: &[R],
        source: &dyn BatchSource,
        step: u64,
    ) -> Result<PhaseTimes, StepError> {
        let started = Instant::now();
        let parameters = self.sum.len() - LOSS_VALUES;
        let (done, finished) = mpsc::channel();
        let mut reduction = InOrder::new(replicas.len());
        let buffers = std::iter::once(std::mem::take(&mut self.sum)).chain(self.staging.drain(..));
        std::thread::scope(|scope| {
            for (index, (replica, mut buffer)) in replicas.iter().zip(buffers).enumerate() {
                let done = done.clone();
                scope.spawn(move || {
                    let result = replica.gradients_into(source, &mut buffer[..parameters]);
                    // The receiver is read until every sender has sent.
                    let _ = done.send((index, buffer, result));
                });
            }
            drop(done);
            for (index, buffer, result) in finished {
                reduction.arrive(index, buffer, result);
            }
        });
        let (sum, staging, mut phases, failure) = reduction.finish();
        (self.sum, self.staging) = (sum, staging);
        if let Some(source) = failure {
            return Err(StepError::Gradients { step, source });
        }
        phases.compute_s = started.elapsed().as_secs_f64();
        Ok(phases)
    }

    /// Phase 3: the sum all-reduced across hosts, in place; returns its seconds.
    fn ring(&mut self, runtime: &Runtime, step: u64) -> Result<f64, StepError> {
        let ring = self.ring.take().ok_or(StepError::AllReduce {
            step,
            source: CollectiveError::Aborted("an earlier all-reduce lost the ring".into()),
        })?;
        let (ring, sum, reduced) = ring
            .all_reduce_on(runtime, std::mem::take(&mut self.sum), LOSS_VALUES)
            .map_err(|source| StepError::AllReduce { step, source })?;
        self.ring = Some(ring);
        self.sum = sum;
        Ok(reduced.seconds)
    }

    /// The silent-accelerator drill: this worker's reduced gradients perturbed.
    fn drill(&mut self, step: u64) {
        if self.diverge_from_step.is_some_and(|from| step >= from)
            && let Some(first) = self.sum.first_mut()
        {
            *first += 1.0;
            tracing::warn!(
                step,
                "fault drill: this worker's reduced gradients perturbed"
            );
        }
    }
}

/// Replicas' buffers added into the first one's, the sum, in replica order as they arrive
/// (one arriving early waits for those before it).
struct InOrder {
    waiting: Vec<Option<(Vec<f32>, Computed)>>,
    next: usize,
    sum: Vec<f32>,
    returned: Vec<Vec<f32>>,
    phases: PhaseTimes,
    failure: Option<ReplicaError>,
}

impl InOrder {
    fn new(replicas: usize) -> Self {
        Self {
            waiting: (0..replicas).map(|_| None).collect(),
            next: 0,
            sum: Vec::new(),
            returned: Vec::with_capacity(replicas),
            phases: PhaseTimes::default(),
            failure: None,
        }
    }

    /// Replica `index`'s buffer has arrived: adds every buffer now in order into the sum.
    fn arrive(&mut self, index: usize, buffer: Vec<f32>, result: Result<Computed, ReplicaError>) {
        match result {
            Ok(computed) => self.waiting[index] = Some((buffer, computed)),
            Err(error) => {
                self.failure.get_or_insert(error);
                self.keep(index, buffer);
            }
        }
        while let Some((mut buffer, computed)) =
            self.waiting.get_mut(self.next).and_then(Option::take)
        {
            let reducing = Instant::now();
            let parameters = buffer.len() - LOSS_VALUES;
            put_losses(&mut buffer[parameters..], computed.loss);
            if self.next > 0 {
                add_into(&mut self.sum, &buffer);
            }
            self.phases.local_reduce_s += reducing.elapsed().as_secs_f64();
            self.phases.copy_s = self.phases.copy_s.max(computed.copy_s);
            self.keep(self.next, buffer);
            self.next += 1;
        }
    }

    /// Takes a buffer back for the next step: replica 0's is the sum.
    fn keep(&mut self, index: usize, buffer: Vec<f32>) {
        if index == 0 {
            self.sum = buffer;
        } else {
            self.returned.push(buffer);
        }
    }

    /// The sum, the other buffers (for the next step), the phases' figures, and the first
    /// failure.
    fn finish(mut self) -> (Vec<f32>, Vec<Vec<f32>>, PhaseTimes, Option<ReplicaError>) {
        let left: Vec<(usize, Vec<f32>)> = self
            .waiting
            .iter_mut()
            .enumerate()
            .filter_map(|(index, slot)| slot.take().map(|(buffer, _)| (index, buffer)))
            .collect();
        left.into_iter()
            .for_each(|(index, buffer)| self.keep(index, buffer));
        (self.sum, self.returned, self.phases, self.failure)
    }
}

/// Phase 4: every replica applies `sum`, side by side.
fn apply_all<R: ReplicaModel>(
    replicas: &mut [R],
    sum: &[f32],
    loss: f32,
) -> Result<Vec<Applied>, ReplicaError> {
    side_by_side(replicas, |replica| replica.apply(sum, loss))
        .into_iter()
        .collect()
}

/// Phase 5: every replica's checksum, side by side; they received the same sum, so they
/// must be bitwise equal.
fn checksum_all<R: ReplicaModel>(replicas: &mut [R], step: u64) -> Result<u32, StepError> {
    let checksums = side_by_side(replicas, |replica| replica.checksum());
    match checksums.split_first() {
        Some((&first, rest)) if rest.iter().all(|&other| other == first) => Ok(first),
        Some(_) => Err(StepError::ReplicasDiverged { step, checksums }),
        None => Err(StepError::NoReplicas),
    }
}

/// `work` on every replica, each on a thread of its own; a lone replica's on the caller's,
/// since a thread would only add its start to the step (each replica keeps its own device
/// stream whatever thread drives it).
fn side_by_side<R: Send, T: Send>(replicas: &mut [R], work: impl Fn(&mut R) -> T + Sync) -> Vec<T> {
    if let [only] = replicas {
        return vec![work(only)];
    }
    let work = &work;
    std::thread::scope(|scope| {
        let handles: Vec<_> = replicas
            .iter_mut()
            .map(|replica| scope.spawn(move || work(replica)))
            .collect();
        handles.into_iter().map(join).collect()
    })
}

/// A scoped thread's result; its panic carried on to the caller.
fn join<T>(handle: std::thread::ScopedJoinHandle<'_, T>) -> T {
    match handle.join() {
        Ok(value) => value,
        Err(panic) => std::panic::resume_unwind(panic),
    }
}

/// The slice's loss terms into the last [`LOSS_VALUES`] values of a buffer.
fn put_losses(tail: &mut [f32], loss: SliceLoss) {
    tail.copy_from_slice(&[loss.total, loss.l1, loss.lpips]);
}

/// `sum += values`, element-wise.
fn add_into(sum: &mut [f32], values: &[f32]) {
    for (total, value) in sum.iter_mut().zip(values) {
        *total += value;
    }
}

#[cfg(test)]
mod tests;
