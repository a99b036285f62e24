//! What an indexer produces: sequences with their ordered frame objects, dataset and split.

use serde::{Deserialize, Serialize};

/// The four datasets of the aggregate training set.
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
}

impl DatasetKind {
    /// Every dataset, in a fixed order.
    pub const ALL: [DatasetKind; 4] = [Self::Re10k, Self::Dl3dv, Self::Mvimgnet, Self::Co3dv2];

    /// The name used in configs and logs.
    pub fn name(self) -> &'static str {
        match self {
            Self::Re10k => "re10k",
            Self::Dl3dv => "dl3dv",
            Self::Mvimgnet => "mvimgnet",
            Self::Co3dv2 => "co3dv2",
        }
    }
}

/// Train or test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// Used for training.
    Train,
    /// Held out.
    Test,
}

/// One video: its frames in order, and camera poses where the dataset ships them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sequence {
    /// The dataset it belongs to.
    pub dataset: DatasetKind,
    /// Its split.
    pub split: Split,
    /// Identifier unique within the dataset (e.g. `category/sequence`).
    pub id: String,
    /// Object paths of the frames, in temporal order, relative to the dataset root.
    pub frames: Vec<String>,
    /// Object path of the camera file, where the dataset ships one.
    pub poses: Option<String>,
}

/// All sequences of an indexed dataset tree.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Sequences in a stable order (dataset, then id).
    pub sequences: Vec<Sequence>,
}

impl Manifest {
    /// Frames per sequence, in order: what sharding balances.
    pub fn frame_counts(&self) -> Vec<usize> {
        self.sequences.iter().map(|s| s.frames.len()).collect()
    }
}
