//! The data a stage trains on, as the coordinator resolves it and every rank receives it:
//! datasets, their listing fingerprints, the window sampler's settings and the sample source.

use serde::{Deserialize, Serialize};

/// The datasets a job can train on: XFactor's four, and the three more of E-RayZer's
/// seven-dataset mixture.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DatasetKind {
    /// RealEstate10K.
    Re10k,
    /// DL3DV-10K.
    Dl3dv,
    /// MVImgNet.
    Mvimgnet,
    /// CO3Dv2.
    Co3dv2,
    /// ARKitScenes (E-RayZer's mixture).
    Arkitscenes,
    /// WildRGB-D (E-RayZer's mixture).
    Wildrgbd,
    /// ACID, the Aerial Coastline Imagery Dataset (E-RayZer's mixture).
    Acid,
}

impl DatasetKind {
    /// Every dataset, in a fixed order.
    pub const ALL: [DatasetKind; 7] = [
        Self::Re10k,
        Self::Dl3dv,
        Self::Mvimgnet,
        Self::Co3dv2,
        Self::Arkitscenes,
        Self::Wildrgbd,
        Self::Acid,
    ];

    /// The name used in configs and logs.
    pub fn name(self) -> &'static str {
        match self {
            Self::Re10k => "re10k",
            Self::Dl3dv => "dl3dv",
            Self::Mvimgnet => "mvimgnet",
            Self::Co3dv2 => "co3dv2",
            Self::Arkitscenes => "arkitscenes",
            Self::Wildrgbd => "wildrgbd",
            Self::Acid => "acid",
        }
    }
}

/// What the listing of a dataset root looked like: changes when objects are added, removed,
/// resized or rewritten.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ListingFingerprint {
    /// Objects under the root (the cache itself excluded).
    pub objects: u64,
    /// Their total size in bytes.
    pub bytes: u64,
    /// The newest modification time, seconds since the epoch.
    pub newest: i64,
    /// CRC-32 of the sorted object paths.
    pub paths_crc: u32,
}

/// Sampling settings of one dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetSampling {
    /// The dataset.
    pub dataset: DatasetKind,
    /// Mixture weight (relative).
    pub weight: f64,
    /// Largest window length at step 0.
    pub window_begin: usize,
    /// Largest window length once the curriculum is over.
    pub window_end: usize,
}

/// Sampling settings of one stage (defaults per stage: the paper's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SamplerConfig {
    /// Frames per sample (2 in stage 1, 6 in stage 2).
    pub frames: usize,
    /// Steps over which the largest window grows from `window_begin` to `window_end`.
    pub curriculum_steps: u64,
    /// Probability that the frame order is reversed.
    pub reverse_probability: f64,
    /// Favour long windows with `0.8 exp(-((u - 0.7) / 0.25)^2) + 0.2` (stage 2).
    pub long_baseline: bool,
    /// Keep the reference (middlest) frame within `band * window / 2` of both ends. Off by
    /// default: the release's `GAP_SIGMA = 1.25` never reaches its sampler.
    pub reference_band: Option<f64>,
    /// Per-dataset settings.
    pub datasets: Vec<DatasetSampling>,
}

fn datasets(entries: [(DatasetKind, f64, usize, usize); 4]) -> Vec<DatasetSampling> {
    entries
        .into_iter()
        .map(
            |(dataset, weight, window_begin, window_end)| DatasetSampling {
                dataset,
                weight,
                window_begin,
                window_end,
            },
        )
        .collect()
}

impl SamplerConfig {
    /// Stage 1: pairs; CO3Dv2 `9 -> 20`, DL3DV `5 -> 10`, RE10K `40 -> 100`, MVImgNet `5 -> 10`,
    /// equal weights.
    pub fn stage1() -> Self {
        Self {
            frames: 2,
            curriculum_steps: 50_000,
            reverse_probability: 0.5,
            long_baseline: false,
            reference_band: None,
            datasets: datasets([
                (DatasetKind::Co3dv2, 1.0, 9, 20),
                (DatasetKind::Dl3dv, 1.0, 5, 10),
                (DatasetKind::Re10k, 1.0, 40, 100),
                (DatasetKind::Mvimgnet, 1.0, 5, 10),
            ]),
        }
    }

    /// Stage 2: 6 frames; CO3Dv2 `9 -> 40` (2), DL3DV `6 -> 20` (5), RE10K `40 -> 200` (3),
    /// MVImgNet `6 -> 20` (2); long baselines favoured; interior frames uniform (no reference
    /// band, as the release samples).
    pub fn stage2() -> Self {
        Self {
            frames: 6,
            curriculum_steps: 50_000,
            reverse_probability: 0.5,
            long_baseline: true,
            reference_band: None,
            datasets: datasets([
                (DatasetKind::Co3dv2, 2.0, 9, 40),
                (DatasetKind::Dl3dv, 5.0, 6, 20),
                (DatasetKind::Re10k, 3.0, 40, 200),
                (DatasetKind::Mvimgnet, 2.0, 6, 20),
            ]),
        }
    }

    /// The settings of `dataset`, if it takes part.
    pub fn dataset(&self, dataset: DatasetKind) -> Option<&DatasetSampling> {
        self.datasets.iter().find(|d| d.dataset == dataset)
    }
}

/// One stored dataset, pinned to the listing its manifest cache was built from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StoredDataset {
    /// Which layout.
    pub kind: DatasetKind,
    /// Root URI.
    pub uri: String,
    /// Fingerprint of the listing the coordinator indexed.
    pub fingerprint: ListingFingerprint,
    /// A split file (JSON, training sequence ids as keys) that replaces the layout's
    /// train/test rule: relative to `uri`, or a path or URI of its own.
    #[serde(default)]
    pub split_file: Option<String>,
}

/// Where a stage's samples come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DataSource {
    /// Procedural scenes rendered in memory by every rank.
    Generated {
        /// Scenes.
        scenes: u64,
        /// Camera paths, each rendered in every scene.
        trajectories: u64,
        /// Frames per path.
        frames: usize,
    },
    /// Datasets on an object store.
    Stored(Vec<StoredDataset>),
}

/// Everything a rank needs to read a stage's samples.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataSpec {
    /// The samples' origin.
    pub source: DataSource,
    /// Window sampling and mixture of the stage.
    pub sampler: SamplerConfig,
    /// Training resolution.
    pub image_size: usize,
    /// Root of sampling and sharding draws.
    pub seed: u64,
    /// Samples per optimiser step over all ranks (an epoch is about one sample per sequence).
    pub global_batch: usize,
}
