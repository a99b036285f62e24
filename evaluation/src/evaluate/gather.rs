//! The evaluation's first phase: everything the models are shown and scored against, gathered
//! once before any model runs. The held-out generated scenes, the sequences reconstructed and
//! which of their frames are context views, the frames of every TPS transfer for each number
//! of context views a checkpoint renders from, the scenes the probe trains and is tested on,
//! the real test sequences, the pose oracle and LPIPS.

use std::collections::BTreeMap;

use burn::tensor::Device;
use data::Image;
use data::Split;
use data::scenes::SceneConfig;
use data::synthetic::SyntheticDataset;
use settings::evaluation::{EvaluationSpec, OracleSpec};
use trainer_core::XFactorConfig;
use trainer_core::lpips::Lpips;

use crate::error::EvalError;
use crate::inference::proximity_permutation;
use crate::oracle::{
    ClassicalOracle, ClassicalSettings, ExternalOracle, GroundTruthOracle, PoseOracle,
};
use crate::sequences::{ProtocolSet, load_protocol};
use crate::tps::{PairFrames, draw_pairs, transfer_frames};
use crate::video::evenly_spaced;

/// Everything one evaluation scores its checkpoints on.
pub(super) struct Gathered<'a> {
    /// The evaluation's settings.
    pub(super) spec: &'a EvaluationSpec,
    /// The held-out generated scenes, every path in every scene.
    pub(super) dataset: SyntheticDataset,
    /// The generated sequences reconstructed ([`reconstruction_set`]).
    pub(super) reconstruction: Vec<usize>,
    /// Real test sequences under E-RayZer's protocol, one set per dataset.
    pub(super) protocol_sets: Vec<ProtocolSet>,
    /// The frames of every transfer, by the number of context views of B.
    pub(super) transfers: BTreeMap<usize, Vec<PairFrames>>,
    /// The first scene the probe is tested on: the last `probe.test_scenes` are held out of
    /// its training.
    pub(super) first_probe_test_scene: u64,
    /// The pose oracle of TPS.
    pub(super) oracle: Box<dyn PoseOracle>,
    /// LPIPS, when the spec names weights.
    pub(super) lpips: Option<Lpips>,
    /// The device the models run on.
    pub(super) device: Device,
}

impl Gathered<'_> {
    /// The frames of each generated sequence reconstructed, in gathered order: what the
    /// models render, the baselines copy, the scores compare against and the sheets show.
    pub(super) fn reconstructed_frames(&self) -> impl Iterator<Item = &[Image]> {
        self.reconstruction
            .iter()
            .map(|&index| self.dataset.sequences[index].frames.as_slice())
    }

    /// The frames of every transfer with `views` context views (gathered for every number of
    /// views [`gather`] was asked for).
    pub(super) fn transfers(&self, views: usize) -> Result<&[PairFrames], EvalError> {
        self.transfers
            .get(&views)
            .map(Vec::as_slice)
            .ok_or_else(|| EvalError::Invalid(format!("no transfers gathered for {views} views")))
    }
}

