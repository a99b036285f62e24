//! The rules that span several keys of a cluster YAML, and the bounds the job can act on. serde
//! checks each value alone; these run once the whole file has parsed, so a broken rule is
//! reported before anything starts, naming the key and (where it is written block-style) its
//! line.

use std::fmt;

use settings::model::ConfigError as ModelError;
use settings::objective::{ObjectiveSettings, ObjectiveVariant};

use super::values::locate;
use super::{ClusterConfig, DataConfig};

/// The longest duration any `*_s` key may hold: 30 days.
const MAX_SECONDS: f64 = 30.0 * 24.0 * 3600.0;

/// The most workers one job may expect.
const MAX_WORKERS: u64 = 4096;

/// The most steps one stage may have (the paper's stages have 100k and 200k).
const MAX_STEPS: u64 = 100_000_000;

/// The line of the key a rule is reported at, written as ` at line N`; nothing when the key
/// is not written block-style (a flow mapping, or a default the file does not spell out).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AtLine(pub Option<usize>);

impl fmt::Display for AtLine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(line) => write!(f, " at line {line}"),
            None => Ok(()),
        }
    }
}

/// A cluster YAML that parsed but breaks a rule spanning several keys, or a bound. Each message
/// starts with the key at fault, so an operator knows what to change.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum RuleViolation {
    /// The `model:` section resolves to no valid model.
    #[error("model.{key}: {error}{}{at}", camera_vector_hint(.error))]
    Model {
        /// The key under `model:` the fault is blamed on.
        key: &'static str,
        /// The model rule that failed.
        error: ModelError,
        /// Where the key (or, when not set, `model:`) is.
        at: AtLine,
    },
    /// Stage 2 would train on pairs, which its objective cannot use.
    #[error(
        "stage2.objective.views: {views} is fewer than 3 (stage 2 trains on a reference, at least one more context view and the target; two frames are stage 1's pairs){at}"
    )]
    TooFewStage2Views {
        /// The views asked for.
        views: usize,
        /// Where the key is.
        at: AtLine,
    },
    /// Stage 2 names a variant that only adds a view to stage 1's pairs.
    #[error(
        "stage2.objective.variant: {variant:?} adds a context view to stage 1's pairs; stage 2 has `views` context views already{at}"
    )]
    Stage1OnlyVariantInStage2 {
        /// The variant named.
        variant: ObjectiveVariant,
        /// Where the key is.
        at: AtLine,
    },
    /// A stage's global batch is not made of whole micro-batches.
    #[error(
        "{stage}.micro_batch: global_batch {global} must be a multiple of micro_batch {micro}{at}"
    )]
    UnevenMicroBatch {
        /// `stage1` or `stage2`.
        stage: &'static str,
        /// Samples per step.
        global: u64,
        /// Samples per forward/backward pass.
        micro: u64,
        /// Where `micro_batch` is.
        at: AtLine,
    },
    /// A stage weights LPIPS in its loss but gives no LPIPS weights to compute it with.
    #[error(
        "{stage}.lpips_weight is {lpips_weight} but {stage}.lpips_weights (a safetensors file from tools/convert_lpips_weights.py) is not given; set lpips_weight: 0 to train with L1 alone{at}"
    )]
    LpipsWithoutWeights {
        /// `stage1` or `stage2`.
        stage: &'static str,
        /// The LPIPS weight in the loss.
        lpips_weight: f64,
        /// Where the stage is.
        at: AtLine,
    },
    /// The `evaluate:` section breaks one of the evaluation's limits.
    #[error("evaluate.{problem}{at}")]
    Evaluation {
        /// The evaluation's own message, starting with the key under `evaluate:`.
        problem: String,
        /// Where `evaluate:` is.
        at: AtLine,
    },
    /// The job could continue with more workers than it waits for.
    #[error("workers.minimum ({minimum}) exceeds workers.expected ({expected}){at}")]
    MinimumAboveExpected {
        /// `workers.minimum`.
        minimum: u64,
        /// `workers.expected`.
        expected: u64,
        /// Where `workers.minimum` is.
        at: AtLine,
    },
    /// A duration outside what a clock and the job's liveness checks can act on.
    #[error(
        "workers.{key}: expected between {least} and {max} seconds (30 days), found {value}{at}",
        max = MAX_SECONDS
    )]
    DurationOutOfRange {
        /// The key under `workers:`.
        key: &'static str,
        /// The shortest duration the key may hold.
        least: f64,
        /// The duration given.
        value: f64,
        /// Where the key is.
        at: AtLine,
    },
    /// More workers than one ring may hold.
    #[error(
        "workers.expected: expected at most {max} workers, found {expected}{at}",
        max = MAX_WORKERS
    )]
    TooManyWorkers {
        /// `workers.expected`.
        expected: u64,
        /// Where the key is.
        at: AtLine,
    },
    /// More ring lanes than a ring may have.
    #[error("workers.allreduce_lanes: expected at most {max}, found {lanes}{at}", max = settings::work::MAX_RING_LANES)]
    TooManyLanes {
        /// `workers.allreduce_lanes`.
        lanes: usize,
        /// Where the key is.
        at: AtLine,
    },
    /// The ring on its gRPC stream without TLS: the stream presents the job token and the
    /// ring secret, which would cross the network in the clear (lanes prove the secret
    /// without sending it).
    #[error(
        "workers.allreduce_lanes: 0 (the gRPC stream) needs `tls:`, since the stream presents the job token and the ring's secret; without TLS use 1 or more lanes, which prove the secret without sending it{at}"
    )]
    StreamWithoutTls {
        /// Where the key is.
        at: AtLine,
    },
    /// More steps than one stage may have.
    #[error("{stage}.steps: expected at most {max}, found {steps}{at}", max = MAX_STEPS)]
    TooManySteps {
        /// `stage1` or `stage2`.
        stage: &'static str,
        /// The steps given.
        steps: u64,
        /// Where the key is.
        at: AtLine,
    },
    /// A global batch that would leave some ranks without a sample.
    #[error(
        "{stage}.global_batch: {global} samples cannot be split across workers.expected = {workers} workers (each rank needs at least one){at}"
    )]
    BatchSmallerThanGroup {
        /// `stage1` or `stage2`.
        stage: &'static str,
        /// Samples per step.
        global: u64,
        /// `workers.expected`.
        workers: u64,
        /// Where `global_batch` is.
        at: AtLine,
    },
    /// A live worker would be declared lost between two of its heartbeats.
    #[error(
        "workers.heartbeat_timeout_s ({timeout}) must exceed workers.heartbeat_interval_s ({interval})"
    )]
    HeartbeatTimeoutNotAboveInterval {
        /// `workers.heartbeat_timeout_s`.
        timeout: f64,
        /// `workers.heartbeat_interval_s`.
        interval: f64,
    },
    /// Generated paths are shorter than the window stage 2 draws from them.
    #[error("data.generated.frames ({frames}) is fewer than stage2.objective.views ({views})")]
    TooFewGeneratedFrames {
        /// Frames per generated path.
        frames: u64,
        /// Views per stage-2 sample.
        views: usize,
    },
    /// `data.datasets` lists nothing to train on.
    #[error("data.datasets: expected at least one dataset")]
    NoDatasets,
    /// One dataset kind is listed twice, so its mixture weight would be ambiguous.
    #[error("data.datasets[{index}]: dataset kind `{kind}` appears twice")]
    DuplicateDataset {
        /// Position of the second entry.
        index: usize,
        /// The kind's name.
        kind: &'static str,
    },
}

