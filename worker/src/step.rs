//! One optimizer step of this worker: every replica's gradients of its slice, summed across the
//! worker's replicas, then across hosts by the ring, then applied to every replica. The loss
//! and its terms ride at the end of the same buffer, so one all-reduce carries them all.
//!
//! The replicas of one host come as a list, so a worker driving several devices adds
//! replicas, not code paths. Every replica holds the same weights before a step and receives
//! the same summed gradients, so they stay identical.

use data::BatchSource;
use proto::v1::Activity;
use tokio::runtime::Runtime;
use trainer_core::flat::{LayoutError, flatten_gradients, unflatten_gradients};
use trainer_core::trainer::{StepMetrics, TrainError, Trainer};

use crate::collective::{CollectiveError, Ring};
use crate::progress::Progress;

/// One model replica of this worker with its slice of the rank's samples each step.
pub struct Replica {
    /// The model, its optimizer state and its step.
    pub trainer: Trainer,
    /// The first global sample of its slice.
    pub first: u64,
    /// Samples in its slice.
    pub count: usize,
}

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
        source: TrainError,
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
    /// The summed buffer did not fit the model (replicas of different models).
    #[error("the reduced gradients of step {step} do not fit the model")]
    Layout {
        /// The step.
        step: u64,
        /// The mismatch.
        #[source]
        source: LayoutError,
    },
}

/// Values appended to the gradients: the loss, its L1 and its LPIPS term.
const LOSS_VALUES: usize = 3;

/// Runs steps on a worker's replicas through its ring.
pub struct Stepper {
    ring: Option<Ring>,
    /// Fault drill: from this step on, the reduced gradients are perturbed.
    diverge_from_step: Option<u64>,
}

impl Stepper {
    /// A stepper for `ring`; `diverge_from_step` arms the silent-accelerator drill.
    pub fn new(ring: Ring, diverge_from_step: Option<u64>) -> Self {
        Self {
            ring: Some(ring),
            diverge_from_step,
        }
    }

    /// One optimizer step on every replica; they must all be at the same step. `progress`
    /// tells the heartbeats what the worker is doing (computing, then in the all-reduce),
    /// which is how the coordinator tells a stuck worker from one waiting for it.
    pub fn step(
        &mut self,
        runtime: &Runtime,
        replicas: &mut [Replica],
        source: &dyn BatchSource,
        progress: &Progress,
    ) -> Result<StepFigures, StepError> {
        let step = replicas
            .first()
            .ok_or(StepError::NoReplicas)?
            .trainer
            .step();
        progress.doing(Activity::Computing);
        let local = local_sum(replicas, source, step)?;
        progress.doing(Activity::Allreduce);
        let ring = self.ring.take().ok_or(StepError::AllReduce {
            step,
            source: CollectiveError::Aborted("an earlier all-reduce lost the ring".into()),
        })?;
        let (ring, mut flat, reduced) = ring
            .all_reduce_on(runtime, local)
            .map_err(|source| StepError::AllReduce { step, source })?;
        self.ring = Some(ring);
        let reduced_bytes = flat.len() * std::mem::size_of::<f32>();
        let [loss, l1, lpips] = split_losses(&mut flat);
        if self.diverge_from_step.is_some_and(|from| step >= from)
            && let Some(first) = flat.first_mut()
        {
            *first += 1.0;
            tracing::warn!(
                step,
                "fault drill: this worker's reduced gradients perturbed"
            );
        }
        let mut metrics = None;
        for replica in replicas.iter_mut() {
            let grads = unflatten_gradients(replica.trainer.model(), &flat)
                .map_err(|source| StepError::Layout { step, source })?;
            let applied = replica.trainer.apply_gradients(&grads, loss);
            metrics.get_or_insert(applied);
        }
        Ok(StepFigures {
            metrics: metrics.ok_or(StepError::NoReplicas)?,
            l1,
            lpips,
            allreduce_s: reduced.seconds,
            reduced_bytes,
        })
    }
}

/// The replicas' gradients and loss terms of their slices, summed into one flat buffer with
/// the three loss values at its end.
fn local_sum(
    replicas: &[Replica],
    source: &dyn BatchSource,
    step: u64,
) -> Result<Vec<f32>, StepError> {
    let mut sum: Vec<f32> = Vec::new();
    for replica in replicas {
        let (loss, grads) = replica
            .trainer
            .slice_gradients(source, replica.first, replica.count)
            .map_err(|source| StepError::Gradients { step, source })?;
        let mut flat = flatten_gradients(replica.trainer.model(), &grads);
        flat.extend([loss.total, loss.l1, loss.lpips]);
        add_into(&mut sum, &flat);
    }
    Ok(sum)
}

/// `sum += values`, element-wise; an empty `sum` takes `values` as they are.
fn add_into(sum: &mut Vec<f32>, values: &[f32]) {
    if sum.is_empty() {
        sum.extend_from_slice(values);
    } else {
        for (total, value) in sum.iter_mut().zip(values) {
            *total += value;
        }
    }
}

/// Takes the loss, L1 and LPIPS values off the end of a reduced buffer; NaN where the buffer
/// is shorter than they are.
fn split_losses(flat: &mut Vec<f32>) -> [f32; LOSS_VALUES] {
    let mut values = [f32::NAN; LOSS_VALUES];
    for value in values.iter_mut().rev() {
        *value = flat.pop().unwrap_or(f32::NAN);
    }
    values
}

