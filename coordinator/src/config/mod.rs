//! The cluster YAML: what a job trains, on which data, with how many workers, and where its
//! checkpoints go. Every key is checked: an unknown key or a bad value is an error that names
//! the key, its line and what was expected, before anything starts.

use std::path::Path;

use serde::{Deserialize, Deserializer, Serialize};
use settings::data::{DatasetKind, DatasetSampling, SamplerConfig};
use settings::evaluation::EvaluationSpec;
use settings::model::{ConfigError as ModelError, PoseConditioning};
use settings::objective::{ObjectiveSettings, ObjectiveVariant, Stage1Config, Stage2Config};
use settings::optim::{AdamWConfig, Schedule};
use settings::work::{ChecksumEvery, WireFormat};
use settings::{DeviceSet, Phase, XFactorConfig};

mod checks;
mod model;
mod values;

pub use checks::{AtLine, RuleViolation};
pub use model::{ModelConfig, ModelPreset};

pub use settings::DeviceChoice;
use values::pinpoint;
pub use values::{NonEmpty, NonNegative, Positive};

/// Why a cluster YAML was refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read cluster config {path}")]
    Read {
        /// The file.
        path: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// Syntax, an unknown key or a bad value (the message names key, line and expectation).
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: String,
        /// The parser's message, with key path and position.
        message: String,
    },
    /// The file parsed but breaks a rule spanning several keys, or a bound.
    #[error("{path}: {rule}")]
    Rejected {
        /// The file.
        path: String,
        /// The rule broken, naming the key and its line.
        rule: RuleViolation,
    },
}

/// The whole cluster YAML.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ClusterConfig {
    /// Name of the job (logs, checkpoints, status).
    pub job: NonEmpty,
    /// Root of every random draw (initialisation, sampling, sharding, objectives).
    #[serde(default)]
    pub seed: u64,
    /// `host:port` the coordinator listens on.
    #[serde(default = "default_listen")]
    pub listen: NonEmpty,
    /// Who may join.
    #[serde(with = "serde_norway::with::singleton_map")]
    pub auth: AuthConfig,
    /// Which XFactor.
    pub model: ModelConfig,
    /// The training data.
    #[serde(with = "serde_norway::with::singleton_map")]
    pub data: DataConfig,
    /// Stereo-monocular transferability training.
    pub stage1: StageConfig<Stage1Config>,
    /// Multi-view fine-tune from stage 1's final weights.
    pub stage2: StageConfig<Stage2Config>,
    /// Where checkpoints go.
    pub checkpoint: CheckpointConfig,
    /// How many workers and how they behave.
    #[serde(default)]
    pub workers: WorkersConfig,
    /// Serve gRPC over TLS with this certificate; workers then dial `https://` with
    /// `--tls-ca`. Absent: plain HTTP/2 (fine on a trusted network or loopback).
    #[serde(default)]
    pub tls: Option<TlsConfig>,
    /// `host:port` of the coordinator's Prometheus `/metrics` endpoint (the command line's
    /// `--metrics-address` wins). Absent: no endpoint.
    #[serde(default)]
    pub metrics_listen: Option<NonEmpty>,
    /// A read-only token for the status page on the metrics port (`viewing: {token_env: X}`
    /// or `viewing: {token: ...}`): it shows the job, and cannot join or steer it. The job
    /// token opens the page too. Absent: only the job token.
    #[serde(default)]
    pub viewing: Option<ViewingToken>,
    /// Frames the whole job may skip (corrupt, missing or unreadable objects, summed over
    /// workers and generations) before it stops with a message naming the dataset and
    /// examples: a few bad frames in millions are noise, thousands mean the data is broken.
    #[serde(default = "default_max_skipped_frames")]
    pub max_skipped_frames: u64,
    /// Evaluate the final weights of every trained stage (TPS, pose probe, reconstruction) on
    /// one worker once training is done; the report lands under `<checkpoint.uri>/evaluation/`.
    /// Absent: no evaluation stage. Every key is optional (`evaluate: {}` takes the defaults).
    #[serde(default)]
    pub evaluate: Option<EvaluationSpec>,
    /// A checkpoint directory (ours, or the authors' weights brought in by
    /// `xfactor import-checkpoint`) whose weights start stage 1 instead of a fresh
    /// initialisation; the optimiser starts afresh at step 0. Its model must be the job's.
    #[serde(default)]
    pub init_weights: Option<NonEmpty>,
    /// The last stage the job trains: `stage2` (both, the default) or `stage1` (the stereo
    /// model alone, the checkpoint the paper's Table 3 compares). With `stage1`, stage 2's
    /// section is still read and checked but never trained, and the evaluation scores stage
    /// 1's final weights.
    #[serde(default)]
    pub stop_after: LastStage,
}