/// Why a model rule can be broken without the file naming the key: `se3_plucker` sets the
/// camera-vector conditioning that fixes `pose_dim`.
fn camera_vector_hint(error: &ModelError) -> &'static str {
    match error {
        ModelError::CameraVector { .. } => " (an objective variant is se3_plucker)",
        _ => "",
    }
}

/// One stage's batch and LPIPS settings, so both stages pass through the same checks.
struct StageBatch {
    stage: &'static str,
    global: u64,
    micro: u64,
    lpips_weight: f64,
    has_lpips_weights: bool,
}

impl ClusterConfig {
    /// Checks that span several keys; `text` gives their lines. Returns the first broken rule,
    /// in a fixed order, so a file with several faults always names the same one first.
    pub(super) fn check(&self, text: &str) -> Result<(), RuleViolation> {
        let at = |path: &[&str]| AtLine(locate(text, path));
        self.check_model(text)?;
        self.check_stage2_objective(&at)?;
        self.check_batches(&at)?;
        if let Some(spec) = &self.evaluate {
            spec.validate()
                .map_err(|problem| RuleViolation::Evaluation {
                    problem: problem.to_string(),
                    at: at(&["evaluate"]),
                })?;
        }
        if self.workers.minimum.0 > self.workers.expected.0 {
            return Err(RuleViolation::MinimumAboveExpected {
                minimum: self.workers.minimum.0,
                expected: self.workers.expected.0,
                at: at(&["workers", "minimum"]),
            });
        }
        self.check_bounds(&at)?;
        if self.workers.heartbeat_timeout_s.0 <= self.workers.heartbeat_interval_s.0 {
            return Err(RuleViolation::HeartbeatTimeoutNotAboveInterval {
                timeout: self.workers.heartbeat_timeout_s.0,
                interval: self.workers.heartbeat_interval_s.0,
            });
        }
        self.check_data()
    }

