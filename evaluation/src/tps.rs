//! The transferability score (TPS): pose latents of sequence A's target frames render sequence
//! B's context along A's motion; an oracle estimates the camera motion of A's frames and of the
//! renders, and the camera metrics compare the two.
//!
//! On generated data every trajectory is rendered in every scene, so each pair also carries two
//! calibrations of the oracle: B's true rendering along A's motion (a perfect transfer) and B
//! along an unrelated trajectory (a failed one).
//!
//! A render that reproduces A's video instead of showing B would read as a perfect transfer to
//! any oracle, so every render is first checked against both scenes' frames: a transfer whose
//! renders are mostly closer to A's frames than to any of B's counts as a failed one.

use data::Image;
use data::rng::Stream;
use data::synthetic::SyntheticDataset;
use serde::{Deserialize, Serialize};

use crate::error::EvalError;
use crate::metrics::{
    CameraMetrics, PairError, TrajectoryError, trajectory_error, trajectory_errors,
};
use crate::oracle::PoseOracle;

/// Stream tag of the pair draws.
const TPS_TAG: u64 = 0x0054_5053;
/// Errors recorded for every frame pair of a render the oracle could not read.
const FAILED: PairError = PairError {
    rotation: 180.0,
    translation: 90.0,
};

/// One transfer: A's motion (scene, trajectory) rendered in scene `scene_b`, starting from B's
/// view of A's first frame; `other_trajectory` is the unrelated motion of the failed baseline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TpsPair {
    /// Scene A.
    pub scene_a: u64,
    /// Scene B (never A).
    pub scene_b: u64,
    /// The trajectory transferred.
    pub trajectory: u64,
    /// A different trajectory, for the random baseline.
    pub other_trajectory: u64,
}

/// `count` pairs drawn from `(seed)`; needs at least two scenes and two trajectories.
pub fn draw_pairs(
    seed: u64,
    scenes: u64,
    trajectories: u64,
    count: usize,
) -> Result<Vec<TpsPair>, EvalError> {
    if scenes < 2 || trajectories < 2 {
        return Err(EvalError::Invalid(format!(
            "TPS needs at least 2 scenes and 2 trajectories, got {scenes} and {trajectories}"
        )));
    }
    Ok((0..count as u64)
        .map(|k| {
            let mut stream = Stream::new(&[seed, TPS_TAG, k]);
            let scene_a = stream.below(scenes);
            let scene_b = (scene_a + 1 + stream.below(scenes - 1)) % scenes;
            let trajectory = stream.below(trajectories);
            let other_trajectory = (trajectory + 1 + stream.below(trajectories - 1)) % trajectories;
            TpsPair {
                scene_a,
                scene_b,
                trajectory,
                other_trajectory,
            }
        })
        .collect())
}

/// `count` equally spaced frame indices of a `frames`-frame sequence, first and last included.
pub fn target_frames(frames: usize, count: usize) -> Vec<usize> {
    if count >= frames || count < 2 {
        return (0..frames).collect();
    }
    (0..count).map(|k| k * (frames - 1) / (count - 1)).collect()
}

/// The frames of one TPS pair: A's targets, B's true rendering along them, B along another
/// motion, and B's context views.
#[derive(Debug, Clone)]
pub struct PairFrames {
    /// A's target frames (the first is A's reference).
    pub source: Vec<Image>,
    /// B rendered along A's motion: what a perfect transfer produces.
    pub ideal: Vec<Image>,
    /// B rendered along an unrelated motion.
    pub unrelated: Vec<Image>,
    /// B's context views: first B's view of A's first pose (the reference), then, for a
    /// multi-view model, views spread along the unrelated motion (never on A's path).
    pub contexts: Vec<Image>,
}

/// Gathers the frames of `pair` at `indices`, with `context_views` context views of B.
pub fn pair_frames(
    dataset: &SyntheticDataset,
    pair: &TpsPair,
    indices: &[usize],
    context_views: usize,
) -> Result<PairFrames, EvalError> {
    let sequence = |scene, trajectory| {
        dataset.sequence(scene, trajectory).ok_or_else(|| {
            EvalError::Invalid(format!(
                "no generated sequence for scene {scene}, trajectory {trajectory}"
            ))
        })
    };
    let a = sequence(pair.scene_a, pair.trajectory)?;
    let b = sequence(pair.scene_b, pair.trajectory)?;
    let other = sequence(pair.scene_b, pair.other_trajectory)?;
    let pick = |frames: &[Image]| {
        indices
            .iter()
            .map(|&i| frames[i].clone())
            .collect::<Vec<_>>()
    };
    let mut contexts = vec![b.frames[indices[0]].clone()];
    let extra = crate::video::evenly_spaced(other.frames.len(), context_views.saturating_sub(1));
    contexts.extend(extra.into_iter().map(|i| other.frames[i].clone()));
    Ok(PairFrames {
        source: pick(&a.frames),
        ideal: pick(&b.frames),
        unrelated: pick(&other.frames),
        contexts,
    })
}

