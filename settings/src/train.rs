//! What one process needs to train one stage besides the model configuration.

use serde::{Deserialize, Serialize};

use crate::objective::{ObjectiveSettings, Stage1Config, Stage2Config};
use crate::optim::{AdamWConfig, Schedule};

/// Which objective a run optimises.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StageObjective {
    /// Stereo-monocular transferability.
    Stage1(Stage1Config),
    /// Multi-view fine-tune.
    Stage2(Stage2Config),
}

impl StageObjective {
    /// Weight of LPIPS in the loss.
    pub fn lpips_weight(&self) -> f64 {
        match self {
            Self::Stage1(config) => config.lpips_weight(),
            Self::Stage2(config) => config.lpips_weight(),
        }
    }
}

/// Everything a single-process run needs besides the model configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Root of every random draw.
    pub seed: u64,
    /// The objective.
    pub objective: StageObjective,
    /// Samples per optimiser update.
    pub global_batch: usize,
    /// Samples per forward/backward pass; the global batch is accumulated from these.
    pub micro_batch: usize,
    /// Threads that split each micro-batch (one per core is fastest on the CPU backend).
    pub shards: usize,
    /// Learning-rate schedule.
    pub schedule: Schedule,
    /// Optimiser settings.
    pub optimizer: AdamWConfig,
}
