//! The classical two-view oracle for real images: Harris corners and patch descriptors matched
//! between consecutive frames within a small window and followed into tracks from the first
//! frame (repeated textures defeat matching across wide baselines directly); each tracked
//! corner is then moved to where frame 0's window around it aligns best (sub-pixel
//! Lucas-Kanade against frame 0, so tracks do not drift), and an essential matrix between the
//! first frame and each other frame is fitted to the aligned corners (normalised 8-point,
//! RANSAC on the Sampson error, Levenberg-Marquardt, cheirality).
//!
//! Those pairwise estimates only start a bundle adjustment: with the depths of one pair (the
//! anchor) every frame is resected, corners without a depth are triangulated, and all motions
//! and inverse depths are adjusted together on the robust reprojection error. Sharing frame 0's
//! structure across frames is what makes short baselines' translation directions accurate and
//! all translation lengths consistent (pairs `i < j` with `i > 0` mix the lengths of two
//! frames). Every frame with an essential matrix is tried as the anchor; the bundle with the
//! lowest cost wins.

mod bundle;
mod essential;
mod features;

use data::Image;
use data::scenes::CameraPose;
use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use self::bundle::{Bundle, Free, Observation};
use self::essential::{Ransac, RelativePose, relative_pose};
use self::features::{Feature, Plane, align, detect, match_features};
use super::{OracleError, PoseOracle};
use crate::geometry::pose;

/// Fewest corners two pairs must share to relate their translation lengths.
const MIN_SHARED_DEPTHS: usize = 5;
/// Reprojection error, pixels, up to which the bundle's loss is quadratic (Huber threshold).
const HUBER_PIXELS: f64 = 1.0;
/// Observations further off than this many Huber thresholds after the first adjustment are
/// dropped before the second.
const OUTLIER_HUBERS: f64 = 3.0;
/// Levenberg-Marquardt iterations of a single frame's resection.
const RESECTION_ITERATIONS: usize = 30;
/// Levenberg-Marquardt iterations of a whole-bundle adjustment.
const BUNDLE_ITERATIONS: usize = 50;

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

/// Frame 0's corners followed through the frames.
struct Tracks {
    /// Per frame, its pose against frame 0 and the frame-0 corners of its inliers, where found
    /// (frame 0: `None`).
    pairs: Vec<Option<(RelativePose, Vec<usize>)>>,
    /// Every aligned corner of the later frames, as an observation of its frame-0 corner.
    observations: Vec<Observation>,
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

