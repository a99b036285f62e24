//! The numbers the paper reports: reconstruction quality of images and accuracy of cameras.

pub mod auc;
pub mod camera;
pub mod image;
pub mod trajectory;

pub use camera::{
    CameraMetrics, PairError, THRESHOLDS, ThresholdScores, pair_error, trajectory_errors,
};
pub use image::{ImageMetricError, psnr, ssim};
pub use trajectory::{TrajectoryError, trajectory_error};
