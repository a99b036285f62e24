//! `evaluation`: XFactor's reason to exist — take the camera motion of one video and render it
//! in another scene — and the measurements the paper uses to prove it works: reconstruction
//! metrics, camera metrics, the transferability score (TPS) with pluggable pose oracles, and the
//! pose probe, and the comparison of several runs' reports.

pub mod compare;
pub mod curve;
mod error;
mod figures;
mod frames;
mod geometry;
mod inference;
pub mod metrics;
pub mod oracle;
mod transfer;
mod video;

pub use error::EvalError;
pub use transfer::{TransferOutput, TransferRequest, run_transfer, run_transfer_sampled};
pub use video::Sampling;
pub mod evaluate;
mod probe;
pub mod sequences;
mod so3;
mod tps;

pub use evaluate::{EvaluationReport, run_evaluation};
