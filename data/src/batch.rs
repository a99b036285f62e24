//! What training consumes: the samples of one (micro-)batch, the trait every sample source
//! implements, and why a source can fail.

use settings::data::DatasetKind;

use crate::decode::DecodeError;
use crate::frame::Image;
use crate::manifest::Split;
use crate::store::StoreError;

/// The samples of one (micro-)batch, in the form its stage needs.
#[derive(Debug, Clone)]
pub enum Samples {
    /// Stage 1: `(context, target)` frames.
    Pairs(Vec<(Image, Image)>),
    /// Stage 2: frames with their index in the video.
    Views(Vec<Vec<(u64, Image)>>),
}

/// Where training samples come from. Implementations must return the same samples for the same
/// `(step, first_sample, count)`, whichever process asks: that is what makes runs reproduce.
pub trait BatchSource: Sync {
    /// Global samples `first_sample .. first_sample + count` of `step`.
    fn samples(&self, step: u64, first_sample: u64, count: usize) -> Result<Samples, SampleError>;
}

/// Why one frame of a drawn window could not be used. The loader skips such a frame, counts it
/// and redraws the sample, so a caller meets one only as the last cause of
/// [`SampleError::NoUsableFrames`].
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    /// The frame could not be read: deleted after indexing ([`StoreError::NotFound`], which
    /// names the path) or the store failed.
    #[error(transparent)]
    Read(#[from] StoreError),
    /// The bytes are not a decodable image; the error names the file.
    #[error(transparent)]
    Decode(#[from] DecodeError),
}

/// Why a batch source could not produce the samples asked for.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// No dataset of the source has sequences of the split being sampled.
    #[error("no dataset has {split:?} sequences to sample")]
    NoSequences {
        /// The split sampled.
        split: Split,
    },
    /// The mixture chose a dataset the source was not given.
    #[error("dataset {} is not configured", dataset.name())]
    DatasetNotConfigured {
        /// The dataset chosen.
        dataset: DatasetKind,
    },
    /// The mixture chose a dataset the sampler has no settings for.
    #[error("dataset {} has no sampler settings", dataset.name())]
    NoSamplerSettings {
        /// The dataset chosen.
        dataset: DatasetKind,
    },
    /// Every draw for one sample hit an unusable frame or a sequence too short for the window:
    /// most of the data is corrupt or missing.
    #[error("step {step} sample {sample}: no decodable frames after {draws} draws")]
    NoUsableFrames {
        /// Step of the sample.
        step: u64,
        /// Global index of the sample.
        sample: u64,
        /// Draws tried.
        draws: u64,
        /// The last frame that could not be used; `None` when every draw fell on a sequence
        /// too short for the window.
        #[source]
        last: Option<FrameError>,
    },
    /// A stage-1 sample's window did not hold the two frames of a pair.
    #[error("step {step} sample {sample}: a pair needs two frames, the window has {frames}")]
    IncompletePair {
        /// Step of the sample.
        step: u64,
        /// Global index of the sample.
        sample: u64,
        /// Frames the window held.
        frames: usize,
    },
    /// A generated sequence has fewer frames than one sample takes.
    #[error(
        "synthetic sequence (scene {scene}, trajectory {trajectory}) has {frames} frames, samples need {needed}"
    )]
    SequenceTooShort {
        /// Scene the sequence was rendered in.
        scene: u64,
        /// Its camera trajectory.
        trajectory: u64,
        /// Frames it has.
        frames: usize,
        /// Frames a sample takes.
        needed: usize,
    },
    /// The loader of an epoch's shard could not start the runtime its reads run on.
    #[error("cannot start the data loader of epoch {epoch}")]
    LoaderStart {
        /// The epoch whose shard was to be read.
        epoch: u64,
        /// Why the runtime did not start.
        #[source]
        source: std::io::Error,
    },
    /// A thread panicked while it held the current epoch's loader, which may be half replaced.
    #[error("data loader lock poisoned")]
    LoaderPoisoned,
}
