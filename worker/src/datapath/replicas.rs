//! The model replicas a worker drives, seen by the data path: something that computes its
//! slice's gradients into a flat buffer, applies a flat sum, and hashes its parameters. The
//! trainer-backed [`Replica`] is the one production uses; tests and the scaling benchmark
//! put replicas of their own behind the same trait (ones that wait instead of computing).

use std::time::Instant;

use data::BatchSource;
use trainer_core::flat::{
    LayoutError, flatten_gradients_into, parameter_checksum, parameter_count, unflatten_gradients,
};
use trainer_core::sharded::on_replica_stream;
use trainer_core::trainer::{SliceLoss, StepMetrics, TrainError, Trainer};

/// Why a replica could not take its part of a step.
#[derive(Debug, thiserror::Error)]
pub enum ReplicaError {
    /// Its forward or backward pass failed (its data, its device).
    #[error(transparent)]
    Train(#[from] TrainError),
    /// A flat buffer did not fit its model (replicas of different models).
    #[error(transparent)]
    Layout(#[from] LayoutError),
}

/// A replica's gradients of its slice, as the data path receives them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Computed {
    /// Its slice's loss and terms.
    pub loss: SliceLoss,
    /// Seconds spent copying the gradients from the device into the flat buffer.
    pub copy_s: f64,
}

/// A replica's update, as the data path receives it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Applied {
    /// The optimizer's figures.
    pub metrics: StepMetrics,
    /// Seconds spent copying the summed gradients from the host to the device.
    pub upload_s: f64,
}

/// One model replica of a worker as the data path drives it. Each method runs on a thread of
/// the data path's (one per replica), so the replicas compute, apply and hash side by side.
pub trait ReplicaModel: Send + Sync {
    /// The step this replica is at (all replicas of a worker are at the same one).
    fn step(&self) -> u64;
    /// Values in its flat gradient layout.
    fn parameter_count(&self) -> usize;
    /// The gradients of its slice of the current step written into `out` (exactly
    /// [`ReplicaModel::parameter_count`] values, module order), and its loss terms.
    fn gradients_into(
        &self,
        source: &dyn BatchSource,
        out: &mut [f32],
    ) -> Result<Computed, ReplicaError>;
    /// Applies the summed gradients `sum` of the whole global batch, whose loss is `loss`.
    fn apply(&mut self, sum: &[f32], loss: f32) -> Result<Applied, ReplicaError>;
    /// CRC-32 of its parameters ([`parameter_checksum`]).
    fn checksum(&self) -> u32;
}

/// One trainer-backed replica of this worker with its slice of the rank's samples each step.
pub struct Replica {
    /// The model, its optimizer state and its step.
    pub trainer: Trainer,
    /// Its index among the worker's replicas: which kept device stream it runs on.
    pub index: usize,
    /// The first global sample of its slice.
    pub first: u64,
    /// Samples in its slice.
    pub count: usize,
}

impl ReplicaModel for Replica {
    fn step(&self) -> u64 {
        self.trainer.step()
    }

    fn parameter_count(&self) -> usize {
        parameter_count(self.trainer.model())
    }

    fn gradients_into(
        &self,
        source: &dyn BatchSource,
        out: &mut [f32],
    ) -> Result<Computed, ReplicaError> {
        on_replica_stream(self.index, || {
            let (loss, grads) = self
                .trainer
                .slice_gradients(source, self.first, self.count)?;
            let copying = Instant::now();
            flatten_gradients_into(self.trainer.model(), grads, out)?;
            Ok(Computed {
                loss,
                copy_s: copying.elapsed().as_secs_f64(),
            })
        })
    }

    fn apply(&mut self, sum: &[f32], loss: f32) -> Result<Applied, ReplicaError> {
        on_replica_stream(self.index, || {
            let uploading = Instant::now();
            let grads = unflatten_gradients(self.trainer.model(), sum)?;
            let upload_s = uploading.elapsed().as_secs_f64();
            Ok(Applied {
                metrics: self.trainer.apply_gradients(&grads, loss),
                upload_s,
            })
        })
    }

    fn checksum(&self) -> u32 {
        on_replica_stream(self.index, || parameter_checksum(self.trainer.model()))
    }
}
