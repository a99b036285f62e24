//! The evaluation's third phase: what [`super::infer`] produced, scored against what
//! [`super::gather`] gathered. Reconstruction by PSNR, SSIM and LPIPS; transfers by the pose
//! oracle; PoseEnc's features by the pose probe trained on them; each with its bootstrap spread.

use burn::tensor::{Tensor, TensorData};
use data::Image;
use data::scenes::CameraPose;

use super::gather::{Gathered, targets_of};
use super::infer::{BaselineOutputs, ModelOutputs};
use super::{Baselines, ModelReport};
use crate::error::EvalError;
use crate::metrics::{ReconstructionReport, bootstrap_spread, psnr, ssim};
use crate::oracle::OracleError;
use crate::probe::{ProbePath, ProbeSequence, no_motion, run_probe};
use crate::sequences::SequenceReport;
use crate::tps::{TpsSettings, score_transfers};

/// One model's numbers, and the poses its figures draw.
pub(super) struct Scored {
    /// The numbers.
    pub(super) report: ModelReport,
    /// Each held-out probe sequence's true and predicted path.
    pub(super) probe_paths: Vec<ProbePath>,
    /// The oracle's reading of the first transfer, when it could read the source video.
    pub(super) transfer_paths: Option<TransferPaths>,
}

/// The oracle's camera paths of the first transfer's source video and of its renders.
pub(super) struct TransferPaths {
    /// The source video's poses.
    pub(super) source: Vec<CameraPose>,
    /// The renders' poses, or why the oracle could not read them.
    pub(super) renders: Result<Vec<CameraPose>, OracleError>,
}

/// Scores one model's outputs with `views` context views.
pub(super) fn score_model(
    outputs: &ModelOutputs,
    views: usize,
    gathered: &Gathered<'_>,
) -> Result<Scored, EvalError> {
    let reconstruction = {
        let _span = tracing::info_span!("reconstruction").entered();
        let frames = gathered.reconstructed_frames();
        reconstruction_report(frames, &outputs.reconstruction, views, gathered)?
    };
    let sequences = score_sequences(outputs, gathered)?;
    let transfers = gathered.transfers(views)?;
    let settings = TpsSettings {
        seed: gathered.spec.seed,
    };
    let tps = {
        let _span = tracing::info_span!("tps", oracle = gathered.oracle.name()).entered();
        score_transfers(
            transfers,
            &outputs.transfers,
            settings,
            gathered.oracle.as_ref(),
        )
    };
    let transfer_paths =
        transfers
            .first()
            .zip(outputs.transfers.first())
            .and_then(|(frames, renders)| {
                let source = gathered.oracle.estimate(&frames.source).ok()?;
                let renders = gathered.oracle.estimate(renders);
                Some(TransferPaths { source, renders })
            });
    let (probe, probe_paths) = {
        let _span = tracing::info_span!("probe").entered();
        let (train, test) = probe_sequences(outputs, gathered);
        let spec = gathered.spec;
        let device = gathered.device.clone().autodiff();
        run_probe(&train, &test, &spec.probe, spec.seed, &device)?
    };
    Ok(Scored {
        report: ModelReport {
            reconstruction,
            tps,
            probe,
            sequences,
        },
        probe_paths,
        transfer_paths,
    })
}

/// The reconstruction of each protocol's real test sequences.
fn score_sequences(
    outputs: &ModelOutputs,
    gathered: &Gathered<'_>,
) -> Result<Vec<SequenceReport>, EvalError> {
    gathered
        .protocol_sets
        .iter()
        .zip(&outputs.sequences)
        .map(|(set, renders)| {
            let frames = set.sequences.iter().map(|s| s.frames.as_slice());
            Ok(SequenceReport {
                kind: set.protocol.kind,
                uri: set.protocol.uri.clone(),
                length: set.protocol.length,
                sequences: set.sequences.len(),
                skipped_short: set.skipped_short,
                reconstruction: reconstruction_report(frames, renders, 1, gathered)?,
            })
        })
        .collect()
}

/// PoseEnc's features of every generated sequence with its poses, split into the probe's
/// training sequences and the held-out ones it is tested on.
fn probe_sequences(
    outputs: &ModelOutputs,
    gathered: &Gathered<'_>,
) -> (Vec<ProbeSequence>, Vec<ProbeSequence>) {
    let (mut train, mut test) = (Vec::new(), Vec::new());
    for (sequence, latents) in gathered
        .dataset
        .sequences
        .iter()
        .zip(&outputs.probe_features)
    {
        let item = ProbeSequence {
            latents: latents.clone(),
            poses: sequence.poses.clone(),
        };
        if sequence.scene < gathered.first_probe_test_scene {
            train.push(item);
        } else {
            test.push(item);
        }
    }
    (train, test)
}

