//! The resolved plan of a job: the model, each stage's trainer settings and data (datasets
//! indexed through their manifest caches), and how the expected workers split the data.

use std::fmt::Write as _;

use data::cache::{CacheError, CacheUse, load_or_index};
use data::spec::{rank_slice, shard_ids, steps_per_epoch};
use data::split::{SplitError, read_split_file};
use data::store::{DataRoot, StoreError};
use data::{DatasetKind, Manifest, Split};
use settings::Phase;
use settings::XFactorConfig;
use settings::data::{DataSource, DataSpec, StoredDataset};
use settings::train::{StageObjective, TrainConfig};

use crate::config::{ClusterConfig, DataConfig, StageConfig};

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
}

/// One stage, resolved.
#[derive(Debug, Clone)]
pub struct StagePlan {
    /// Stage 1 or stage 2.
    pub phase: Phase,
    /// Optimiser steps.
    pub steps: u64,
    /// Trainer settings sent to workers (threads are the worker's own choice).
    pub train: TrainConfig,
    /// Data sent to workers.
    pub data: DataSpec,
    /// LPIPS weights file, when the objective uses LPIPS.
    pub lpips_weights: Option<String>,
}

/// Resolves stage `number` of `config` around its `objective`.
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
    manifests: Vec<(DatasetKind, DataRoot, Manifest)>,
}

impl Plan {
    /// Indexes the datasets (reusing caches that match their listing) and resolves both stages.
    pub async fn build(config: ClusterConfig) -> Result<Self, PlanError> {
        let model = config.model_config().map_err(PlanError::Model)?;
        let mut manifests = Vec::new();
        let source = match &config.data {
            DataConfig::Generated(generated) => DataSource::Generated {
                scenes: generated.scenes.0,
                trajectories: generated.trajectories.0,
                frames: generated.frames.0 as usize,
            },
            DataConfig::Datasets(datasets) => {
                let mut stored = Vec::new();
                for (index, dataset) in datasets.iter().enumerate() {
                    let (kind, uri) = (dataset.kind.name(), dataset.uri.0.clone());
                    let root =
                        DataRoot::open(&dataset.uri.0).map_err(|source| PlanError::Open {
                            index,
                            kind,
                            uri: uri.clone(),
                            source,
                        })?;
                    let (cached, used) =
                        load_or_index(&root, dataset.kind).await.map_err(|source| {
                            PlanError::Index {
                                index,
                                kind,
                                uri,
                                source,
                            }
                        })?;
                    tracing::info!(
                        dataset = dataset.kind.name(),
                        uri = %dataset.uri.0,
                        sequences = cached.manifest.sequences.len(),
                        cache = if used == CacheUse::Reused { "reused" } else { "rebuilt" },
                        "indexed"
                    );
                    let mut train = cached.manifest.clone();
                    let split_file = dataset.split_file.as_ref().map(|name| name.0.clone());
                    if let Some(name) = &split_file {
                        let split = read_split_file(&root, name).await.map_err(|source| {
                            PlanError::Split {
                                index,
                                kind,
                                uri: dataset.uri.0.clone(),
                                source,
                            }
                        })?;
                        split.apply(&mut train);
                    }
                    train.sequences.retain(|s| s.split == Split::Train);
                    manifests.push((dataset.kind, root, train));
                    stored.push(StoredDataset {
                        kind: dataset.kind,
                        uri: dataset.uri.0.clone(),
                        fingerprint: cached.fingerprint,
                        split_file,
                    });
                }
                DataSource::Stored(stored)
            }
        };
        let stages = [
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

    /// Human-readable plan for `--dry-run`: ranks, shards of the first epoch, steps.
    pub fn describe(&self) -> String {
        let config = &self.config;
        let world = config.workers.expected.0 as usize;
        let mut out = String::new();
        let _ = writeln!(out, "job: {}", config.job.0);
        let _ = writeln!(out, "seed: {}", config.seed);
        let _ = writeln!(out, "listen: {}", config.listen.0);
        let _ = writeln!(
            out,
            "model: {:?} image_size={} width={} heads={} pose_layers={} render_layers={}",
            config.model.preset,
            self.model.image_size,
            self.model.width,
            self.model.num_heads,
            self.model.pose_layers,
            self.model.render_layers
        );
        let _ = writeln!(
            out,
            "workers: expected={} minimum={} device={:?}",
            world, config.workers.minimum.0, config.workers.device
        );
        for stage in &self.stages {
            let _ = writeln!(
                out,
                "{}: steps={} global_batch={} micro_batch={} lr {}→{}→{} warmup={} lpips_weight={} frames_per_sample={}",
                stage.phase,
                stage.steps,
                stage.train.global_batch,
                stage.train.micro_batch,
                stage.train.schedule.initial_lr,
                stage.train.schedule.peak_lr,
                stage.train.schedule.final_lr,
                stage.train.schedule.warmup_steps,
                stage.train.objective.lpips_weight(),
                stage.data.sampler.frames,
            );
            for rank in 0..world {
                let (first, count) = rank_slice(stage.train.global_batch, world, rank);
                let _ = writeln!(
                    out,
                    "  rank {rank}: samples {first}..{} of each step ({} micro-batches)",
                    first + count as u64,
                    count.div_ceil(stage.train.micro_batch.max(1))
                );
            }
        }
        match &self.stages[0].data.source {
            DataSource::Generated {
                scenes,
                trajectories,
                frames,
            } => {
                let _ = writeln!(
                    out,
                    "data: generated, {scenes} scenes x {trajectories} trajectories x {frames} frames, drawn by global sample index (not sharded)"
                );
            }
            DataSource::Stored(datasets) => {
                for (dataset, (_, _, manifest)) in datasets.iter().zip(&self.manifests) {
                    let _ = writeln!(
                        out,
                        "data: {} at {}: {} train sequences, {} frames",
                        dataset.kind.name(),
                        dataset.uri,
                        manifest.sequences.len(),
                        manifest.frame_counts().iter().sum::<usize>()
                    );
                }
                let sequences: usize = self
                    .manifests
                    .iter()
                    .map(|(_, _, m)| m.sequences.len())
                    .sum();
                let epoch_steps = steps_per_epoch(sequences, self.stages[0].train.global_batch);
                let _ = writeln!(out, "epoch: {epoch_steps} steps; shards of epoch 0:");
                for rank in 0..world {
                    let ids = shard_ids(&self.manifests, world, rank, config.seed, 0);
                    let preview: Vec<&str> = ids.iter().take(4).map(String::as_str).collect();
                    let _ = writeln!(
                        out,
                        "  rank {rank}: {} sequences ({}{})",
                        ids.len(),
                        preview.join(", "),
                        if ids.len() > 4 { ", ..." } else { "" }
                    );
                }
            }
        }
        let _ = writeln!(
            out,
            "checkpoints: {} every {} steps",
            config.checkpoint.uri.0, config.checkpoint.every.0
        );
        match &config.evaluate {
            Some(spec) => {
                let _ = writeln!(
                    out,
                    "stage 3: one worker evaluates stage 2's final weights ({} scenes x {} trajectories, {} TPS pairs, probe {} steps); report under {}/evaluation/",
                    spec.scenes,
                    spec.trajectories,
                    spec.tps_pairs,
                    spec.probe.steps,
                    config.checkpoint.uri.0.trim_end_matches('/')
                );
            }
            None => {
                let _ = writeln!(out, "no evaluation stage (add `evaluate: {{}}` for one)");
            }
        }
        out
    }
}