/// The last training stage of a job.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LastStage {
    /// Stage 1 alone.
    Stage1,
    /// Stage 1, then stage 2 from its final weights.
    #[default]
    Stage2,
}

/// PEM files of the coordinator's TLS identity. They are read when the job starts, so a
/// `--dry-run` on a machine without them still checks the rest of the file.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// Certificate chain (PEM), leaf first.
    pub cert: NonEmpty,
    /// Private key (PEM, PKCS#8, SEC1 or PKCS#1).
    pub key: NonEmpty,
}

fn default_max_skipped_frames() -> u64 {
    1000
}

fn default_listen() -> NonEmpty {
    NonEmpty("127.0.0.1:50051".into())
}

/// The job token: given inline or, better, by the name of the environment variable holding it.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, rename_all = "snake_case")]
pub enum AuthConfig {
    /// The token itself (fine for local runs; use `token_env` elsewhere).
    Token(NonEmpty),
    /// Name of the environment variable holding the token.
    TokenEnv(NonEmpty),
}

impl AuthConfig {
    /// The token, read from the environment when configured so.
    pub fn resolve(&self) -> Result<String, TokenNotSet> {
        match self {
            Self::Token(token) => Ok(token.0.clone()),
            Self::TokenEnv(name) => {
                proto::auth::token_from_env(&name.0).map_err(|_| TokenNotSet(name.0.clone()))
            }
        }
    }
}

/// The status page's read-only token, given as the job token is (`token` or `token_env`).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
pub struct ViewingToken(#[serde(with = "serde_norway::with::singleton_map")] pub AuthConfig);

/// `auth.token_env` names a variable that is not set.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("auth.token_env names `{0}`, which is not set in the environment")]
pub struct TokenNotSet(pub String);

/// Either generated scenes or stored datasets.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, rename_all = "snake_case")]
pub enum DataConfig {
    /// Procedural scenes rendered in memory by every worker.
    Generated(GeneratedConfig),
    /// RE10K / DL3DV / MVImgNet / CO3Dv2 trees on any object store.
    Datasets(Vec<DatasetConfig>),
}

/// Size of the generated data.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct GeneratedConfig {
    /// Scenes.
    pub scenes: Positive,
    /// Camera paths, each rendered in every scene.
    pub trajectories: Positive,
    /// Frames per path (at least stage 2's views).
    pub frames: Positive,
}

/// One stored dataset.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetConfig {
    /// `re10k`, `dl3dv`, `mvimgnet`, `co3dv2`, `arkitscenes`, `wildrgbd` or `acid`.
    pub kind: DatasetKind,
    /// Root: a path, `file://`, `s3://`, `gs://` or `az://`.
    pub uri: NonEmpty,
    /// The paper's split file for this dataset (JSON, training sequence ids as keys), used
    /// instead of the layout's train/test rule: a path relative to `uri`, or a path or URI of
    /// its own.
    #[serde(default)]
    pub split_file: Option<NonEmpty>,
    /// Stage-1 mixture weight and window range (defaults: the paper's).
    #[serde(default)]
    pub stage1: Option<SamplingOverride>,
    /// Stage-2 mixture weight and window range (defaults: the paper's).
    #[serde(default)]
    pub stage2: Option<SamplingOverride>,
}

/// Mixture weight and window curriculum of one dataset in one stage.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SamplingOverride {
    /// Relative mixture weight.
    pub weight: Option<NonNegative>,
    /// Largest window at step 0.
    pub window_begin: Option<Positive>,
    /// Largest window once the curriculum is over.
    pub window_end: Option<Positive>,
}

/// One stage's length, batch, schedule and objective.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StageConfig<O> {
    /// Optimiser steps.
    pub steps: u64,
    /// Samples per step over all workers.
    pub global_batch: u64,
    /// Samples per forward/backward pass on one worker.
    pub micro_batch: u64,
    /// LPIPS weights (safetensors from tools/convert_lpips_weights.py); needed when
    /// `lpips_weight` is positive.
    pub lpips_weights: Option<String>,
    /// Learning-rate schedule (default: the `recipe` key's, XFactor's shape fitted to
    /// `steps` unless it names another).
    pub schedule: Schedule,
    /// AdamW settings (default: the `recipe` key's).
    pub optimizer: AdamWConfig,
    /// Objective probabilities and augmentation (default: the paper's).
    pub objective: O,
    /// Steps over which windows grow (default: the paper's 50000).
    pub curriculum_steps: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStage<O> {
    steps: Positive,
    global_batch: Positive,
    micro_batch: Positive,
    #[serde(default)]
    lpips_weight: Option<NonNegative>,
    #[serde(default)]
    lpips_weights: Option<NonEmpty>,
    #[serde(default)]
    recipe: Recipe,
    #[serde(default)]
    schedule: Option<Schedule>,
    #[serde(default)]
    optimizer: Option<AdamWConfig>,
    #[serde(default)]
    objective: Option<O>,
    #[serde(default)]
    curriculum_steps: Option<Positive>,
}

