//! The ground-truth oracle for generated scenes: every generated frame comes with its exact
//! pose, so a frame's pose is read off the generated frame it is closest to (absolute
//! difference of block-averaged thumbnails, so the blur of a model's render does not decide the
//! match; the fine detail a renderer has not learnt yet should not hide the layout it has).
//! Generated frames themselves get their exact pose back; a model's render gets the pose of the
//! real view it looks most like, which is what "ground truth" can mean for an image no
//! renderer of the scene produced.

use data::Image;
use data::scenes::{CameraPose, SceneConfig};
use data::synthetic::SyntheticDataset;

use super::{OracleError, PoseOracle};

/// Thumbnail side frames are compared at (or the frame's side, if smaller).
const THUMBNAIL: usize = 8;

/// Render-and-compare against frames of known pose.
#[derive(Debug, Clone)]
pub struct GroundTruthOracle {
    candidates: Vec<(Image, CameraPose)>,
}

/// Block averages of `image` on a `THUMBNAIL`-sided grid (or the image itself when smaller).
fn thumbnail(image: &Image) -> Image {
    let side = THUMBNAIL.min(image.height).min(image.width).max(1);
    let mut sums = vec![0.0f32; side * side * 3];
    let mut counts = vec![0.0f32; side * side];
    for y in 0..image.height {
        for x in 0..image.width {
            let cell = (y * side / image.height) * side + x * side / image.width;
            counts[cell] += 1.0;
            for c in 0..3 {
                sums[cell * 3 + c] += image.pixels[(y * image.width + x) * 3 + c];
            }
        }
    }
    Image {
        height: side,
        width: side,
        pixels: sums
            .iter()
            .enumerate()
            .map(|(i, s)| s / counts[i / 3].max(1.0))
            .collect(),
    }
}

impl GroundTruthOracle {
    /// An oracle over explicit `(frame, pose)` pairs (frames of any one size).
    pub fn new(candidates: Vec<(Image, CameraPose)>) -> Self {
        Self {
            candidates: candidates
                .into_iter()
                .map(|(image, pose)| (thumbnail(&image), pose))
                .collect(),
        }
    }

    /// An oracle knowing every frame of a generated dataset (every trajectory in every scene,
    /// so any transferred motion has its true rendering among the candidates).
    pub fn from_dataset(dataset: &SyntheticDataset) -> Self {
        Self::new(
            dataset
                .sequences
                .iter()
                .flat_map(|s| s.frames.iter().cloned().zip(s.poses.iter().copied()))
                .collect(),
        )
    }

    /// An oracle knowing every path of a generated dataset at `subdivisions` views per gap
    /// between its frames ([`SyntheticDataset::views_between_frames`]; `config` is the one the
    /// dataset was generated with): a render between two frames reads its pose to a
    /// `subdivisions`-th of a frame instead of snapping to one of them.
    pub fn between_frames(
        dataset: &SyntheticDataset,
        subdivisions: usize,
        config: &SceneConfig,
    ) -> Self {
        Self::new(dataset.views_between_frames(subdivisions, config))
    }

    fn nearest(&self, frame: &Image) -> Option<CameraPose> {
        let frame = &thumbnail(frame);
        self.candidates
            .iter()
            .filter(|(c, _)| c.pixels.len() == frame.pixels.len())
            .map(|(c, pose)| {
                let distance: f32 = c
                    .pixels
                    .iter()
                    .zip(&frame.pixels)
                    .map(|(a, b)| (a - b).abs())
                    .sum();
                (distance, pose)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, pose)| *pose)
    }
}

impl PoseOracle for GroundTruthOracle {
    fn name(&self) -> &'static str {
        "ground_truth"
    }

    fn estimate(&self, frames: &[Image]) -> Result<Vec<CameraPose>, OracleError> {
        frames
            .iter()
            .map(|frame| {
                self.nearest(frame).ok_or_else(|| OracleError::Estimate {
                    oracle: "ground_truth",
                    reason: format!(
                        "no known frame of size {}x{} to compare with",
                        frame.height, frame.width
                    ),
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use data::scenes::{Scene, Trajectory};

    #[test]
    fn generated_frames_get_their_exact_poses() {
        let config = SceneConfig {
            image_size: 16,
            ..SceneConfig::default()
        };
        let dataset = SyntheticDataset::generate(3, 2, 2, 4, &config);
        let oracle = GroundTruthOracle::from_dataset(&dataset);
        let sequence = &dataset.sequences[3];
        assert_eq!(oracle.estimate(&sequence.frames).unwrap(), sequence.poses);
        let small = Image {
            height: 4,
            width: 4,
            pixels: vec![0.0; 48],
        };
        assert_eq!(thumbnail(&sequence.frames[0]).pixels.len(), 8 * 8 * 3);
        assert!(oracle.estimate(&[small]).is_err());
    }

    #[test]
    fn a_view_between_two_frames_reads_its_own_pose_with_views_between_frames() {
        let config = SceneConfig {
            image_size: 16,
            ..SceneConfig::default()
        };
        let dataset = SyntheticDataset::generate_split(3, data::Split::Test, 2, 2, 4, &config);
        // The second path in the first scene at half-frame spacing: view 3 lies halfway
        // between frames 1 and 2.
        let first = data::synthetic::HELD_OUT_FIRST_INDEX;
        let halfway = Trajectory::random_between_frames(3, first + 1, 4, 2).poses[3];
        let image = Scene::random(3, first, &config).render(&halfway);
        let coarse =
            GroundTruthOracle::from_dataset(&dataset).estimate(std::slice::from_ref(&image));
        let fine = GroundTruthOracle::between_frames(&dataset, 2, &config)
            .estimate(std::slice::from_ref(&image));
        let sequence = &dataset.sequences[1];
        let coarse = coarse.unwrap()[0];
        assert!(
            coarse == sequence.poses[1] || coarse == sequence.poses[2],
            "the frames alone snap it to a neighbour"
        );
        assert_eq!(fine.unwrap()[0], halfway);
        // The generated frames keep their exact poses.
        let oracle = GroundTruthOracle::between_frames(&dataset, 2, &config);
        let read = oracle.estimate(&sequence.frames).unwrap();
        for (read, truth) in read.iter().zip(&sequence.poses) {
            assert!((0..3).all(|k| (read.translation[k] - truth.translation[k]).abs() < 1e-9));
        }
    }
}