/// Gathers what checkpoints of `config`'s image size are scored on, with TPS frames for each
/// of `views` (context views per checkpoint).
pub(super) fn gather<'a>(
    spec: &'a EvaluationSpec,
    config: &XFactorConfig,
    views: &[usize],
    device: &Device,
) -> Result<Gathered<'a>, EvalError> {
    let scene_config = SceneConfig {
        image_size: config.image_size,
        ..SceneConfig::default()
    };
    let dataset = {
        let _span = tracing::info_span!(
            "generate",
            scenes = spec.scenes,
            trajectories = spec.trajectories
        )
        .entered();
        SyntheticDataset::generate_split(
            spec.seed,
            Split::Test,
            spec.scenes,
            spec.trajectories,
            spec.frames,
            &scene_config,
        )
    };
    let pairs = draw_pairs(spec.seed, spec.scenes, spec.trajectories, spec.tps_pairs)?;
    let transfers = views
        .iter()
        .map(|&v| Ok((v, transfer_frames(&dataset, &pairs, spec.tps_frames, v)?)))
        .collect::<Result<BTreeMap<_, _>, EvalError>>()?;
    let protocol_sets = spec
        .sequences
        .iter()
        .map(|protocol| {
            let _span = tracing::info_span!("load_sequences", dataset = ?protocol.kind).entered();
            load_protocol(protocol, config.image_size)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let lpips =
        match &spec.lpips_weights {
            Some(path) => Some(Lpips::from_file(path, device).map_err(|e| {
                EvalError::Invalid(format!("LPIPS weights {}: {e}", path.display()))
            })?),
            None => None,
        };
    Ok(Gathered {
        spec,
        reconstruction: reconstruction_set(&dataset, spec.reconstruction_sequences),
        oracle: oracle_for(&spec.oracle, &dataset, &scene_config),
        dataset,
        protocol_sets,
        transfers,
        first_probe_test_scene: spec.scenes.saturating_sub(spec.probe.test_scenes),
        lpips,
        device: device.clone(),
    })
}

fn oracle_for(
    spec: &OracleSpec,
    dataset: &SyntheticDataset,
    scene: &SceneConfig,
) -> Box<dyn PoseOracle> {
    match spec {
        OracleSpec::GroundTruth { subdivisions: 1 } => {
            Box::new(GroundTruthOracle::from_dataset(dataset))
        }
        OracleSpec::GroundTruth { subdivisions } => {
            let _span = tracing::info_span!("oracle_views", subdivisions).entered();
            Box::new(GroundTruthOracle::between_frames(
                dataset,
                *subdivisions as usize,
                scene,
            ))
        }
        OracleSpec::Classical => Box::new(ClassicalOracle::new(ClassicalSettings {
            fov_degrees: scene.fov_degrees,
            ..ClassicalSettings::default()
        })),
        OracleSpec::External { program, args } => Box::new(ExternalOracle::new(program, args)),
    }
}

/// Which frames of a `frames`-frame sequence are context views (ordered middlest-first, as the
/// release's multi-view inference orders them; the first is the reference) and which are
/// rendered. One context is frame 0; more are spread evenly with the first and last included.
pub(super) fn layout(frames: usize, contexts: usize) -> (Vec<usize>, Vec<usize>) {
    let chosen = if contexts <= 1 {
        vec![0]
    } else {
        evenly_spaced(frames, contexts.min(frames.saturating_sub(1)))
    };
    let positions: Vec<i64> = chosen.iter().map(|&i| i as i64).collect();
    let ordered = proximity_permutation(&positions)
        .into_iter()
        .map(|k| chosen[k])
        .collect();
    let targets = (0..frames).filter(|i| !chosen.contains(i)).collect();
    (ordered, targets)
}

/// The target frames of `frames` under [`layout`] with `contexts` context views.
pub(super) fn targets_of(frames: &[Image], contexts: usize) -> Vec<Image> {
    let (_, targets) = layout(frames.len(), contexts);
    targets.iter().map(|&t| frames[t].clone()).collect()
}

/// The sequences reconstructed, as indices into `dataset.sequences`: at least one from every
/// scene (scene-major round robin, each scene's paths taken in turn), `count` in all when that
/// is more.
pub(super) fn reconstruction_set(dataset: &SyntheticDataset, count: usize) -> Vec<usize> {
    let scenes = dataset
        .sequences
        .iter()
        .map(|s| s.scene)
        .max()
        .map_or(0, |m| m + 1);
    let trajectories = dataset.sequences.len() as u64 / scenes.max(1);
    (0..(count as u64).max(scenes))
        .filter_map(|k| {
            let scene = k % scenes.max(1);
            let trajectory = (k + k / scenes.max(1)) % trajectories.max(1);
            dataset
                .sequences
                .iter()
                .position(|s| s.scene == scene && s.trajectory == trajectory)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contexts_are_spread_ordered_middlest_first_and_never_targets() {
        assert_eq!(layout(8, 1), (vec![0], (1..8).collect()));
        assert_eq!(layout(8, 2), (vec![0, 7], (1..7).collect()));
        assert_eq!(layout(9, 3), (vec![4, 0, 8], vec![1, 2, 3, 5, 6, 7]));
        let (contexts, targets) = layout(3, 5);
        assert_eq!((contexts.len(), targets.len()), (2, 1));
    }

    #[test]
    fn every_scene_is_reconstructed() {
        let config = SceneConfig {
            image_size: 16,
            ..SceneConfig::default()
        };
        let dataset = SyntheticDataset::generate(1, 4, 3, 4, &config);
        let scene_of = |set: &[usize]| -> Vec<(u64, u64)> {
            set.iter()
                .map(|&i| (dataset.sequences[i].scene, dataset.sequences[i].trajectory))
                .collect()
        };
        let set = reconstruction_set(&dataset, 2);
        let scenes: Vec<u64> = scene_of(&set).iter().map(|s| s.0).collect();
        assert_eq!(scenes, [0, 1, 2, 3]);
        let set = reconstruction_set(&dataset, 8);
        let pairs: std::collections::BTreeSet<(u64, u64)> = scene_of(&set).into_iter().collect();
        assert_eq!(pairs.len(), 8, "no sequence twice: {pairs:?}");
    }
}