/// Mean squared difference of two images of one size.
fn mean_squared(a: &Image, b: &Image) -> f64 {
    let sum: f64 = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(x, y)| f64::from(x - y).powi(2))
        .sum();
    sum / a.pixels.len().max(1) as f64
}

/// Renders of `renders` that are closer to some frame of A's video than to every frame of B
/// the pair holds: copies of the source rather than views of the target scene.
fn copies_of_source(renders: &[Image], frames: &PairFrames) -> usize {
    let nearest = |render: &Image, pool: &mut dyn Iterator<Item = &Image>| {
        pool.map(|frame| mean_squared(render, frame))
            .fold(f64::INFINITY, f64::min)
    };
    renders
        .iter()
        .filter(|render| {
            let source = nearest(render, &mut frames.source.iter());
            let mut target_scene = frames
                .ideal
                .iter()
                .chain(&frames.unrelated)
                .chain(&frames.contexts);
            source < nearest(render, &mut target_scene)
        })
        .count()
}

/// TPS of one renderer and of the two calibrations.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TpsReport {
    /// Oracle used.
    pub oracle: String,
    /// Pairs evaluated.
    pub pairs: usize,
    /// Target frames per pair.
    pub frames_per_pair: usize,
    /// Pairs skipped because the oracle could not read A's frames.
    pub skipped: usize,
    /// Model renders the oracle could not read (their frame pairs count as wrong).
    pub failures: usize,
    /// Context views of B each transfer rendered from.
    #[serde(default)]
    pub context_views: usize,
    /// Transfers whose renders were mostly copies of the source video (scored as failed).
    #[serde(default)]
    pub copied_transfers: usize,
    /// Share of all renders closer to the source video than to the target scene.
    #[serde(default)]
    pub copy_share: f64,
    /// The model's transfers.
    pub model: CameraMetrics,
    /// B's true rendering along A's motion (perfect transfer).
    pub ideal_transfer: CameraMetrics,
    /// B along an unrelated motion (failed transfer).
    pub unrelated_trajectory: CameraMetrics,
}

/// How TPS is scored: the seed of the spreads (the frames and context views are the
/// [`PairFrames`]' own).
#[derive(Debug, Clone, Copy)]
pub struct TpsSettings {
    /// Seed of the bootstrap spreads.
    pub seed: u64,
}

/// The frames of every pair in `pairs`, `frames_per_pair` equally spaced targets each, with
/// `context_views` context views of B: everything TPS shows a renderer and scores against,
/// gathered before any model runs.
pub fn transfer_frames(
    dataset: &SyntheticDataset,
    pairs: &[TpsPair],
    frames_per_pair: usize,
    context_views: usize,
) -> Result<Vec<PairFrames>, EvalError> {
    let frames = dataset.sequences.first().map_or(0, |s| s.frames.len());
    let indices = target_frames(frames, frames_per_pair);
    pairs
        .iter()
        .map(|pair| pair_frames(dataset, pair, &indices, context_views))
        .collect()
}

/// Scores TPS: `renders[k]` holds one render of `transfers[k].contexts` along each of
/// `transfers[k].source`'s frames; the oracle reads the source, the renders and both
/// calibrations of every transfer.
pub fn score_transfers(
    transfers: &[PairFrames],
    renders: &[Vec<Image>],
    settings: TpsSettings,
    oracle: &dyn PoseOracle,
) -> TpsReport {
    let frames_per_pair = transfers.first().map_or(0, |t| t.source.len());
    let context_views = transfers.first().map_or(0, |t| t.contexts.len());
    let (mut model, mut ideal, mut unrelated) =
        (Scored::default(), Scored::default(), Scored::default());
    let (mut skipped, mut failures, mut copied_transfers, mut copied_renders, mut renders_seen) =
        (0, 0, 0, 0, 0);
    let pair_count = frames_per_pair * frames_per_pair.saturating_sub(1) / 2;
    for (index, (frames, renders)) in transfers.iter().zip(renders).enumerate() {
        let reference = match oracle.estimate(&frames.source) {
            Ok(poses) => poses,
            Err(error) => {
                tracing::warn!(pair = index, %error, "oracle cannot read the source; pair skipped");
                skipped += 1;
                continue;
            }
        };
        let score = |images: &[Image], into: &mut Scored| -> bool {
            match oracle.estimate(images) {
                Ok(poses) => {
                    into.groups.push(trajectory_errors(&reference, &poses));
                    into.trajectories.push(trajectory_error(&reference, &poses));
                    true
                }
                Err(error) => {
                    tracing::debug!(pair = index, %error, "oracle cannot read a transfer");
                    into.groups.push(vec![FAILED; pair_count]);
                    false
                }
            }
        };
        let copies = copies_of_source(renders, frames);
        (copied_renders, renders_seen) = (copied_renders + copies, renders_seen + renders.len());
        if 2 * copies > renders.len() {
            copied_transfers += 1;
            model.groups.push(vec![FAILED; pair_count]);
        } else {
            failures += usize::from(!score(renders, &mut model));
        }
        score(&frames.ideal, &mut ideal);
        score(&frames.unrelated, &mut unrelated);
    }
    TpsReport {
        oracle: oracle.name().to_string(),
        pairs: transfers.len(),
        frames_per_pair,
        skipped,
        failures,
        context_views,
        copied_transfers,
        copy_share: copied_renders as f64 / renders_seen.max(1) as f64,
        model: model.metrics(settings.seed),
        ideal_transfer: ideal.metrics(settings.seed),
        unrelated_trajectory: unrelated.metrics(settings.seed),
    }
}

