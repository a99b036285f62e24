//! The numbers the paper reports: reconstruction quality of images and accuracy of cameras.

mod auc;
mod camera;
mod image;
mod spread;
mod trajectory;

pub use camera::{
    CameraMetrics, PairError, THRESHOLDS, ThresholdScores, pair_error, trajectory_errors,
};
pub use camera::{CameraSpread, camera_spread};
pub use image::{ImageMetricError, ReconstructionReport, psnr, ssim};
pub use spread::bootstrap_spread;
pub use trajectory::{TrajectoryError, trajectory_error};