/// Whose schedule and optimiser a stage takes where the YAML names none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Recipe {
    /// XFactor's: warm-up over 4% of the steps from 1e-12 to 4e-4, cosine to 1e-4; AdamW
    /// clipped at global norm 1.
    #[default]
    Xfactor,
    /// E-RayZer's: warm-up over 3000 steps (at most the stage) from 0 to 4e-4, cosine to 0;
    /// AdamW clipped at 1, and a step whose gradient norm before clipping exceeds 5 (or is
    /// NaN) is skipped.
    Erayzer,
}

/// E-RayZer's warm-up length.
const ERAYZER_WARMUP_STEPS: u64 = 3000;

/// E-RayZer's gradient-norm limit above which a step is skipped.
const ERAYZER_SKIP_NORM: f64 = 5.0;

impl Recipe {
    fn schedule(self, steps: u64) -> Schedule {
        match self {
            Self::Xfactor => fitted_schedule(steps),
            Self::Erayzer => Schedule {
                initial_lr: 0.0,
                peak_lr: 4e-4,
                final_lr: 0.0,
                warmup_steps: ERAYZER_WARMUP_STEPS.min(steps),
                total_steps: steps,
            },
        }
    }

    fn optimizer(self) -> AdamWConfig {
        match self {
            Self::Xfactor => AdamWConfig::default(),
            Self::Erayzer => AdamWConfig {
                skip_norm_above: Some(ERAYZER_SKIP_NORM),
                ..AdamWConfig::default()
            },
        }
    }
}

/// The paper's warm-up share (4000 of 100000 steps), kept when a stage is shorter.
fn fitted_schedule(steps: u64) -> Schedule {
    let paper = Schedule::default();
    Schedule {
        warmup_steps: (steps * paper.warmup_steps / paper.total_steps)
            .max(1)
            .min(steps),
        total_steps: steps,
        ..paper
    }
}

impl<'de, O: Deserialize<'de> + ObjectiveSettings> Deserialize<'de> for StageConfig<O> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let raw = RawStage::<O>::deserialize(deserializer)?;
        let mut objective = raw.objective.unwrap_or_default();
        if let Some(weight) = raw.lpips_weight {
            objective.set_lpips_weight(weight.0);
        }
        Ok(Self {
            steps: raw.steps.0,
            global_batch: raw.global_batch.0,
            micro_batch: raw.micro_batch.0,
            lpips_weights: raw.lpips_weights.map(|p| p.0),
            schedule: raw
                .schedule
                .unwrap_or_else(|| raw.recipe.schedule(raw.steps.0)),
            optimizer: raw.optimizer.unwrap_or_else(|| raw.recipe.optimizer()),
            objective,
            curriculum_steps: raw.curriculum_steps.map(|c| c.0),
        })
    }
}

/// Where checkpoints go and how often.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CheckpointConfig {
    /// URI prefix (path, `file://`, `s3://`, `gs://`, `az://`).
    pub uri: NonEmpty,
    /// Commit a checkpoint every this many steps (and after each stage's last).
    pub every: Positive,
}

/// Group size and liveness settings.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorkersConfig {
    /// Workers to wait for before starting.
    pub expected: Positive,
    /// Fewest workers the job may continue with after losing some.
    pub minimum: Positive,
    /// Default device of workers (a worker's `--device` overrides it).
    pub device: DeviceChoice,
    /// Which of a host's devices each worker drives, one model replica each: `all`, a count,
    /// or a list of indices (a worker's `--devices` overrides it).
    pub devices: DeviceSet,
    /// Threads per worker for each micro-batch (0: every core of its host on the CPU backend,
    /// one on a GPU backend).
    pub threads: u64,
    /// Seconds between heartbeats.
    pub heartbeat_interval_s: NonNegative,
    /// A worker silent this long is declared lost.
    pub heartbeat_timeout_s: NonNegative,
    /// After `expected` is not reached for this long, start with `minimum`.
    pub quorum_timeout_s: NonNegative,
    /// After losing a worker, wait this long for a replacement before re-forming.
    pub regroup_grace_s: NonNegative,
    /// A group member that makes no progress in its step this long while a peer waits for
    /// it in the all-reduce is removed (a worker stuck with its heartbeats alive).
    pub stall_timeout_s: NonNegative,
    /// A worker blamed for a failed generation sits out this long before it may join a group
    /// again, doubled for each further failure (at most an hour).
    pub exclusion_s: NonNegative,
    /// Parameter checksums every this many steps, or `auto` (the default): the fewest steps
    /// that keep them under 2% of the steps' time for the model's size (docs/data-path.md).
    pub checksum_every: ChecksumEvery,
    /// How the ring carries gradients: `f32` (every bit) or `bf16` (half the bytes, summed
    /// in float32).
    pub allreduce_wire: WireFormat,
    /// TCP lanes of the ring, each on a thread of its own and each a TLS session of its own
    /// when the job runs `tls:` (1, the default; at most 64); 0: one gRPC stream (only under
    /// `tls:`, since the stream presents the job token).
    pub allreduce_lanes: usize,
}

