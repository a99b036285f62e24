//! The classical two-view oracle for real images: Harris corners and patch descriptors matched
//! between consecutive frames within a small window and followed into tracks from the first
//! frame (repeated textures defeat matching across wide baselines directly), then an essential
//! matrix between the first frame and each other frame from the tracked corners (normalised
//! 8-point, RANSAC on the Sampson error, cheirality), chained into one trajectory.
//!
//! Chaining: every frame is estimated against frame 0 directly (no drift from composing
//! consecutive relative poses), which fixes rotations and translation directions. Each pair's translation has its
//! own unknown length; lengths are made consistent through the depths of frame 0's corners,
//! which every pair triangulates in its own baseline units: the length of pair `i` relative to
//! the anchor pair (the last estimated frame, usually the widest baseline) is the median ratio
//! of the anchor's depths to pair `i`'s over the corners both keep as inliers (1 when fewer
//! than [`MIN_SHARED_DEPTHS`] are shared).

mod essential;
mod features;

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use trainer_core::augment::Image;
use trainer_core::scenes::CameraPose;

use self::essential::{Ransac, RelativePose, relative_pose};
use self::features::{Feature, detect, match_features};
use super::{OracleError, PoseOracle};
use crate::geometry::pose;

/// Fewest corners two pairs must share to relate their translation lengths.
const MIN_SHARED_DEPTHS: usize = 5;

/// Knobs of the classical oracle.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ClassicalSettings {
    /// Field of view of the square frames, degrees (the generated scenes use 60; for real
    /// videos it is an assumption the caller states).
    pub fov_degrees: f64,
    /// Corners kept per frame.
    pub max_corners: usize,
    /// RANSAC hypotheses per pair.
    pub ransac_iterations: usize,
    /// Inlier threshold, pixels (Sampson distance).
    pub pixel_threshold: f64,
    /// Largest displacement of a corner between consecutive frames, as a share of the side.
    pub max_shift: f64,
    /// Seed of RANSAC's draws.
    pub seed: u64,
}

impl Default for ClassicalSettings {
    /// 60° field of view, 800 corners, 1000 hypotheses, half-pixel threshold, shifts up to 8% per frame.
    fn default() -> Self {
        Self {
            fov_degrees: 60.0,
            max_corners: 800,
            ransac_iterations: 1000,
            pixel_threshold: 0.5,
            max_shift: 0.08,
            seed: 0,
        }
    }
}

/// Feature matching and essential matrices, each frame against the first.
#[derive(Debug, Clone)]
pub struct ClassicalOracle {
    settings: ClassicalSettings,
}

impl ClassicalOracle {
    /// An oracle with the given settings.
    pub fn new(settings: ClassicalSettings) -> Self {
        Self { settings }
    }

    fn failure(reason: String) -> OracleError {
        OracleError::Estimate {
            oracle: "classical",
            reason,
        }
    }

    /// Pinhole normalisation of a pixel position (pixel centres at integers, principal point
    /// at the image centre, as the scene renderer casts rays).
    fn normalised(&self, feature: &Feature, side: usize) -> Vector2<f64> {
        let half = side as f64 / 2.0;
        let focal = self.focal(side);
        Vector2::new(
            (feature.x + 0.5 - half) / focal,
            (feature.y + 0.5 - half) / focal,
        )
    }

    /// Relative pose of frame `index` against frame 0 from `tracks` (frame-0 corner, corner
    /// in frame `index`), with the frame-0 corner of each inlier.
    fn against_first(
        &self,
        first: &[Feature],
        other: &[Feature],
        tracks: &[(usize, usize)],
        index: usize,
        side: usize,
    ) -> Result<(RelativePose, Vec<usize>), OracleError> {
        let x1: Vec<Vector2<f64>> = tracks
            .iter()
            .map(|&(i, _)| self.normalised(&first[i], side))
            .collect();
        let x2: Vec<Vector2<f64>> = tracks
            .iter()
            .map(|&(_, j)| self.normalised(&other[j], side))
            .collect();
        let ransac = Ransac {
            iterations: self.settings.ransac_iterations,
            threshold: (self.settings.pixel_threshold / self.focal(side)).powi(2),
            seed: self.settings.seed ^ index as u64,
        };
        let relative = relative_pose(&x1, &x2, &ransac).ok_or_else(|| {
            Self::failure(format!(
                "frame {index}: no essential matrix from {} corners tracked from frame 0",
                tracks.len()
            ))
        })?;
        let corners = relative.inliers.iter().map(|&m| tracks[m].0).collect();
        Ok((relative, corners))
    }

    /// Focal length in pixels of a square frame of `side` pixels.
    fn focal(&self, side: usize) -> f64 {
        side as f64 / 2.0 / (self.settings.fov_degrees.to_radians() / 2.0).tan()
    }
}

/// Median of `values` (which must not be empty).
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

impl PoseOracle for ClassicalOracle {
    fn name(&self) -> &'static str {
        "classical"
    }

    fn estimate(&self, frames: &[Image]) -> Result<Vec<CameraPose>, OracleError> {
        let Some(first_frame) = frames.first() else {
            return Ok(Vec::new());
        };
        if frames.iter().any(|f| f.width != f.height) {
            return Err(Self::failure("frames must be square".to_string()));
        }
        let side = first_frame.width;
        let features: Vec<Vec<Feature>> = frames
            .iter()
            .map(|frame| detect(frame, self.settings.max_corners))
            .collect();
        let first = &features[0];
        // tracked[c] = index in the current frame of frame-0 corner c, while it is followed.
        let mut tracked: Vec<Option<usize>> = (0..first.len()).map(Some).collect();
        let mut pairs = Vec::with_capacity(frames.len() - 1);
        for index in 1..frames.len() {
            let links = match_features(
                &features[index - 1],
                &features[index],
                self.settings.max_shift * side as f64,
            );
            let mut next = vec![None; features[index - 1].len()];
            for (a, b) in links {
                next[a] = Some(b);
            }
            tracked = tracked.iter().map(|t| t.and_then(|k| next[k])).collect();
            let tracks: Vec<(usize, usize)> = tracked
                .iter()
                .enumerate()
                .filter_map(|(c, t)| t.map(|k| (c, k)))
                .collect();
            pairs.push(self.against_first(first, &features[index], &tracks, index, side)?);
        }
        let depth_of = |(relative, corners): &(RelativePose, Vec<usize>)| -> Vec<Option<f64>> {
            let mut by_corner = vec![None; first.len()];
            for (corner, depth) in corners.iter().zip(&relative.depths) {
                by_corner[*corner] = *depth;
            }
            by_corner
        };
        let anchor = pairs.last().map(depth_of).unwrap_or_default();
        let mut poses = vec![CameraPose::identity()];
        for pair in &pairs {
            let depths = depth_of(pair);
            let ratios: Vec<f64> = anchor
                .iter()
                .zip(&depths)
                .filter_map(|(a, d)| Some(a.as_ref()? / d.as_ref()?))
                .collect();
            let length = if ratios.len() >= MIN_SHARED_DEPTHS {
                median(ratios)
            } else {
                1.0
            };
            let rotation: Matrix3<f64> = pair.0.rotation;
            let translation: Vector3<f64> = pair.0.direction * length;
            poses.push(pose(&rotation, &translation));
        }
        Ok(poses)
    }
}