    /// The model section resolves, with the conditioning the objective variants ask for; a
    /// fault is reported at the key the file set, or at `model:` when it set none.
    fn check_model(&self, text: &str) -> Result<(), RuleViolation> {
        self.model_config().map(|_| ()).map_err(|error| {
            let key = self.model.key_at_fault(&error);
            let line = locate(text, &["model", key]).or_else(|| locate(text, &["model"]));
            RuleViolation::Model {
                key,
                error,
                at: AtLine(line),
            }
        })
    }

    /// Stage 2 trains on at least three views and with a variant that is not stage 1's own.
    fn check_stage2_objective(&self, at: &dyn Fn(&[&str]) -> AtLine) -> Result<(), RuleViolation> {
        let objective = &self.stage2.objective;
        if objective.views < 3 {
            // Two frames are a stage-1 pair: the data sources serve them as pairs, which the
            // stage-2 objective cannot train on (the generation would fail again and again).
            return Err(RuleViolation::TooFewStage2Views {
                views: objective.views,
                at: at(&["stage2", "objective", "views"]),
            });
        }
        if objective.variant.stage1_only() {
            return Err(RuleViolation::Stage1OnlyVariantInStage2 {
                variant: objective.variant,
                at: at(&["stage2", "objective", "variant"]),
            });
        }
        Ok(())
    }

    /// Each stage's global batch is whole micro-batches, and a stage that weights LPIPS has
    /// the weights to compute it.
    fn check_batches(&self, at: &dyn Fn(&[&str]) -> AtLine) -> Result<(), RuleViolation> {
        let stages = [
            StageBatch {
                stage: "stage1",
                global: self.stage1.global_batch,
                micro: self.stage1.micro_batch,
                lpips_weight: self.stage1.objective.lpips_weight(),
                has_lpips_weights: self.stage1.lpips_weights.is_some(),
            },
            StageBatch {
                stage: "stage2",
                global: self.stage2.global_batch,
                micro: self.stage2.micro_batch,
                lpips_weight: self.stage2.objective.lpips_weight(),
                has_lpips_weights: self.stage2.lpips_weights.is_some(),
            },
        ];
        for batch in stages {
            let stage = batch.stage;
            if batch.global % batch.micro != 0 {
                return Err(RuleViolation::UnevenMicroBatch {
                    stage,
                    global: batch.global,
                    micro: batch.micro,
                    at: at(&[stage, "micro_batch"]),
                });
            }
            if batch.lpips_weight > 0.0 && !batch.has_lpips_weights {
                return Err(RuleViolation::LpipsWithoutWeights {
                    stage,
                    lpips_weight: batch.lpips_weight,
                    at: at(&[stage]),
                });
            }
        }
        Ok(())
    }