impl Default for WorkersConfig {
    fn default() -> Self {
        Self {
            expected: Positive(2),
            minimum: Positive(1),
            device: DeviceChoice::Auto,
            devices: DeviceSet::All,
            threads: 0,
            heartbeat_interval_s: NonNegative(0.5),
            heartbeat_timeout_s: NonNegative(5.0),
            quorum_timeout_s: NonNegative(300.0),
            regroup_grace_s: NonNegative(2.0),
            stall_timeout_s: NonNegative(120.0),
            exclusion_s: NonNegative(30.0),
            checksum_every: ChecksumEvery::Auto,
            allreduce_wire: WireFormat::F32,
            allreduce_lanes: 1,
        }
    }
}

impl ClusterConfig {
    /// Reads and checks a cluster YAML file.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Read {
            path: path.display().to_string(),
            source: e,
        })?;
        Self::from_yaml(&text, &path.display().to_string())
    }

    /// Parses and checks YAML text; `label` names it in errors.
    pub fn from_yaml(text: &str, label: &str) -> Result<Self, ConfigError> {
        let config: Self = serde_norway::from_str(text).map_err(|e| ConfigError::Invalid {
            path: label.to_string(),
            message: pinpoint(text, &e.to_string()),
        })?;
        config.check(text).map_err(|rule| ConfigError::Rejected {
            path: label.to_string(),
            rule,
        })?;
        Ok(config)
    }

    /// The model configuration (already checked when the file was read). Render is
    /// conditioned on Plücker rays when either stage trains `se3_plucker`: both stages train
    /// one model.
    pub fn model_config(&self) -> Result<XFactorConfig, ModelError> {
        let conditioning = [self.stage1.objective.variant, self.stage2.objective.variant]
            .into_iter()
            .map(ObjectiveVariant::pose_conditioning)
            .find(|c| *c != PoseConditioning::Latent)
            .unwrap_or_default();
        self.model.resolve(conditioning)
    }

    /// The window sampler of training stage `phase` with the datasets' overrides.
    pub fn sampler(&self, phase: Phase) -> SamplerConfig {
        let stage = phase.stage_number().unwrap_or(2);
        let mut sampler = if stage == 1 {
            SamplerConfig::stage1()
        } else {
            SamplerConfig::stage2()
        };
        if stage == 2 {
            sampler.frames = self.stage2.objective.views;
        } else {
            sampler.frames = self.stage1.objective.variant.stage1_frames();
        }
        let curriculum = if stage == 1 {
            self.stage1.curriculum_steps
        } else {
            self.stage2.curriculum_steps
        };
        if let Some(steps) = curriculum {
            sampler.curriculum_steps = steps;
        }
        if let DataConfig::Datasets(datasets) = &self.data {
            sampler.datasets = datasets
                .iter()
                .map(|d| {
                    let default = sampler.dataset(d.kind).cloned().unwrap_or(DatasetSampling {
                        dataset: d.kind,
                        weight: 1.0,
                        window_begin: sampler.frames,
                        window_end: sampler.frames,
                    });
                    let chosen = if stage == 1 { &d.stage1 } else { &d.stage2 };
                    match chosen {
                        None => default,
                        Some(o) => DatasetSampling {
                            dataset: d.kind,
                            weight: o.weight.map_or(default.weight, |w| w.0),
                            window_begin: o
                                .window_begin
                                .map_or(default.window_begin, |w| w.0 as usize),
                            window_end: o.window_end.map_or(default.window_end, |w| w.0 as usize),
                        },
                    }
                })
                .collect();
        }
        sampler
    }
}

#[cfg(test)]
mod fuzz_tests;
#[cfg(test)]
mod tests;
