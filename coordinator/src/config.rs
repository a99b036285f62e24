//! The cluster YAML: what a job trains, on which data, with how many workers, and where its
//! checkpoints go. Every key is checked: an unknown key or a bad value is an error that names
//! the key, its line and what was expected, before anything starts.

use std::path::Path;

use serde::{Deserialize, Deserializer, Serialize};
use trainer_core::XFactorConfig;
use trainer_core::data::{DatasetKind, DatasetSampling, SamplerConfig};
use trainer_core::objective::{Stage1Config, Stage2Config};
use trainer_core::optim::{AdamWConfig, Schedule};

/// Why a cluster YAML was refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read cluster config {path}: {reason}")]
    Read {
        /// The file.
        path: String,
        /// The OS error.
        reason: String,
    },
    /// Syntax, an unknown key or a bad value (the message names key, line and expectation).
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: String,
        /// The parser's message, with key path and position.
        message: String,
    },
}

/// Marks a value a validated type refused, so [`pinpoint`] can find its key and line (serde
/// reports such errors at the enclosing mapping).
const REFUSED: &str = "refused value ";

fn refused(value: &str, expectation: &str) -> String {
    format!("{REFUSED}{value}: {expectation}")
}

/// Rewrites `<path>: refused value V: <expectation> at line L ...` into
/// `<path>.<key>: <expectation>, found V at line N`, by finding the key holding `V` in the
/// mapping that starts at line L.
fn pinpoint(text: &str, message: &str) -> String {
    let Some(start) = message.find(REFUSED) else {
        return message.to_string();
    };
    let path = message[..start].trim_end_matches(": ").to_string();
    let rest = &message[start + REFUSED.len()..];
    let Some((value, tail)) = rest.split_once(": ") else {
        return message.to_string();
    };
    let (expectation, position) = match tail.split_once(" at line ") {
        Some((expectation, position)) => (expectation, Some(position)),
        None => (tail, None),
    };
    let first_line: usize = position
        .and_then(|p| p.split_whitespace().next())
        .and_then(|l| l.parse().ok())
        .unwrap_or(1);
    for (index, line) in text.lines().enumerate().skip(first_line.saturating_sub(1)) {
        for segment in line.split(['{', ',', '}']) {
            if let Some((key, found)) = segment.split_once(':')
                && found.trim() == value
            {
                let key = key.trim().trim_start_matches("- ");
                let full = if path.is_empty() {
                    key.to_string()
                } else {
                    format!("{path}.{key}")
                };
                return format!("{full}: {expectation}, found {value} at line {}", index + 1);
            }
        }
    }
    format!("{path}: {expectation}, found {value} (in the mapping at line {first_line})")
}

/// Line (1-based) of the block-style key `path` (e.g. `["stage1", "micro_batch"]`).
fn locate(text: &str, path: &[&str]) -> Option<usize> {
    let mut depth = 0;
    let mut indent: Option<usize> = None;
    for (index, line) in text.lines().enumerate() {
        let trimmed = line.trim_start();
        let here = line.len() - trimmed.len();
        if indent.is_some_and(|i| here <= i) && !trimmed.is_empty() && depth > 0 {
            return None;
        }
        let deeper = match indent {
            None => here == 0,
            Some(i) => here > i,
        };
        if deeper && trimmed.starts_with(&format!("{}:", path[depth])) {
            depth += 1;
            indent = Some(here);
            if depth == path.len() {
                return Some(index + 1);
            }
        }
    }
    None
}

/// A whole number of at least 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Positive(pub u64);

impl<'de> Deserialize<'de> for Positive {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = u64::deserialize(deserializer)?;
        if value == 0 {
            return Err(serde::de::Error::custom(refused(
                "0",
                "expected a positive whole number",
            )));
        }
        Ok(Self(value))
    }
}

/// A finite number of at least 0.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NonNegative(pub f64);

