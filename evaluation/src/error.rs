//! The library's one error type, so the coordinator and the binary can report any failure of an
//! evaluation with its cause.

use std::path::PathBuf;

use data::decode::DecodeError;
use data::index::IndexError;
use data::store::StoreError;
use settings::evaluation::EvaluationSpecError;
use trainer_core::checkpoint::CheckpointError;

use crate::figures::FigureError;
use crate::metrics::ImageMetricError;
use crate::oracle::OracleError;
use crate::video::VideoError;

/// Why a transfer or an evaluation failed.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// The checkpoint could not be loaded or a model not built.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// Frames could not be listed or read.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A dataset of the sequence protocol could not be indexed.
    #[error(transparent)]
    Index(#[from] IndexError),
    /// A frame could not be decoded.
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// A video could not be decoded or written.
    #[error(transparent)]
    Video(#[from] VideoError),
    /// A figure could not be written.
    #[error(transparent)]
    Figure(#[from] FigureError),
    /// The pose oracle failed.
    #[error(transparent)]
    Oracle(#[from] OracleError),
    /// Two images could not be compared.
    #[error(transparent)]
    ImageMetric(#[from] ImageMetricError),
    /// A file of the report could not be written.
    #[error("{path}: {reason}")]
    Io {
        /// File or directory at fault.
        path: PathBuf,
        /// What the file system said.
        reason: String,
    },
    /// The evaluation spec breaks one of its limits.
    #[error(transparent)]
    Spec(#[from] EvaluationSpecError),
    /// The inputs or the spec cannot be evaluated as given.
    #[error("{0}")]
    Invalid(String),
    /// A tensor could not be read back from the device.
    #[error("reading a tensor back: {0}")]
    Tensor(String),
}

/// An [`EvalError::Io`] for `path`.
pub(crate) fn io_error(path: &std::path::Path, error: impl ToString) -> EvalError {
    EvalError::Io {
        path: path.to_path_buf(),
        reason: error.to_string(),
    }
}
