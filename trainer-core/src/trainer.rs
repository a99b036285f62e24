//! The single-process trainer: one stage of XFactor training over a [`BatchSource`], with
//! checkpoints that resume exactly.
//!
//! A checkpoint directory holds `model.safetensors` + `model.json` (weights and model config),
//! `optimizer.safetensors` (AdamW moments by flax name) and `state.json` (step, update count,
//! seed). Every random draw is keyed by `(seed, step, sample)`, so the step number is the whole
//! RNG position and resuming needs nothing else.

use std::path::{Path, PathBuf};

use burn::optim::GradientsParams;
use burn::tensor::{Device, FloatDType};
use serde::{Deserialize, Serialize};

use data::{BatchSource, SampleError, Samples};
use settings::XFactorConfig;
use settings::model::Precision;
use settings::train::{StageObjective, TrainConfig};

use crate::checkpoint::{self, CheckpointError};
use crate::flax::{FlaxError, FlaxTensors};
use crate::lpips::Lpips;
use crate::model::XFactor;
use crate::objective::{ObjectiveBatch, Stage1Objective, Stage2Objective, objective_loss};
use crate::optim::AdamW;
use crate::sharded::{add_gradients, sharded_gradients};

/// Why training could not start or continue.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The LPIPS weight is positive but no LPIPS network was given.
    #[error(
        "the objective weights LPIPS by {0} but no LPIPS weights were given: convert them with tools/convert_lpips_weights.py or set lpips_weight to 0"
    )]
    MissingLpips(f64),
    /// The model's mixed precision or compute type needs a half type this device cannot
    /// compute in.
    #[error(
        "the model's {key} {precision} needs {precision} arithmetic, which this device does not have; use {key} f32, or f16 where bf16 is storage-only"
    )]
    Precision {
        /// `precision` or `compute`: the key under `model:` that asks for it.
        key: &'static str,
        /// The half type asked for.
        precision: &'static str,
    },
    /// The batch sizes do not divide.
    #[error("global_batch {global} must be a positive multiple of micro_batch {micro}")]
    BatchSizes {
        /// Configured global batch.
        global: usize,
        /// Configured micro-batch.
        micro: usize,
    },
    /// The batch source failed.
    #[error("batch source, step {step}")]
    Source {
        /// Step being assembled.
        step: u64,
        /// What the source reported.
        #[source]
        source: SampleError,
    },
    /// The source returned samples of the other stage.
    #[error("batch source returned {found} samples for a {expected} objective")]
    WrongSamples {
        /// The objective's stage.
        expected: &'static str,
        /// What came back.
        found: &'static str,
    },
    /// A checkpoint file could not be written or read.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// The optimiser moments could not be written.
    #[error(transparent)]
    TensorFile(#[from] TensorFileError),
    /// Optimiser state is missing or misshapen.
    #[error("optimizer state: {0}")]
    OptimizerState(#[from] FlaxError),
    /// `state.json` could not be written or read.
    #[error("trainer state {path}: {reason}")]
    State {
        /// File at fault.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// Why tensors could not be written to a safetensors file.
#[derive(Debug, thiserror::Error)]
pub enum TensorFileError {
    /// A tensor's values do not fill its shape.
    #[error("tensor `{name}` does not match its shape {shape:?}")]
    Shape {
        /// The tensor's name.
        name: String,
        /// Its shape.
        shape: Vec<usize>,
        /// What the safetensors library found.
        #[source]
        source: safetensors::SafeTensorError,
    },
    /// The file could not be written.
    #[error("cannot write {}", path.display())]
    Write {
        /// The temporary file being written.
        path: PathBuf,
        /// What the safetensors library reported.
        #[source]
        source: safetensors::SafeTensorError,
    },
    /// The written file could not be renamed into place.
    #[error("cannot rename {} to {}", from.display(), to.display())]
    Rename {
        /// The temporary file.
        from: PathBuf,
        /// Its final name.
        to: PathBuf,
        /// What the file system said.
        #[source]
        source: std::io::Error,
    },
}

/// What one optimiser step measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepMetrics {
    /// The step just taken (counted from 0).
    pub step: u64,
    /// Loss of the global batch.
    pub loss: f32,
    /// Learning rate used.
    pub learning_rate: f64,
    /// Global gradient norm before clipping.
    pub grad_norm: f64,
    /// False when the update was skipped for an exploding norm.
    pub applied: bool,
}

/// The loss of a slice of the global batch and its terms, each weighted `1 / global_batch` per
/// sample as the gradients are, so the data-parallel ranks' values sum to the global batch's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SliceLoss {
    /// `l1 + w * lpips`, the loss the gradients are of.
    pub total: f32,
    /// The L1 term.
    pub l1: f32,
    /// The LPIPS term before its weight; NaN when the stage trains without LPIPS.
    pub lpips: f32,
}

/// `state.json` of a checkpoint directory; the importer of release checkpoints writes it too.
#[derive(Debug, Serialize, Deserialize)]
pub(crate) struct TrainerState {
    /// The next step to run.
    pub(crate) step: u64,
    /// AdamW updates applied (bias-correction count).
    pub(crate) updates: u64,
    /// Seed of the run that wrote it.
    pub(crate) seed: u64,
}

/// Refuses a model whose `precision` or `compute` asks for a half type `device` cannot
/// compute in, naming the key: the trainer and the evaluation check before any kernel runs
/// (on such a device the first half-typed op would panic).
pub fn check_device_arithmetic(config: &XFactorConfig, device: &Device) -> Result<(), TrainError> {
    check_precision("precision", config.precision, device)?;
    check_precision("compute", config.compute, device)
}

/// Refuses a mixed precision or compute type (`key`) whose half type `device` cannot compute
/// in.
fn check_precision(
    key: &'static str,
    precision: Precision,
    device: &Device,
) -> Result<(), TrainError> {
    let half = match precision {
        Precision::F32 => return Ok(()),
        Precision::Bf16 => FloatDType::BF16,
        Precision::F16 => FloatDType::F16,
    };
    if device.supports_dtype(half) {
        Ok(())
    } else {
        Err(TrainError::Precision {
            key,
            precision: precision.name(),
        })
    }
}

/// A model, its optimiser and the step counter.
pub struct Trainer {
    config: TrainConfig,
    model_config: XFactorConfig,
    model: XFactor,
    optimizer: AdamW,
    lpips: Option<Lpips>,
    step: u64,
    device: Device,
}

impl Trainer {
    /// Starts from `model` at step 0. Refuses a positive LPIPS weight without an LPIPS network;
    /// with weight 0 it logs once that LPIPS is off.
    pub fn new(
        config: TrainConfig,
        model_config: XFactorConfig,
        model: XFactor,
        lpips: Option<Lpips>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let weight = config.objective.lpips_weight();
        if weight > 0.0 && lpips.is_none() {
            return Err(TrainError::MissingLpips(weight));
        }
        if weight == 0.0 {
            tracing::info!("LPIPS weight is 0: training with the L1 loss alone");
        }
        check_device_arithmetic(&model_config, device)?;
        if config.micro_batch == 0
            || config.global_batch == 0
            || !config.global_batch.is_multiple_of(config.micro_batch)
        {
            return Err(TrainError::BatchSizes {
                global: config.global_batch,
                micro: config.micro_batch,
            });
        }
        Ok(Self {
            optimizer: AdamW::new(config.optimizer.clone()),
            config,
            model_config,
            model,
            lpips,
            step: 0,
            device: device.clone(),
        })
    }

    /// The model as trained so far.
    pub fn model(&self) -> &XFactor {
        &self.model
    }

    /// The next step to run.
    pub fn step(&self) -> u64 {
        self.step
    }

    /// One optimiser update over the global batch of the current step.
    pub fn train_step(&mut self, source: &dyn BatchSource) -> Result<StepMetrics, TrainError> {
        let (loss, grads) = self.batch_gradients(source)?;
        Ok(self.apply_gradients(&grads, loss))
    }

    /// The loss and gradients of the current step's global batch, accumulated over micro-batches
    /// (each split into shards), without touching the model.
    pub fn batch_gradients(
        &self,
        source: &dyn BatchSource,
    ) -> Result<(f32, GradientsParams), TrainError> {
        self.slice_gradients(source, 0, self.config.global_batch)
            .map(|(loss, grads)| (loss.total, grads))
    }

    /// This process's share of the current step: the loss and gradients of global samples
    /// `first .. first + count`, each weighted `1 / global_batch`, so that summing the shares of
    /// all data-parallel ranks (the all-reduce) gives exactly [`Trainer::batch_gradients`].
    /// The last micro-batch may be smaller than `micro_batch`.
    pub fn slice_gradients(
        &self,
        source: &dyn BatchSource,
        first: u64,
        count: usize,
    ) -> Result<(SliceLoss, GradientsParams), TrainError> {
        let step = self.step;
        let _span = tracing::info_span!("slice_gradients", step, first, count).entered();
        let micro = self.config.micro_batch;
        let mut loss = SliceLoss {
            total: 0.0,
            l1: 0.0,
            lpips: if self.lpips.is_some() { 0.0 } else { f32::NAN },
        };
        let mut accumulated: Option<GradientsParams> = None;
        for offset in (0..count).step_by(micro) {
            let size = micro.min(count - offset);
            let share = size as f64 / self.config.global_batch as f64;
            let batch = self.assemble(source, step, first + offset as u64, size)?;
            let (micro_loss, grads) = self.micro_batch_gradients(&batch, share);
            loss.total += micro_loss.total;
            loss.l1 += micro_loss.l1;
            loss.lpips += micro_loss.lpips;
            accumulated = Some(match accumulated {
                None => grads,
                Some(sum) => add_gradients(&self.model, sum, grads),
            });
        }
        Ok((loss, accumulated.unwrap_or_default()))
    }

    /// The model configuration being trained.
    pub fn model_config(&self) -> &XFactorConfig {
        &self.model_config
    }

    /// The device the model lives on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Applies one optimiser update with the current step's learning rate and advances the step.
    pub fn apply_gradients(&mut self, grads: &GradientsParams, loss: f32) -> StepMetrics {
        let step = self.step;
        let learning_rate = self.config.schedule.learning_rate(step);
        let (model, report) = self
            .optimizer
            .step(self.model.clone(), grads, learning_rate);
        self.model = model;
        self.step += 1;
        tracing::debug!(
            step,
            loss,
            learning_rate,
            grad_norm = report.grad_norm,
            "update"
        );
        StepMetrics {
            step,
            loss,
            learning_rate,
            grad_norm: report.grad_norm,
            applied: report.applied,
        }
    }

    fn assemble(
        &self,
        source: &dyn BatchSource,
        step: u64,
        first: u64,
        count: usize,
    ) -> Result<Vec<ObjectiveBatch>, TrainError> {
        let samples = source
            .samples(step, first, count)
            .map_err(|source| TrainError::Source { step, source })?;
        let shards = self.config.shards.clamp(1, count.max(1));
        let (seed, patch) = (self.config.seed, self.model_config.patch_size);
        let bounds = |shard: usize| (shard * count / shards, (shard + 1) * count / shards);
        (0..shards)
            .map(|shard| {
                let (begin, end) = bounds(shard);
                let offset = first + begin as u64;
                match (&self.config.objective, &samples) {
                    (StageObjective::Stage1(objective), Samples::Pairs(pairs))
                        if objective.variant.stage1_frames() == 2 =>
                    {
                        Ok(objective.batch(
                            &pairs[begin..end],
                            seed,
                            step,
                            offset,
                            patch,
                            &self.device,
                        ))
                    }
                    (StageObjective::Stage1(objective), Samples::Views(views))
                        if objective.variant.stage1_frames() == 3 =>
                    {
                        Ok(objective.batch_with_extra_view(
                            &views[begin..end],
                            seed,
                            step,
                            offset,
                            patch,
                            &self.device,
                        ))
                    }
                    (StageObjective::Stage2(objective), Samples::Views(views)) => Ok(objective
                        .batch(&views[begin..end], seed, step, offset, patch, &self.device)),
                    // The guards above took the samples each stage-1 variant wants.
                    (StageObjective::Stage1(_), Samples::Pairs(_)) => {
                        Err(TrainError::WrongSamples {
                            expected: "three-frame stage-1",
                            found: "pair",
                        })
                    }
                    (StageObjective::Stage1(_), Samples::Views(_)) => {
                        Err(TrainError::WrongSamples {
                            expected: "stage-1 pair",
                            found: "multi-view",
                        })
                    }
                    (StageObjective::Stage2(_), Samples::Pairs(_)) => {
                        Err(TrainError::WrongSamples {
                            expected: "stage-2",
                            found: "pair",
                        })
                    }
                }
            })
            .collect()
    }

    fn micro_batch_gradients(
        &self,
        shards: &[ObjectiveBatch],
        share: f64,
    ) -> (SliceLoss, GradientsParams) {
        let total: usize = shards.iter().map(|b| b.target.dims()[0]).sum();
        let weight = self.config.objective.lpips_weight();
        let lpips = self.lpips.as_ref();
        // The terms are read on the side: the shards' threads add their weighted values here.
        let terms = std::sync::Mutex::new((0.0f32, 0.0f32));
        let (loss, grads) = sharded_gradients(&self.model, shards.len(), |copy, shard| {
            let batch = &shards[shard];
            let scale = batch.target.dims()[0] as f64 / total as f64 * share;
            let loss = objective_loss(copy, lpips, weight, batch);
            let l1 = loss.l1.into_scalar::<f32>() * scale as f32;
            let lpips = loss
                .lpips
                .map_or(0.0, |d| d.into_scalar::<f32>() * scale as f32);
            if let Ok(mut sums) = terms.lock() {
                sums.0 += l1;
                sums.1 += lpips;
            }
            loss.total * scale
        });
        let (l1, lpips_sum) = terms.into_inner().unwrap_or_default();
        let lpips = if self.lpips.is_some() {
            lpips_sum
        } else {
            f32::NAN
        };
        (
            SliceLoss {
                total: loss,
                l1,
                lpips,
            },
            grads,
        )
    }

    /// Writes weights, optimiser moments and the step into `dir` (created if needed); files are
    /// written to temporary names and renamed, state last, so a crash never leaves a checkpoint
    /// that looks complete but is not.
    pub fn save_checkpoint(&self, dir: &Path) -> Result<(), TrainError> {
        let state_error = |reason: String| TrainError::State {
            path: dir.join("state.json"),
            reason,
        };
        std::fs::create_dir_all(dir).map_err(|e| state_error(e.to_string()))?;
        checkpoint::save(
            &self.model,
            &self.model_config,
            &dir.join("model.safetensors"),
        )?;
        let moments = self.optimizer.export_moments(&self.model);
        write_host_tensors(&dir.join("optimizer.safetensors"), &moments)?;
        let state = TrainerState {
            step: self.step,
            updates: self.optimizer.updates(),
            seed: self.config.seed,
        };
        let json = serde_json::to_string_pretty(&state).map_err(|e| state_error(e.to_string()))?;
        let temporary = dir.join("state.json.partial");
        std::fs::write(&temporary, json).map_err(|e| state_error(e.to_string()))?;
        std::fs::rename(&temporary, dir.join("state.json")).map_err(|e| state_error(e.to_string()))
    }

    /// Runs steps until `total_steps`, writing a checkpoint into `dir` every `every` steps and
    /// after the last one, and handing each step's metrics to `on_step` (progress, logs).
    pub fn run(
        &mut self,
        source: &dyn BatchSource,
        total_steps: u64,
        checkpoints: Option<(&Path, u64)>,
        mut on_step: impl FnMut(&StepMetrics),
    ) -> Result<(), TrainError> {
        while self.step < total_steps {
            let metrics = self.train_step(source)?;
            on_step(&metrics);
            if let Some((dir, every)) = checkpoints {
                let done = self.step;
                if done == total_steps || (every > 0 && done.is_multiple_of(every)) {
                    let _span = tracing::info_span!("checkpoint", step = done).entered();
                    self.save_checkpoint(dir)?;
                }
            }
        }
        Ok(())
    }

    /// Starts a new run (step 0, fresh optimiser) from the weights of a checkpoint directory:
    /// how stage 2 begins from stage 1's final checkpoint. A stage-2 objective keeps only
    /// PoseEnc and initialises Render afresh from the run's seed, as the release does, unless
    /// its `render_from_stage1` is set.
    pub fn from_weights(
        config: TrainConfig,
        dir: &Path,
        lpips: Option<Lpips>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let (mut model, model_config) = checkpoint::load(&dir.join("model.safetensors"), device)?;
        if let StageObjective::Stage2(stage2) = &config.objective
            && !stage2.render_from_stage1
        {
            let fresh = XFactor::new(&model_config, config.seed, device).map_err(|source| {
                CheckpointError::Config {
                    path: checkpoint::config_path(&dir.join("model.safetensors")),
                    source,
                }
            })?;
            model.render = fresh.render;
        }
        Self::new(config, model_config, model, lpips, device)
    }

    /// Rebuilds a trainer from a checkpoint directory written by [`Trainer::save_checkpoint`].
    pub fn resume(
        config: TrainConfig,
        dir: &Path,
        lpips: Option<Lpips>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let state_path = dir.join("state.json");
        let state_error = |reason: String| TrainError::State {
            path: state_path.clone(),
            reason,
        };
        let text = std::fs::read_to_string(&state_path).map_err(|e| state_error(e.to_string()))?;
        let state: TrainerState =
            serde_json::from_str(&text).map_err(|e| state_error(e.to_string()))?;
        let (model, model_config) = checkpoint::load(&dir.join("model.safetensors"), device)?;
        let mut trainer = Self::new(config, model_config, model, lpips, device)?;
        let moments = FlaxTensors::read(&dir.join("optimizer.safetensors"))?;
        trainer
            .optimizer
            .import_moments(&trainer.model, &moments, state.updates)?;
        trainer.step = state.step;
        Ok(trainer)
    }
}

/// Writes float32 tensors to a safetensors file through a temporary name, so a crash never
/// leaves a truncated file under the final one.
pub(crate) fn write_host_tensors(
    path: &Path,
    tensors: &[(String, crate::flax::HostTensor)],
) -> Result<(), TensorFileError> {
    let bytes: Vec<(String, Vec<u8>, Vec<usize>)> = tensors
        .iter()
        .map(|(name, host)| {
            let data = host.values.iter().flat_map(|v| v.to_le_bytes()).collect();
            (name.clone(), data, host.shape.clone())
        })
        .collect();
    let views = bytes
        .iter()
        .map(|(name, data, shape)| {
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), data)
                .map(|view| (name.clone(), view))
                .map_err(|source| TensorFileError::Shape {
                    name: name.clone(),
                    shape: shape.clone(),
                    source,
                })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let temporary = path.with_extension("partial");
    safetensors::serialize_to_file(views, None, &temporary).map_err(|source| {
        TensorFileError::Write {
            path: temporary.clone(),
            source,
        }
    })?;
    std::fs::rename(&temporary, path).map_err(|source| TensorFileError::Rename {
        from: temporary,
        to: path.to_path_buf(),
        source,
    })
}