    /// Follows frame 0's corners from frame to frame and relates each later frame to frame 0.
    fn track(&self, planes: &[Plane], features: &[Vec<Feature>], side: usize) -> Tracks {
        let first = &features[0];
        // tracked[c] = index in the current frame of frame-0 corner c, while it is followed.
        let mut tracked: Vec<Option<usize>> = (0..first.len()).map(Some).collect();
        let mut pairs = vec![None];
        let mut observations = Vec::new();
        for index in 1..features.len() {
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
            // The matched corners, moved to where frame 0's window aligns best.
            let mut aligned = features[index].clone();
            let mut tracks = Vec::new();
            for (c, t) in tracked.iter_mut().enumerate() {
                let Some(k) = *t else {
                    continue;
                };
                let corner = &first[c];
                let guess = (aligned[k].x, aligned[k].y);
                match align(&planes[0], corner.x, corner.y, &planes[index], guess) {
                    Some((x, y)) => {
                        (aligned[k].x, aligned[k].y) = (x, y);
                        tracks.push((c, k));
                    }
                    None => *t = None,
                }
            }
            observations.extend(tracks.iter().map(|&(point, k)| Observation {
                point,
                frame: index,
                position: self.normalised(&aligned[k], side),
            }));
            pairs.push(
                self.against_first(first, &aligned, &tracks, index, side)
                    .ok(),
            );
        }
        Tracks {
            pairs,
            observations,
        }
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
        let planes: Vec<Plane> = frames.iter().map(Plane::smoothed).collect();
        let features: Vec<Vec<Feature>> = frames
            .iter()
            .map(|frame| detect(frame, self.settings.max_corners))
            .collect();
        let Tracks {
            pairs,
            observations,
        } = self.track(&planes, &features, side);
        if frames.len() > 1 && pairs.iter().all(Option::is_none) {
            return Err(Self::failure(
                "no frame has an essential matrix against frame 0".to_string(),
            ));
        }
        let rays: Vec<Vector3<f64>> = features[0]
            .iter()
            .map(|f| self.normalised(f, side).push(1.0))
            .collect();
        let delta = HUBER_PIXELS / self.focal(side);
        let best = (1..frames.len())
            .filter(|&anchor| pairs[anchor].is_some())
            .map(|anchor| {
                let bundle = adjusted(&rays, &pairs, anchor, &observations, delta);
                (bundle.cost(&observations, delta), bundle)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let Some((_, bundle)) = best else {
            return Ok(vec![CameraPose::identity()]);
        };
        Ok(bundle
            .rotations
            .iter()
            .zip(&bundle.translations)
            .map(|(r, t)| pose(r, t))
            .collect())
    }
}

/// Depth of each frame-0 corner in `pair`'s baseline units, where it triangulated.
fn depths_by_corner(pair: &(RelativePose, Vec<usize>), corners: usize) -> Vec<Option<f64>> {
    let mut by_corner = vec![None; corners];
    for (corner, depth) in pair.1.iter().zip(&pair.0.depths) {
        by_corner[*corner] = *depth;
    }
    by_corner
}

/// The bundle started from the depths of pair `anchor` (its baseline is the unit length):
/// each frame resected in turn from its own essential matrix (translation length from the
/// median depth ratio to the anchor) or from the previous frame's pose, whichever fits
/// better; corners the anchor lacks triangulated from their widest-parallax view; then all
/// adjusted together, outlying observations dropped, and adjusted again.
fn adjusted(
    rays: &[Vector3<f64>],
    pairs: &[Option<(RelativePose, Vec<usize>)>],
    anchor: usize,
    observations: &[Observation],
    delta: f64,
) -> Bundle {
    let frames = pairs.len();
    let anchor_depths = pairs[anchor]
        .as_ref()
        .map(|pair| depths_by_corner(pair, rays.len()))
        .unwrap_or_default();
    let mut bundle = Bundle {
        rays: rays.to_vec(),
        inverse_depths: anchor_depths
            .iter()
            .map(|d| d.map_or(0.0, |d| 1.0 / d))
            .collect(),
        rotations: vec![Matrix3::identity(); frames],
        translations: vec![Vector3::zeros(); frames],
    };
    for frame in 1..frames {
        if let Some(candidate) =
            resected(&bundle, pairs, frame, &anchor_depths, observations, delta)
        {
            bundle = candidate;
        }
    }
    triangulate_missing(&mut bundle, observations);
    let free = Free {
        frames: vec![true; frames],
        points: true,
    };
    bundle.adjust(observations, &free, delta, BUNDLE_ITERATIONS);
    let kept: Vec<Observation> = observations
        .iter()
        .filter(|o| {
            bundle
                .residual(o)
                .is_some_and(|r| r.norm() < OUTLIER_HUBERS * delta)
        })
        .copied()
        .collect();
    bundle.adjust(&kept, &free, delta, BUNDLE_ITERATIONS);
    bundle
}

/// A copy of `bundle` with frame `frame` resected from whichever start fits it better.
fn resected(
    bundle: &Bundle,
    pairs: &[Option<(RelativePose, Vec<usize>)>],
    frame: usize,
    anchor_depths: &[Option<f64>],
    observations: &[Observation],
    delta: f64,
) -> Option<Bundle> {
    let frames = pairs.len();
    let seen: Vec<Observation> = observations
        .iter()
        .filter(|o| o.frame == frame)
        .copied()
        .collect();
    let mut free = Free {
        frames: vec![false; frames],
        points: false,
    };
    free.frames[frame] = true;
    let mut starts = vec![(bundle.rotations[frame - 1], bundle.translations[frame - 1])];
    if let Some(pair) = &pairs[frame] {
        let ratios: Vec<f64> = anchor_depths
            .iter()
            .zip(depths_by_corner(pair, bundle.rays.len()))
            .filter_map(|(a, d)| Some(a.as_ref()? / d?))
            .collect();
        let length = if ratios.len() >= MIN_SHARED_DEPTHS {
            median(ratios)
        } else {
            1.0
        };
        starts.push((pair.0.rotation, pair.0.direction * length));
    }
    starts
        .into_iter()
        .map(|(rotation, translation)| {
            let mut candidate = bundle.clone();
            candidate.rotations[frame] = rotation;
            candidate.translations[frame] = translation;
            let cost = candidate.adjust(&seen, &free, delta, RESECTION_ITERATIONS);
            (cost, candidate)
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, candidate)| candidate)
}

/// Gives each corner without an inverse depth the one triangulated from its widest-parallax view.
fn triangulate_missing(bundle: &mut Bundle, observations: &[Observation]) {
    for point in 0..bundle.rays.len() {
        if bundle.inverse_depths[point] > 0.0 {
            continue;
        }
        let widest = observations
            .iter()
            .filter(|o| o.point == point)
            .filter_map(|o| bundle.triangulate(o))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((depth, _)) = widest {
            bundle.inverse_depths[point] = 1.0 / depth;
        }
    }
}
