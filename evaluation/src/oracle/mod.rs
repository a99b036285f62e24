//! Pose oracles: programs that look at frames and say where the camera was. TPS compares the
//! oracle's reading of a source video with its reading of the renders made from it, so every
//! estimator sits behind one trait.

mod classical;
mod external;
mod ground_truth;

pub use classical::{ClassicalOracle, ClassicalSettings};
pub use external::ExternalOracle;
pub use ground_truth::GroundTruthOracle;

use data::Image;
use data::scenes::CameraPose;

/// Why an oracle could not estimate the poses of a sequence.
#[derive(Debug, thiserror::Error)]
pub enum OracleError {
    /// The oracle needs more frames or more texture than it got.
    #[error("{oracle}: {reason}")]
    Estimate {
        /// The oracle's name.
        oracle: &'static str,
        /// What was missing.
        reason: String,
    },
    /// The external program failed or printed something unusable.
    #[error("external pose command `{command}`: {reason}")]
    External {
        /// The program run.
        command: String,
        /// What went wrong.
        reason: String,
    },
}

/// Estimates one world-to-camera pose per frame (any world frame and, for translations, any
/// common scale: the camera metrics only compare relative rotations and directions).
pub trait PoseOracle: Sync {
    /// Short name for reports.
    fn name(&self) -> &'static str;
    /// The camera pose of each of `frames`, in order.
    fn estimate(&self, frames: &[Image]) -> Result<Vec<CameraPose>, OracleError>;
}