#[cfg(test)]
mod tests {
    use data::spec::RankSource;
    use settings::data::{DataSource, DataSpec, SamplerConfig};
    use settings::objective::Stage1Config;
    use settings::optim::{AdamWConfig, Schedule};
    use settings::train::{StageObjective, TrainConfig};
    use settings::{DeviceSet, XFactorConfig};
    use trainer_core::XFactor;
    use trainer_core::backend::{Backend, BackendDevices};
    use trainer_core::flat::{flatten_parameters, parameter_checksum};

    use super::*;
    use crate::collective::{CollectiveService, Link, RingKeys};

    #[test]
    fn replicas_gradients_add_up_element_wise() {
        let mut sum = Vec::new();
        add_into(&mut sum, &[1.0, 2.0, 0.5]);
        add_into(&mut sum, &[0.25, -2.0, 0.5]);
        assert_eq!(sum, [1.25, 0.0, 1.0]);
    }

    #[test]
    fn the_loss_terms_come_off_the_end_in_order() {
        let mut flat = vec![0.1, 0.2, 3.0, 1.0, 2.0];
        assert_eq!(split_losses(&mut flat), [3.0, 1.0, 2.0]);
        assert_eq!(flat, [0.1, 0.2]);
        let mut short = vec![7.0];
        let [loss, l1, lpips] = split_losses(&mut short);
        assert!(loss.is_nan() && l1.is_nan());
        assert_eq!(lpips, 7.0);
    }

    const GLOBAL_BATCH: usize = 4;

    fn train_config() -> TrainConfig {
        TrainConfig {
            seed: 5,
            objective: StageObjective::Stage1(Stage1Config {
                lpips_weight: 0.0,
                ..Stage1Config::default()
            }),
            global_batch: GLOBAL_BATCH,
            micro_batch: 1,
            shards: 1,
            schedule: Schedule::default(),
            optimizer: AdamWConfig::default(),
        }
    }

    /// One trainer per device of `set` on the CPU, from the same seed, with the global batch
    /// cut as `generation::prepare` cuts it.
    fn replicas(set: &DeviceSet) -> Vec<Replica> {
        let model = XFactorConfig::tiny(16);
        let devices = Backend::Cpu.devices(set).unwrap();
        let slices = crate::generation::replica_slices(0, GLOBAL_BATCH, 1, devices.len());
        devices
            .into_iter()
            .zip(slices)
            .map(|(device, (first, count))| {
                let device = device.autodiff();
                let xfactor = XFactor::new(&model, 5, &device).unwrap();
                let trainer =
                    Trainer::new(train_config(), model.clone(), xfactor, None, &device).unwrap();
                Replica {
                    trainer,
                    first,
                    count,
                }
            })
            .collect()
    }

    /// Parameters of every replica after `steps` steps, through a ring of one.
    fn train(set: &DeviceSet, steps: usize) -> (Vec<Vec<f32>>, Vec<u32>) {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        let spec = DataSpec {
            source: DataSource::Generated {
                scenes: 2,
                trajectories: 2,
                frames: 6,
            },
            sampler: SamplerConfig::stage1(),
            image_size: 16,
            seed: 5,
            global_batch: GLOBAL_BATCH,
        };
        let source = runtime.block_on(RankSource::open(&spec, 1, 0)).unwrap();
        let link = Link {
            token: "token".into(),
            timeout: std::time::Duration::from_secs(5),
            tls: None,
        };
        let mailbox = CollectiveService::default().mailbox();
        let cancelled = tokio_util::sync::CancellationToken::new();
        let peers = ["127.0.0.1:1".to_string()];
        let ring = runtime
            .block_on(Ring::connect(
                &mailbox,
                0,
                &peers,
                1,
                &RingKeys::default(),
                &link,
                cancelled,
            ))
            .unwrap();
        let mut stepper = Stepper::new(ring, None);
        let mut replicas = replicas(set);
        let progress = Progress::new();
        for _ in 0..steps {
            stepper
                .step(&runtime, &mut replicas, &source, &progress)
                .unwrap();
        }
        let parameters = replicas
            .iter()
            .map(|r| flatten_parameters(r.trainer.model()))
            .collect();
        let checksums = replicas
            .iter()
            .map(|r| parameter_checksum(r.trainer.model()))
            .collect();
        (parameters, checksums)
    }

    #[test]
    fn two_replicas_train_to_the_weights_of_one_with_the_same_global_batch() {
        let steps = 3;
        let (single, _) = train(&DeviceSet::Count(1), steps);
        let (pair, checksums) = train(&DeviceSet::Count(2), steps);
        assert_eq!(
            checksums[0], checksums[1],
            "the replicas stay bitwise identical"
        );
        let largest = single[0]
            .iter()
            .zip(&pair[0])
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        println!("replicas=2 steps={steps} max_abs_difference={largest:e}");
        assert!(largest <= 1e-5, "largest difference {largest:e}");
        assert_ne!(
            single[0],
            flatten_parameters(
                &XFactor::new(
                    &XFactorConfig::tiny(16),
                    5,
                    &Backend::Cpu.device().unwrap().autodiff()
                )
                .unwrap()
            ),
            "training moved the weights"
        );
    }
}