impl<'de> Deserialize<'de> for NonNegative {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = f64::deserialize(deserializer)?;
        if !value.is_finite() || value < 0.0 {
            return Err(serde::de::Error::custom(refused(
                &value.to_string(),
                "expected a finite number >= 0",
            )));
        }
        Ok(Self(value))
    }
}

/// A string with something in it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct NonEmpty(pub String);

impl<'de> Deserialize<'de> for NonEmpty {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = String::deserialize(deserializer)?;
        if value.trim().is_empty() {
            return Err(serde::de::Error::custom(refused(
                "\"\"",
                "expected a non-empty string",
            )));
        }
        Ok(Self(value))
    }
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
    /// Evaluate stage 2's final weights (TPS, pose probe, reconstruction) on one worker once
    /// training is done; the report lands under `<checkpoint.uri>/evaluation/`. Absent: no
    /// evaluation stage. Every key is optional (`evaluate: {}` takes the defaults).
    #[serde(default)]
    pub evaluate: Option<evaluation::EvaluationSpec>,
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
    pub fn resolve(&self) -> Result<String, String> {
        match self {
            Self::Token(token) => Ok(token.0.clone()),
            Self::TokenEnv(name) => {
                proto::auth::token_from_env(&name.0).map_err(|e| format!("auth.token_env: {e}"))
            }
        }
    }
}

/// Model presets with the few overrides worth a YAML key.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// `tiny`, `benchmark` or `paper`.
    pub preset: ModelPreset,
    /// Training resolution (defaults to the preset's; `tiny` defaults to 32).
    #[serde(default)]
    pub image_size: Option<usize>,
    /// Round q/k/v to bfloat16 as the authors' mixed precision does.
    #[serde(default)]
    pub round_qkv_bf16: bool,
}

/// The model sizes a job can name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelPreset {
    /// Trains in seconds on a laptop CPU.
    Tiny,
    /// The benchmark model (64x64, width 256).
    Benchmark,
    /// The paper's model (305M parameters).
    Paper,
}

impl ModelConfig {
    /// The model configuration, checked.
    pub fn resolve(&self) -> Result<XFactorConfig, String> {
        let mut config = match self.preset {
            ModelPreset::Tiny => XFactorConfig::tiny(32),
            ModelPreset::Benchmark => XFactorConfig::benchmark(),
            ModelPreset::Paper => XFactorConfig::paper(),
        };
        if let Some(size) = self.image_size {
            config.image_size = size;
        }
        config.round_qkv_bf16 = self.round_qkv_bf16;
        config
            .validate()
            .map_err(|e| format!("model: {e}"))
            .map(|()| config)
    }
}

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
    /// `re10k`, `dl3dv`, `mvimgnet` or `co3dv2`.
    pub kind: DatasetKind,
    /// Root: a path, `file://`, `s3://`, `gs://` or `az://`.
    pub uri: NonEmpty,
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
    /// Learning-rate schedule (default: the paper's shape fitted to `steps`).
    pub schedule: Schedule,
    /// AdamW settings (default: the paper's).
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
    schedule: Option<Schedule>,
    #[serde(default)]
    optimizer: Option<AdamWConfig>,
    #[serde(default)]
    objective: Option<O>,
    #[serde(default)]
    curriculum_steps: Option<Positive>,
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

/// Objectives whose LPIPS weight the stage's `lpips_weight` key sets.
pub trait WithLpipsWeight: Default {
    /// Sets the weight.
    fn set_lpips_weight(&mut self, weight: f64);
    /// The weight.
    fn lpips_weight(&self) -> f64;
}

impl WithLpipsWeight for Stage1Config {
    fn set_lpips_weight(&mut self, weight: f64) {
        self.lpips_weight = weight;
    }
    fn lpips_weight(&self) -> f64 {
        self.lpips_weight
    }
}

impl WithLpipsWeight for Stage2Config {
    fn set_lpips_weight(&mut self, weight: f64) {
        self.lpips_weight = weight;
    }
    fn lpips_weight(&self) -> f64 {
        self.lpips_weight
    }
}

