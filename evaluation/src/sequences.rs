//! E-RayZer's evaluation protocol on real test sequences: each dataset has one fixed sequence
//! length, an evaluated sequence's frames are spread evenly over its video with the first and
//! the last always among them, and a sequence too short for the length is skipped (counted in
//! the report) rather than padded or evaluated shorter.

use data::decode::decode_frame;
use data::index::index;
use data::store::DataRoot;
use data::{Image, Split};
use serde::{Deserialize, Serialize};
use settings::data::DatasetKind;
use settings::evaluation::SequenceProtocol;

use crate::error::EvalError;
use crate::frames::block_on;
use crate::metrics::ReconstructionReport;
use crate::video::evenly_spaced;

/// The protocol's frames of a `len`-frame sequence: `length` indices spread evenly over it,
/// first and last included, strictly increasing; `None` when the sequence is shorter.
pub fn protocol_frames(len: usize, length: usize) -> Option<Vec<usize>> {
    (len >= length).then(|| evenly_spaced(len, length))
}

/// One evaluated sequence.
#[derive(Debug, Clone)]
pub struct ProtocolSequence {
    /// Its id in the dataset's manifest.
    pub id: String,
    /// Positions of the chosen frames in the whole sequence.
    pub frame_indices: Vec<usize>,
    /// The chosen frames, decoded at the model's size.
    pub frames: Vec<Image>,
}

/// One dataset's sequences under the protocol.
#[derive(Debug, Clone)]
pub struct ProtocolSet {
    /// What was asked for.
    pub protocol: SequenceProtocol,
    /// The first `count` test sequences long enough, in manifest order.
    pub sequences: Vec<ProtocolSequence>,
    /// Test sequences passed over for being shorter than `length`.
    pub skipped_short: usize,
}

/// The numbers of one dataset under the protocol, as `report.json` carries them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SequenceReport {
    /// The dataset's layout.
    pub kind: DatasetKind,
    /// Its root.
    pub uri: String,
    /// Frames per sequence.
    pub length: usize,
    /// Sequences evaluated.
    pub sequences: usize,
    /// Test sequences skipped for being shorter than `length`.
    pub skipped_short: usize,
    /// Reconstruction of every frame after the first from the first.
    pub reconstruction: ReconstructionReport,
}

/// Indexes `protocol`'s dataset and reads its evaluated sequences at `size x size`.
pub async fn load_protocol_async(
    protocol: &SequenceProtocol,
    size: usize,
) -> Result<ProtocolSet, EvalError> {
    let root = DataRoot::open(&protocol.uri)?;
    let indexed = index(&root, protocol.kind).await?;
    let tests = indexed
        .manifest
        .sequences
        .iter()
        .filter(|s| s.split == Split::Test)
        .count();
    let (chosen, skipped_short) = indexed
        .manifest
        .evaluated_test_sequences(protocol.length, protocol.count);
    let mut set = ProtocolSet {
        protocol: protocol.clone(),
        sequences: Vec::new(),
        skipped_short,
    };
    for sequence in chosen {
        // The chosen sequences are never shorter than the protocol's length.
        let frame_indices =
            protocol_frames(sequence.frames.len(), protocol.length).ok_or_else(|| {
                EvalError::Invalid(format!(
                    "sequence {} has {} frames, fewer than the protocol's {}",
                    sequence.id,
                    sequence.frames.len(),
                    protocol.length
                ))
            })?;
        let mut frames = Vec::with_capacity(frame_indices.len());
        for &i in &frame_indices {
            let path = &sequence.frames[i];
            let bytes = root.read(path).await?;
            frames.push(decode_frame(
                &bytes,
                &format!("{}/{path}", root.uri()),
                size,
            )?);
        }
        set.sequences.push(ProtocolSequence {
            id: sequence.id.clone(),
            frame_indices,
            frames,
        });
    }
    if set.sequences.is_empty() {
        return Err(EvalError::Invalid(format!(
            "evaluate.sequences: {:?} root `{}` has no test sequence of at least {} frames ({} test sequences)",
            protocol.kind, protocol.uri, protocol.length, tests
        )));
    }
    Ok(set)
}

/// [`load_protocol_async`] for callers outside an async runtime.
pub fn load_protocol(protocol: &SequenceProtocol, size: usize) -> Result<ProtocolSet, EvalError> {
    block_on(load_protocol_async(protocol, size))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_evenly_spaced_with_first_and_last() {
        assert_eq!(protocol_frames(30, 5), Some(vec![0, 7, 14, 21, 29]));
        assert_eq!(protocol_frames(10, 10), Some((0..10).collect()));
        assert_eq!(protocol_frames(9, 10), None);
        for len in 2..60 {
            for length in 2..=len {
                let frames = protocol_frames(len, length).unwrap();
                assert_eq!(frames.len(), length);
                assert_eq!((frames[0], frames[length - 1]), (0, len - 1));
                assert!(frames.windows(2).all(|w| w[0] < w[1]), "{len} {length}");
            }
        }
    }
}