/// Pair errors of every scored transfer, one group each (failures as the worst error), and the
/// trajectory errors of those the oracle could read.
#[derive(Default)]
struct Scored {
    groups: Vec<Vec<PairError>>,
    trajectories: Vec<TrajectoryError>,
}

impl Scored {
    fn metrics(&self, seed: u64) -> CameraMetrics {
        CameraMetrics::from_groups(&self.groups, seed).with_trajectory_errors(&self.trajectories)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::oracle::GroundTruthOracle;
    use data::scenes::SceneConfig;

    /// 3 scenes x 4 paths of 9 frames, their ground-truth oracle, and 6 transfers.
    fn three_scenes() -> (SyntheticDataset, GroundTruthOracle, Vec<TpsPair>) {
        let config = SceneConfig {
            image_size: 24,
            ..SceneConfig::default()
        };
        let dataset = SyntheticDataset::generate(2, 3, 4, 9, &config);
        let oracle = GroundTruthOracle::from_dataset(&dataset);
        (dataset, oracle, draw_pairs(1, 3, 4, 6).unwrap())
    }

    #[test]
    fn ground_truth_tps_is_perfect_for_itself_and_low_for_random_motion() {
        let (dataset, oracle, pairs) = three_scenes();
        assert!(
            pairs
                .iter()
                .all(|p| p.scene_a != p.scene_b && p.trajectory != p.other_trajectory)
        );
        assert_eq!(target_frames(9, 5), vec![0, 2, 4, 6, 8]);
        // A "renderer" that returns the ideal transfer: B's own frames along A's motion.
        let transfers = transfer_frames(&dataset, &pairs, 5, 1).unwrap();
        let renders: Vec<Vec<Image>> = transfers
            .iter()
            .map(|frames| {
                let (source, contexts) = (&frames.source, &frames.contexts);
                let pose_source = oracle.estimate(source).unwrap();
                dataset
                    .sequences
                    .iter()
                    .find(|s| s.poses[0] == pose_source[0] && s.frames[0] == contexts[0])
                    .map(|s| {
                        [0, 2, 4, 6, 8]
                            .iter()
                            .map(|&i| s.frames[i].clone())
                            .collect()
                    })
                    .unwrap_or_default()
            })
            .collect();
        let report = score_transfers(&transfers, &renders, TpsSettings { seed: 0 }, &oracle);
        assert_eq!(report.model.pairs, 6 * 10);
        let perfect = report.ideal_transfer.at(3).unwrap();
        assert_eq!(
            (perfect.rotation_accuracy, perfect.translation_accuracy),
            (1.0, 1.0)
        );
        assert!(perfect.auc > 0.99);
        assert_eq!(report.model.at(3).unwrap().auc, perfect.auc);
        let random = report.unrelated_trajectory.at(30).unwrap();
        assert!(random.auc < 0.5, "{:?}", report.unrelated_trajectory);
        assert!(random.auc < perfect.auc);
        assert_eq!((report.copied_transfers, report.copy_share), (0, 0.0));
        assert!(draw_pairs(0, 1, 4, 2).is_err());
    }

    #[test]
    fn a_renderer_that_returns_the_source_video_scores_no_transfer() {
        let (dataset, oracle, pairs) = three_scenes();
        let transfers = transfer_frames(&dataset, &pairs, 5, 2).unwrap();
        assert!(transfers.iter().all(|frames| frames.contexts.len() == 2));
        let renders: Vec<Vec<Image>> = transfers.iter().map(|f| f.source.clone()).collect();
        let report = score_transfers(&transfers, &renders, TpsSettings { seed: 0 }, &oracle);
        assert_eq!(report.copied_transfers, 6);
        assert_eq!(report.copy_share, 1.0);
        for scores in &report.model.thresholds {
            assert_eq!(
                (
                    scores.rotation_accuracy,
                    scores.translation_accuracy,
                    scores.auc
                ),
                (0.0, 0.0, 0.0),
                "{scores:?}"
            );
        }
        // The oracle alone would have called the copy perfect.
        assert!(report.ideal_transfer.at(30).unwrap().auc > 0.99);
    }
}