impl<'de, O: Deserialize<'de> + WithLpipsWeight> Deserialize<'de> for StageConfig<O> {
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
            schedule: raw.schedule.unwrap_or_else(|| fitted_schedule(raw.steps.0)),
            optimizer: raw.optimizer.unwrap_or_default(),
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

/// Which compute device workers train on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DeviceChoice {
    /// wgpu when a GPU adapter is present, the CPU otherwise.
    #[default]
    Auto,
    /// burn's CPU backend.
    Cpu,
    /// burn-wgpu.
    Wgpu,
}

impl DeviceChoice {
    /// The name assignments carry to workers (the YAML spelling).
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Cpu => "cpu",
            Self::Wgpu => "wgpu",
        }
    }
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
    /// Threads per worker for each micro-batch (0: every core of its host).
    pub threads: u64,
    /// Seconds between heartbeats.
    pub heartbeat_interval_s: NonNegative,
    /// A worker silent this long is declared lost.
    pub heartbeat_timeout_s: NonNegative,
    /// After `expected` is not reached for this long, start with `minimum`.
    pub quorum_timeout_s: NonNegative,
    /// After losing a worker, wait this long for a replacement before re-forming.
    pub regroup_grace_s: NonNegative,
    /// Parameter checksums every this many steps.
    pub checksum_every: Positive,
}

impl Default for WorkersConfig {
    fn default() -> Self {
        Self {
            expected: Positive(2),
            minimum: Positive(1),
            device: DeviceChoice::Auto,
            threads: 0,
            heartbeat_interval_s: NonNegative(0.5),
            heartbeat_timeout_s: NonNegative(5.0),
            quorum_timeout_s: NonNegative(300.0),
            regroup_grace_s: NonNegative(2.0),
            checksum_every: Positive(1),
        }
    }
}