/// Scores the pose-free baselines on the frames and transfers the models are scored on.
pub(super) fn score_baselines(
    outputs: &BaselineOutputs,
    views: usize,
    gathered: &Gathered<'_>,
) -> Result<Baselines, EvalError> {
    let _span = tracing::info_span!("baselines", views).entered();
    let frames = || gathered.reconstructed_frames();
    let settings = TpsSettings {
        seed: gathered.spec.seed,
    };
    let still = score_transfers(
        gathered.transfers(views)?,
        &outputs.still,
        settings,
        gathered.oracle.as_ref(),
    );
    let held_out: Vec<Vec<CameraPose>> = gathered
        .dataset
        .sequences
        .iter()
        .filter(|s| s.scene >= gathered.first_probe_test_scene)
        .map(|s| s.poses.clone())
        .collect();
    Ok(Baselines {
        copy: reconstruction_report(frames(), &outputs.copy, views, gathered)?,
        mean_colour: reconstruction_report(frames(), &outputs.mean_colour, views, gathered)?,
        tps_no_motion: still.model,
        probe_no_motion: no_motion(&held_out, gathered.spec.seed),
    })
}

/// One sequence's per-frame scores.
#[derive(Default)]
struct SequenceScores {
    psnr: Vec<f64>,
    ssim: Vec<f64>,
    lpips: Vec<f64>,
}

/// The mean of one measure over every frame of `sample`, which the spread resamples by sequence
/// (frames of one sequence are not independent).
fn pooled_mean(sample: &[&SequenceScores], measure: fn(&SequenceScores) -> &[f64]) -> f64 {
    let values: Vec<f64> = sample
        .iter()
        .flat_map(|s| measure(s).iter().copied())
        .collect();
    values.iter().sum::<f64>() / values.len().max(1) as f64
}

/// Scores `renders[k]` against the targets of `sequences[k]` (with `views` context views).
fn reconstruction_report<'s>(
    sequences: impl Iterator<Item = &'s [Image]>,
    renders: &[Vec<Image>],
    views: usize,
    gathered: &Gathered<'_>,
) -> Result<ReconstructionReport, EvalError> {
    let mut scores = Vec::new();
    for (frames, renders) in sequences.zip(renders) {
        let truth = targets_of(frames, views);
        if truth.is_empty() {
            continue;
        }
        let mut sequence = SequenceScores::default();
        for (render, target) in renders.iter().zip(&truth) {
            sequence.psnr.push(psnr(render, target)?);
            sequence.ssim.push(ssim(render, target)?);
        }
        sequence.lpips = lpips_distances(renders, &truth, gathered)?;
        scores.push(sequence);
    }
    let all: Vec<&SequenceScores> = scores.iter().collect();
    let seed = gathered.spec.seed;
    let lpips = pooled_mean(&all, |s| &s.lpips);
    Ok(ReconstructionReport {
        frames: scores.iter().map(|s| s.psnr.len()).sum(),
        psnr: pooled_mean(&all, |s| &s.psnr),
        ssim: pooled_mean(&all, |s| &s.ssim),
        lpips: scores.iter().any(|s| !s.lpips.is_empty()).then_some(lpips),
        psnr_spread: bootstrap_spread(&scores, seed, |s| pooled_mean(s, |s| &s.psnr)),
        ssim_spread: bootstrap_spread(&scores, seed, |s| pooled_mean(s, |s| &s.ssim)),
    })
}

/// LPIPS distances of `renders` to `targets`, one per frame (none without LPIPS weights).
fn lpips_distances(
    renders: &[Image],
    targets: &[Image],
    gathered: &Gathered<'_>,
) -> Result<Vec<f64>, EvalError> {
    let Some(lpips) = &gathered.lpips else {
        return Ok(Vec::new());
    };
    let upload = |images: &[Image]| {
        let values: Vec<f32> = images
            .iter()
            .flat_map(|i| i.pixels.iter().copied())
            .collect();
        let (height, width) = (images[0].height, images[0].width);
        Tensor::<4>::from_data(
            TensorData::new(values, [images.len(), height, width, 3]),
            &gathered.device,
        )
    };
    let distances = lpips
        .distance(upload(renders), upload(targets))
        .try_into_vec_as::<f32>()
        .map_err(|e| EvalError::Tensor(format!("{e:?}")))?;
    Ok(distances.iter().map(|&d| f64::from(d)).collect())
}
