//! The resolved plan of a job: the model, each stage's trainer settings and data (datasets
//! indexed through their manifest caches), and how the expected workers split the data.

use data::cache::CacheError;
use data::index::IndexError;
use data::split::SplitError;
use data::store::StoreError;
use settings::Phase;
use settings::XFactorConfig;
use settings::data::{DataSource, DataSpec};
use settings::train::{StageObjective, TrainConfig};

use crate::config::{ClusterConfig, DataConfig, LastStage, StageConfig};

mod datasets;
mod describe;
mod held_out;

use datasets::{TrainManifest, index_datasets};

/// Why a plan could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    /// The model section is invalid.
    #[error("model")]
    Model(#[source] settings::model::ConfigError),
    /// A dataset root could not be opened.
    #[error("data.datasets[{index}] ({kind} at {uri})")]
    Open {
        /// Position in the YAML list.
        index: usize,
        /// Its kind.
        kind: &'static str,
        /// Its root.
        uri: String,
        /// What failed.
        #[source]
        source: StoreError,
    },
    /// A dataset could not be indexed.
    #[error("data.datasets[{index}] ({kind} at {uri})")]
    Index {
        /// Position in the YAML list.
        index: usize,
        /// Its kind.
        kind: &'static str,
        /// Its root.
        uri: String,
        /// What failed.
        #[source]
        source: CacheError,
    },
    /// A dataset's split file could not be read or parsed.
    #[error("data.datasets[{index}].split_file ({kind} at {uri})")]
    Split {
        /// Position in the YAML list.
        index: usize,
        /// Its kind.
        kind: &'static str,
        /// Its root.
        uri: String,
        /// What failed (naming the file).
        #[source]
        source: SplitError,
    },
    /// An evaluation dataset's root could not be opened for the held-out check.
    #[error("evaluate.sequences[{index}] ({kind} at {uri})")]
    EvaluationOpen {
        /// Position in the YAML list.
        index: usize,
        /// Its kind.
        kind: &'static str,
        /// Its root.
        uri: String,
        /// What failed.
        #[source]
        source: StoreError,
    },
    /// An evaluation dataset could not be indexed for the held-out check.
    #[error("evaluate.sequences[{index}] ({kind} at {uri})")]
    EvaluationIndex {
        /// Position in the YAML list.
        index: usize,
        /// Its kind.
        kind: &'static str,
        /// Its root.
        uri: String,
        /// What failed.
        #[source]
        source: IndexError,
    },
    /// The evaluation would score scenes the training data holds.
    #[error(
        "{what}: {count} evaluated scene(s) are also training data ({named}); evaluate on scenes no training step reads"
    )]
    EvaluationOverlap {
        /// The evaluation data, as the YAML names it.
        what: String,
        /// Scenes shared.
        count: usize,
        /// The first few shared scenes' ids.
        named: String,
    },
}

/// One stage, resolved.
#[derive(Debug, Clone)]
pub struct StagePlan {
    /// Stage 1 or stage 2.
    pub phase: Phase,
    /// Optimiser steps; 0 for a stage the job does not train (stage 2 of `stop_after:
    /// stage1`), so progress and estimates count only what runs.
    pub steps: u64,
    /// Trainer settings sent to workers (threads are the worker's own choice).
    pub train: TrainConfig,
    /// Data sent to workers.
    pub data: DataSpec,
    /// LPIPS weights file, when the objective uses LPIPS.
    pub lpips_weights: Option<String>,
}

/// Resolves stage `phase` of `config` around its `objective`.
fn stage_plan<O>(
    config: &ClusterConfig,
    phase: Phase,
    stage: &StageConfig<O>,
    objective: StageObjective,
    source: &DataSource,
    image_size: usize,
) -> StagePlan {
    StagePlan {
        phase,
        steps: stage.steps,
        train: TrainConfig {
            seed: config.seed,
            objective,
            global_batch: stage.global_batch as usize,
            micro_batch: stage.micro_batch as usize,
            shards: config.workers.threads as usize,
            schedule: stage.schedule.clone(),
            optimizer: stage.optimizer.clone(),
        },
        data: DataSpec {
            source: source.clone(),
            sampler: config.sampler(phase),
            image_size,
            seed: config.seed,
            global_batch: stage.global_batch as usize,
        },
        lpips_weights: stage.lpips_weights.clone(),
    }
}

/// The whole job, resolved.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The cluster YAML it came from.
    pub config: ClusterConfig,
    /// The model.
    pub model: XFactorConfig,
    /// Stage 1 then stage 2.
    pub stages: [StagePlan; 2],
    /// Train sequences of each stored dataset, for the shard summary.
    manifests: Vec<TrainManifest>,
}

impl Plan {
    /// Indexes the datasets (reusing caches that match their listing) and resolves both stages.
    pub async fn build(config: ClusterConfig) -> Result<Self, PlanError> {
        let model = config.model_config().map_err(PlanError::Model)?;
        let (source, manifests) = match &config.data {
            DataConfig::Generated(generated) => {
                let source = DataSource::Generated {
                    scenes: generated.scenes.0,
                    trajectories: generated.trajectories.0,
                    frames: generated.frames.0 as usize,
                };
                (source, Vec::new())
            }
            DataConfig::Datasets(datasets) => index_datasets(datasets).await?,
        };
        held_out::check_held_out(&config, &manifests).await?;
        let mut stages = [
            stage_plan(
                &config,
                Phase::Stage1,
                &config.stage1,
                StageObjective::Stage1(config.stage1.objective.clone()),
                &source,
                model.image_size,
            ),
            stage_plan(
                &config,
                Phase::Stage2,
                &config.stage2,
                StageObjective::Stage2(config.stage2.objective.clone()),
                &source,
                model.image_size,
            ),
        ];
        if config.stop_after == LastStage::Stage1 {
            stages[1].steps = 0;
        }
        Ok(Self {
            config,
            model,
            stages,
            manifests,
        })
    }

    /// The plan of training stage `phase`; the stage-2 plan for any later phase.
    pub fn stage(&self, phase: Phase) -> &StagePlan {
        &self.stages[usize::from(phase != Phase::Stage1)]
    }

    /// Whether the job trains `phase` (not stage 2 when it stops after stage 1; never the
    /// evaluation).
    pub fn trains(&self, phase: Phase) -> bool {
        phase.is_training() && self.stage(phase).steps > 0
    }

    /// The phase after the last trained stage: the evaluation, when the job has one.
    pub fn after_training(&self) -> Phase {
        if self.config.evaluate.is_some() {
            Phase::Evaluate
        } else {
            Phase::Finished
        }
    }

    /// The training stages the job runs, in order.
    pub fn trained_stages(&self) -> Vec<Phase> {
        [Phase::Stage1, Phase::Stage2]
            .into_iter()
            .filter(|&phase| self.trains(phase))
            .collect()
    }
}
