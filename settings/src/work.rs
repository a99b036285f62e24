//! What the coordinator hands a worker and what a worker says back when its part failed, as
//! domain types: absent values are `Option`s, choices are enums, counts are `usize`. The wire
//! forms (`proto::v1::Assignment`, `GenerationFailure`) become these once, in
//! `proto::convert`, so nothing past the edge sees an empty string or a bare integer stage.

use crate::data::DataSpec;
use crate::evaluation::EvaluationSpec;
use crate::train::TrainConfig;
use crate::{DeviceChoice, DeviceSet, Phase, XFactorConfig};

/// One assignment: the generation it belongs to and what to do in it.
#[derive(Debug, Clone, PartialEq)]
pub struct Assignment {
    /// The group's generation; every report of this work names it.
    pub generation: u64,
    /// What to do.
    pub work: Work,
}

/// What a worker does in a generation.
#[derive(Debug, Clone, PartialEq)]
pub enum Work {
    /// Train one stage as one rank of the group.
    Train(Box<TrainWork>),
    /// Evaluate stage 2's final weights and commit the report.
    Evaluate(Box<EvaluateWork>),
    /// The job is over: exit.
    Finish,
}

/// One rank's part of a training stage.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainWork {
    /// Stage 1 or stage 2.
    pub stage: Phase,
    /// This worker's place in the ring.
    pub rank: usize,
    /// Collective addresses of every rank, by rank; its length is the world size.
    pub peers: Vec<String>,
    /// Steps of the stage; training continues from [`TrainStart`]'s step up to this.
    pub total_steps: u64,
    /// Where the trainer's state comes from.
    pub start: TrainStart,
    /// Where this stage's checkpoints go (URI prefix).
    pub checkpoint_prefix: String,
    /// A checkpoint is written and committed every this many steps (and after the last).
    pub checkpoint_every: u64,
    /// When parameter checksums are computed and reported (always after the last step too).
    pub checksum_every: ChecksumEvery,
    /// LPIPS weights (URI or path) when the objective uses LPIPS.
    pub lpips_weights: Option<String>,
    /// The device the job asks for (a worker started with `--device` keeps its own).
    pub device: DeviceChoice,
    /// The model.
    pub model: XFactorConfig,
    /// The optimizer and the stage's objective.
    pub train: TrainConfig,
    /// The data and how it is sampled.
    pub data: DataSpec,
    /// Secrets of the ring streams; `None` in a group of one.
    pub ring: Option<RingSecrets>,
    /// Which of its host's devices the worker drives (the job's; `--devices` overrides).
    pub devices: DeviceSet,
    /// How the ring carries the gradients between ranks.
    pub wire: WireFormat,
    /// TCP lanes the ring runs on (TLS sessions when the job runs TLS), each on a thread of
    /// its own (`workers.allreduce_lanes`); 0: one gRPC stream.
    pub lanes: usize,
}

/// Most lanes a ring may have.
pub const MAX_RING_LANES: usize = 64;

/// How often the replicas hash their parameters for the coordinator to compare
/// (`workers.checksum_every` in the cluster YAML: `auto`, the default, or a step count).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ChecksumEvery {
    /// Every rank derives the interval from the model's size alone (so all ranks agree): the
    /// fewest steps that keep the checksum under 2% of the steps' time (docs/data-path.md):
    /// every step for small models, about every 19 at the paper's size.
    #[default]
    Auto,
    /// Every this many steps (at least 1).
    Steps(u64),
}

impl ChecksumEvery {
    /// Bytes a checksum hashes per second, measured on a 2-core machine at the paper's size
    /// (`cargo bench -p trainer-core --bench checksum`: 1.22 GB in 0.169 s).
    pub const HASHED_BYTES_PER_S: f64 = 7.2e9;
    /// The step the checksum's share is measured against: JAX's stage-1 step of the paper
    /// model on one H200 (0.47 s).
    pub const REFERENCE_STEP_S: f64 = 0.47;
    /// The largest share of the steps' time the checksum may take.
    pub const MAX_SHARE: f64 = 0.02;

    /// The interval in steps for a model of `parameters` float32 values.
    pub fn steps(self, parameters: usize) -> u64 {
        match self {
            Self::Steps(steps) => steps.max(1),
            Self::Auto => {
                let checksum_s = parameters as f64 * 4.0 / Self::HASHED_BYTES_PER_S;
                (checksum_s / (Self::MAX_SHARE * Self::REFERENCE_STEP_S))
                    .ceil()
                    .max(1.0) as u64
            }
        }
    }
}

impl<'de> serde::Deserialize<'de> for ChecksumEvery {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Steps(u64),
            Word(String),
        }
        match Raw::deserialize(deserializer)? {
            Raw::Steps(0) => Err(serde::de::Error::custom(
                "checksum_every must be auto or at least 1",
            )),
            Raw::Steps(steps) => Ok(Self::Steps(steps)),
            Raw::Word(word) if word == "auto" => Ok(Self::Auto),
            Raw::Word(word) => Err(serde::de::Error::custom(format!(
                "checksum_every {word:?}: expected auto or a number of steps"
            ))),
        }
    }
}

impl serde::Serialize for ChecksumEvery {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            Self::Auto => serializer.serialize_str("auto"),
            Self::Steps(steps) => serializer.serialize_u64(*steps),
        }
    }
}