impl ClusterConfig {
    /// Reads and checks a cluster YAML file.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Read {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_yaml(&text, &path.display().to_string())
    }

    /// Parses and checks YAML text; `label` names it in errors.
    pub fn from_yaml(text: &str, label: &str) -> Result<Self, ConfigError> {
        let invalid = |message: String| ConfigError::Invalid {
            path: label.to_string(),
            message,
        };
        let config: Self =
            serde_norway::from_str(text).map_err(|e| invalid(pinpoint(text, &e.to_string())))?;
        config.check(text).map_err(invalid)?;
        Ok(config)
    }

    /// Checks that span several keys; `text` gives their lines.
    fn check(&self, text: &str) -> Result<(), String> {
        let at =
            |path: &[&str]| locate(text, path).map_or(String::new(), |l| format!(" at line {l}"));
        self.model
            .resolve()
            .map_err(|e| format!("{e}{}", at(&["model"])))?;
        let batches = [
            (
                "stage1",
                self.stage1.global_batch,
                self.stage1.micro_batch,
                self.stage1.objective.lpips_weight(),
                self.stage1.lpips_weights.is_some(),
            ),
            (
                "stage2",
                self.stage2.global_batch,
                self.stage2.micro_batch,
                self.stage2.objective.lpips_weight(),
                self.stage2.lpips_weights.is_some(),
            ),
        ];
        for (stage, global, micro, lpips_weight, has_weights) in batches {
            if global % micro != 0 {
                return Err(format!(
                    "{stage}.micro_batch: global_batch {global} must be a multiple of micro_batch {micro}{}",
                    at(&[stage, "micro_batch"])
                ));
            }
            if lpips_weight > 0.0 && !has_weights {
                return Err(format!(
                    "{stage}.lpips_weight is {lpips_weight} but {stage}.lpips_weights (a safetensors file from tools/convert_lpips_weights.py) is not given; set lpips_weight: 0 to train with L1 alone{}",
                    at(&[stage])
                ));
            }
        }
        if let Some(spec) = &self.evaluate {
            spec.validate()
                .map_err(|e| format!("evaluate.{e}{}", at(&["evaluate"])))?;
        }
        if self.workers.minimum.0 > self.workers.expected.0 {
            return Err(format!(
                "workers.minimum ({}) exceeds workers.expected ({}){}",
                self.workers.minimum.0,
                self.workers.expected.0,
                at(&["workers", "minimum"])
            ));
        }
        if self.workers.heartbeat_timeout_s.0 <= self.workers.heartbeat_interval_s.0 {
            return Err(format!(
                "workers.heartbeat_timeout_s ({}) must exceed workers.heartbeat_interval_s ({})",
                self.workers.heartbeat_timeout_s.0, self.workers.heartbeat_interval_s.0
            ));
        }
        if let DataConfig::Generated(generated) = &self.data
            && (generated.frames.0 as usize) < self.stage2.objective.views
        {
            return Err(format!(
                "data.generated.frames ({}) is fewer than stage2.objective.views ({})",
                generated.frames.0, self.stage2.objective.views
            ));
        }
        if let DataConfig::Datasets(datasets) = &self.data {
            if datasets.is_empty() {
                return Err("data.datasets: expected at least one dataset".into());
            }
            for (i, a) in datasets.iter().enumerate() {
                if datasets[..i].iter().any(|b| b.kind == a.kind) {
                    return Err(format!(
                        "data.datasets[{i}]: dataset kind `{}` appears twice",
                        a.kind.name()
                    ));
                }
            }
        }
        Ok(())
    }

    /// The model configuration (already checked when the file was read).
    pub fn model_config(&self) -> Result<XFactorConfig, String> {
        self.model.resolve()
    }

    /// The window sampler of `stage` (1 or 2) with the datasets' overrides.
    pub fn sampler(&self, stage: u32) -> SamplerConfig {
        let mut sampler = if stage == 1 {
            SamplerConfig::stage1()
        } else {
            SamplerConfig::stage2()
        };
        if stage == 2 {
            sampler.frames = self.stage2.objective.views;
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
mod tests {
    use super::*;

    const GOOD: &str = "job: demo
auth:
  token: abc
model:
  preset: tiny
  image_size: 32
data:
  datasets:
    - kind: re10k
      uri: /data/re10k
      stage1: {weight: 2, window_begin: 3, window_end: 9}
stage1:
  steps: 10
  global_batch: 8
  micro_batch: 4
  lpips_weight: 0
stage2:
  steps: 5
  global_batch: 8
  micro_batch: 2
  lpips_weight: 0
checkpoint:
  uri: /tmp/ckpt
  every: 5
";

    fn error_of(yaml: &str) -> String {
        ClusterConfig::from_yaml(yaml, "cluster.yaml")
            .expect_err("the YAML must be refused")
            .to_string()
    }

    #[test]
    fn a_good_file_resolves_with_paper_defaults_where_silent() {
        let config = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
        assert_eq!(config.stage1.steps, 10);
        assert_eq!(config.stage1.optimizer, AdamWConfig::default());
        assert_eq!(config.stage1.schedule.total_steps, 10);
        assert_eq!(config.stage1.schedule.peak_lr, 4e-4);
        assert_eq!(config.workers.expected.0, 2);
        let sampler = config.sampler(1);
        assert_eq!(sampler.datasets.len(), 1);
        assert_eq!(sampler.datasets[0].weight, 2.0);
        assert_eq!(sampler.datasets[0].window_end, 9);
        let stage2 = config.sampler(2);
        assert_eq!(
            stage2.datasets[0].window_end, 200,
            "paper default for RE10K"
        );
        assert_eq!(stage2.frames, 6);
        assert_eq!(config.auth.resolve().unwrap(), "abc");
    }

    #[test]
    fn an_unknown_key_is_named_with_its_line() {
        let yaml = GOOD.replace("  micro_batch: 2\n", "  micro_batch: 2\n  micro_bacth: 3\n");
        let error = error_of(&yaml);
        assert!(error.contains("micro_bacth"), "{error}");
        assert!(error.contains("stage2"), "{error}");
        assert!(error.contains("line 21"), "{error}");
        assert!(error.contains("expected one of"), "{error}");
    }

    #[test]
    fn the_evaluation_section_takes_defaults_and_names_unknown_keys() {
        let config =
            ClusterConfig::from_yaml(&format!("{GOOD}evaluate: {{tps_pairs: 4}}\n"), "t.yaml")
                .unwrap_or_else(|e| panic!("{e}"));
        let spec = config.evaluate.expect("an evaluation");
        assert_eq!(spec.tps_pairs, 4);
        assert_eq!(spec.probe, evaluation::EvaluationSpec::default().probe);
        let error = error_of(&format!("{GOOD}evaluate:\n  tps_pairz: 4\n"));
        assert!(error.contains("tps_pairz"), "{error}");
        assert!(error.contains("evaluate"), "{error}");
        assert!(error.contains("line"), "{error}");
        let limits = error_of(&format!(
            "{GOOD}evaluate:\n  scenes: 3\n  probe: {{test_scenes: 3}}\n"
        ));
        assert!(limits.contains("evaluate.probe.test_scenes"), "{limits}");
        assert!(limits.contains("line"), "{limits}");
    }

    #[test]
    fn bad_values_name_the_key_the_line_and_the_expectation() {
        let zero = error_of(&GOOD.replace("  steps: 10", "  steps: 0"));
        assert!(zero.contains("stage1.steps"), "{zero}");
        assert!(zero.contains("line 13"), "{zero}");
        assert!(zero.contains("positive whole number"), "{zero}");

        let negative = error_of(&GOOD.replace("weight: 2,", "weight: -1,"));
        assert!(
            negative.contains("data.datasets[0].stage1.weight"),
            "{negative}"
        );
        assert!(negative.contains("line 11"), "{negative}");
        assert!(negative.contains(">= 0"), "{negative}");

        let kind = error_of(&GOOD.replace("kind: re10k", "kind: imagenet"));
        assert!(kind.contains("unknown variant `imagenet`"), "{kind}");
        assert!(kind.contains("line 9"), "{kind}");

        let batch = error_of(&GOOD.replace("  micro_batch: 4", "  micro_batch: 3"));
        assert!(batch.contains("multiple of micro_batch 3"), "{batch}");
        assert!(batch.contains("stage1.micro_batch"), "{batch}");
        assert!(batch.contains("line 15"), "{batch}");

        let text = error_of(&GOOD.replace("every: 5", "every: often"));
        assert!(text.contains("checkpoint.every"), "{text}");
        assert!(text.contains("invalid type"), "{text}");
    }

    #[test]
    fn lpips_without_weights_and_inconsistent_workers_are_refused() {
        let lpips =
            error_of(&GOOD.replace("  lpips_weight: 0\nstage2", "  lpips_weight: 0.5\nstage2"));
        assert!(lpips.contains("lpips_weights"), "{lpips}");
        let workers = error_of(&format!("{GOOD}workers:\n  expected: 2\n  minimum: 3\n"));
        assert!(
            workers.contains("workers.minimum (3) exceeds workers.expected (2)"),
            "{workers}"
        );
        let malformed = error_of("job: [unclosed");
        assert!(malformed.contains("line 1"), "{malformed}");
        let missing = error_of(&GOOD.replace("checkpoint:\n  uri: /tmp/ckpt\n  every: 5\n", ""));
        assert!(missing.contains("missing field `checkpoint`"), "{missing}");
    }

    #[test]
    fn a_token_variable_that_is_not_set_is_named() {
        let yaml = GOOD.replace(
            "  token: abc",
            "  token_env: XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET",
        );
        let config = ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap();
        let error = config.auth.resolve().unwrap_err();
        assert!(
            error.contains("XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET"),
            "{error}"
        );
    }
}