    /// Durations and counts within what the job can act on: a timeout of `1e20` seconds does
    /// not fit a clock, a billion workers do not fit a ring, and a global batch smaller than
    /// the group would leave ranks without samples.
    fn check_bounds(&self, at: &dyn Fn(&[&str]) -> AtLine) -> Result<(), RuleViolation> {
        let workers = &self.workers;
        let seconds = [
            ("heartbeat_interval_s", workers.heartbeat_interval_s.0, 0.01),
            ("heartbeat_timeout_s", workers.heartbeat_timeout_s.0, 0.1),
            ("quorum_timeout_s", workers.quorum_timeout_s.0, 0.0),
            ("regroup_grace_s", workers.regroup_grace_s.0, 0.0),
            ("stall_timeout_s", workers.stall_timeout_s.0, 0.1),
            ("exclusion_s", workers.exclusion_s.0, 0.0),
        ];
        for (key, value, least) in seconds {
            if !(least..=MAX_SECONDS).contains(&value) {
                return Err(RuleViolation::DurationOutOfRange {
                    key,
                    least,
                    value,
                    at: at(&["workers", key]),
                });
            }
        }
        if workers.expected.0 > MAX_WORKERS {
            return Err(RuleViolation::TooManyWorkers {
                expected: workers.expected.0,
                at: at(&["workers", "expected"]),
            });
        }
        if workers.allreduce_lanes > settings::work::MAX_RING_LANES {
            return Err(RuleViolation::TooManyLanes {
                lanes: workers.allreduce_lanes,
                at: at(&["workers", "allreduce_lanes"]),
            });
        }
        if workers.allreduce_lanes == 0 && self.tls.is_none() {
            return Err(RuleViolation::StreamWithoutTls {
                at: at(&["workers", "allreduce_lanes"]),
            });
        }
        for (stage, steps, global) in [
            ("stage1", self.stage1.steps, self.stage1.global_batch),
            ("stage2", self.stage2.steps, self.stage2.global_batch),
        ] {
            if steps > MAX_STEPS {
                return Err(RuleViolation::TooManySteps {
                    stage,
                    steps,
                    at: at(&[stage, "steps"]),
                });
            }
            if global < workers.expected.0 {
                return Err(RuleViolation::BatchSmallerThanGroup {
                    stage,
                    global,
                    workers: workers.expected.0,
                    at: at(&[stage, "global_batch"]),
                });
            }
        }
        Ok(())
    }

    /// Generated paths are long enough for stage 2's windows, and stored datasets are a
    /// non-empty list with each kind once.
    fn check_data(&self) -> Result<(), RuleViolation> {
        match &self.data {
            DataConfig::Generated(generated)
                if (generated.frames.0 as usize) < self.stage2.objective.views =>
            {
                Err(RuleViolation::TooFewGeneratedFrames {
                    frames: generated.frames.0,
                    views: self.stage2.objective.views,
                })
            }
            DataConfig::Generated(_) => Ok(()),
            DataConfig::Datasets(datasets) if datasets.is_empty() => Err(RuleViolation::NoDatasets),
            DataConfig::Datasets(datasets) => {
                let repeated = datasets
                    .iter()
                    .enumerate()
                    .find(|(i, a)| datasets[..*i].iter().any(|b| b.kind == a.kind));
                match repeated {
                    Some((index, dataset)) => Err(RuleViolation::DuplicateDataset {
                        index,
                        kind: dataset.kind.name(),
                    }),
                    None => Ok(()),
                }
            }
        }
    }
}