/// How the ring carries gradients between workers (`workers.allreduce_wire` in the cluster
/// YAML). Sums are float32 either way; bf16 halves the bytes each rank sends and rounds each
/// gradient once to bf16 (8 bits of mantissa) on its way round the ring.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum WireFormat {
    /// Every bit of every value (the default).
    #[default]
    F32,
    /// bf16 values summed in float32; the loss terms still travel in float32.
    Bf16,
}

impl WireFormat {
    /// The name the YAML and the logs use.
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
        }
    }
}

impl TrainWork {
    /// Ranks in the group.
    pub fn world_size(&self) -> usize {
        self.peers.len()
    }
}

/// Where a rank's trainer starts from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TrainStart {
    /// Resume exactly from a committed checkpoint of this stage (URI prefix): weights,
    /// optimizer state and step.
    Resume(String),
    /// Start the stage at step 0 from another checkpoint's weights (stage 2 from stage 1's
    /// final).
    InitWeights(String),
    /// A fresh initialisation from the job's seed.
    Fresh,
}

/// Secrets a rank's ring streams carry, fresh for every generation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RingSecrets {
    /// This rank's, for its stream to the right neighbour.
    pub own: String,
    /// The left neighbour's, which this rank demands of the stream it accepts.
    pub left: String,
}

/// One stage's final weights, scored as that stage trained them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckpointToEvaluate {
    /// The stage that committed them.
    pub stage: Phase,
    /// The committed checkpoint's location.
    pub weights: String,
    /// The step it was committed at.
    pub step: u64,
    /// Context views it renders from (stage 1: 1; stage 2: its views less the target).
    pub context_views: usize,
}

/// The evaluation of every stage's final weights, on a group of one.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluateWork {
    /// The committed checkpoints to evaluate, stage 1 first; never empty.
    pub checkpoints: Vec<CheckpointToEvaluate>,
    /// Where the report goes (URI prefix).
    pub report_prefix: String,
    /// The device the job asks for.
    pub device: DeviceChoice,
    /// The model the weights are.
    pub model: XFactorConfig,
    /// What to evaluate and how.
    pub spec: EvaluationSpec,
}

/// A worker's report that its part of a generation failed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GenerationFailure {
    /// The error, as the worker logged it.
    pub reason: String,
    /// Whose fault it was, which decides what the coordinator does.
    pub cause: FailureCause,
}

/// Whose fault a failed generation was, as far as the failing worker can tell.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FailureCause {
    /// The reporting worker's own (its data, its device, its disk): it is blamed.
    Worker,
    /// The peer at this rank timed out, broke its stream or sent a bad chunk: it is blamed.
    Peer {
        /// The suspect's rank.
        rank: usize,
    },
    /// The object store failed after its retries: no worker is blamed, and the group re-forms
    /// after a back-off of the store's own.
    Store,
    /// A committed checkpoint does not verify: the phase falls back to the commit before it.
    CorruptCheckpoint {
        /// Where it is.
        location: String,
    },
}

/// What a worker is doing within its step, so the coordinator can tell stuck from slow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Activity {
    /// Between steps, or not in a generation.
    #[default]
    Idle,
    /// Loading samples and computing gradients of its step.
    Computing,
    /// In the all-reduce of its step, waiting for its peers.
    Allreduce,
    /// Writing and committing a checkpoint.
    Committing,
}

/// The loss of one step as rank 0 saw it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StepLoss {
    /// The loss of the global batch.
    pub total: f32,
    /// The learning rate of the step.
    pub learning_rate: f64,
    /// The global gradient norm before clipping.
    pub grad_norm: f64,
    /// False when the update was skipped for an exploding gradient norm.
    pub applied: bool,
    /// The L1 term of `total`.
    pub l1: f32,
    /// The LPIPS term before its weight, where the stage has one.
    pub lpips: Option<f32>,
}

/// One rank's report of a finished step.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct StepReport {
    /// The generation it ran in.
    pub generation: u64,
    /// The step just finished (counted from 0).
    pub step: u64,
    /// Its loss, when the rank reports one.
    pub loss: Option<StepLoss>,
    /// The parameter checksum after the step, when computed.
    pub checksum: Option<u32>,
    /// Samples per second of this worker during the step.
    pub samples_per_s: f64,
    /// Seconds of the step spent in the all-reduce.
    pub allreduce_s: f64,
    /// Wall time of the whole step on this worker.
    pub step_s: f64,
    /// Seconds the step waited for its data loader.
    pub data_wait_s: f64,
    /// Frames skipped so far in this generation.
    pub skipped_frames: u64,
    /// The newest frames skipped, `dataset path: why`.
    pub skipped_examples: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::ChecksumEvery;

    #[test]
    fn auto_checks_small_models_every_step_and_the_papers_about_every_19() {
        assert_eq!(ChecksumEvery::Auto.steps(1_000_000), 1);
        assert_eq!(ChecksumEvery::Auto.steps(305_178_624), 19);
        assert_eq!(ChecksumEvery::Steps(4).steps(305_178_624), 4);
        assert_eq!(ChecksumEvery::Steps(0).steps(10), 1);
    }

    #[test]
    fn the_yaml_says_auto_or_a_positive_count() {
        let read = |text: &str| serde_json::from_str::<ChecksumEvery>(text);
        assert_eq!(read("\"auto\"").unwrap(), ChecksumEvery::Auto);
        assert_eq!(read("7").unwrap(), ChecksumEvery::Steps(7));
        assert!(read("0").unwrap_err().to_string().contains("at least 1"));
        assert!(read("\"often\"").unwrap_err().to_string().contains("often"));
        assert_eq!(
            serde_json::to_string(&ChecksumEvery::Auto).unwrap(),
            "\"auto\""
        );
    }
}
