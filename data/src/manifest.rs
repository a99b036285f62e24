//! What an indexer produces: sequences with their ordered frame objects, dataset and split.

use serde::{Deserialize, Serialize};
use settings::data::DatasetKind;

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

    /// The test sequences an evaluation of `count` sequences of `length` frames reads (the
    /// first of the test split, in manifest order, with at least `length` frames), and how many
    /// shorter ones it passed over on the way. The evaluation and the coordinator's held-out
    /// check both choose with this, so the check covers exactly what is evaluated.
    pub fn evaluated_test_sequences(&self, length: usize, count: usize) -> (Vec<&Sequence>, usize) {
        let mut chosen = Vec::new();
        let mut skipped_short = 0;
        for sequence in self.sequences.iter().filter(|s| s.split == Split::Test) {
            if chosen.len() == count {
                break;
            }
            if sequence.frames.len() < length {
                skipped_short += 1;
            } else {
                chosen.push(sequence);
            }
        }
        (chosen, skipped_short)
    }
}
