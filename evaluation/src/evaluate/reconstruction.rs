//! Autoencoding: the frames of a sequence that are not context views, rendered from the context
//! views with the poses PoseEnc reads from the sequence itself, by the model or by a baseline
//! that knows no pose at all (copy the nearest context view, paint the contexts' mean colour),
//! scored on exactly the same frames.

use burn::tensor::{Tensor, TensorData};
use data::Image;
use data::synthetic::{SyntheticDataset, SyntheticSequence};
use trainer_core::XFactor;

use super::{Context, GRID_PAIRS};
use crate::error::EvalError;
use crate::inference::{pose_latents, proximity_permutation, render_targets};
use crate::metrics::{ReconstructionReport, bootstrap_spread, psnr, ssim};
use crate::video::evenly_spaced;

/// What renders the targets.
#[derive(Clone, Copy)]
pub(super) enum Renderer<'m> {
    /// The model: Render from the context views along PoseEnc's latents.
    Model(&'m XFactor),
    /// Every target is the context view nearest to it in the sequence.
    CopyNearestContext,
    /// Every target is one colour: the context views' mean.
    MeanColour,
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

/// The sequences reconstructed: at least one from every scene (scene-major round robin, each
/// scene's paths taken in turn), `count` in all when that is more.
pub(super) fn reconstruction_set(
    dataset: &SyntheticDataset,
    count: usize,
) -> Vec<&SyntheticSequence> {
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
            dataset.sequence(scene, trajectory)
        })
        .collect()
}

/// Renders the targets of `frames` (indices of [`layout`]) with `renderer`.
fn render(
    renderer: Renderer<'_>,
    frames: &[Image],
    contexts: &[usize],
    targets: &[usize],
    context: &Context<'_>,
) -> Result<Vec<Image>, EvalError> {
    match renderer {
        Renderer::Model(model) => {
            let latents = pose_latents(model, &frames[contexts[0]], frames, &context.device)?;
            let pick = |indices: &[usize]| indices.iter().map(|&i| latents[i].clone()).collect();
            let views: Vec<Image> = contexts.iter().map(|&i| frames[i].clone()).collect();
            let context_latents: Vec<_> = pick(contexts);
            let target_latents: Vec<_> = pick(targets);
            render_targets(
                model,
                &views,
                &context_latents,
                &target_latents,
                &context.device,
            )
        }
        Renderer::CopyNearestContext => Ok(targets
            .iter()
            .map(|&t| {
                let nearest = contexts.iter().min_by_key(|&&c| c.abs_diff(t)).copied();
                frames[nearest.unwrap_or(0)].clone()
            })
            .collect()),
        Renderer::MeanColour => {
            let mut sum = [0.0f64; 3];
            let mut count = 0usize;
            for &c in contexts {
                for pixel in frames[c].pixels.chunks_exact(3) {
                    (0..3).for_each(|k| sum[k] += f64::from(pixel[k]));
                    count += 1;
                }
            }
            let mean = sum.map(|s| (s / count.max(1) as f64) as f32);
            let first = &frames[contexts[0]];
            let flat = Image {
                height: first.height,
                width: first.width,
                pixels: mean.repeat(first.height * first.width),
            };
            Ok(vec![flat; targets.len()])
        }
    }
}

/// LPIPS distances of `renders` to `targets`, one per frame.
fn lpips_distances(
    renders: &[Image],
    targets: &[Image],
    context: &Context<'_>,
) -> Result<Vec<f64>, EvalError> {
    let Some(lpips) = &context.lpips else {
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
            &context.device,
        )
    };
    let distances = lpips
        .distance(upload(renders), upload(targets))
        .try_into_vec_as::<f32>()
        .map_err(|e| EvalError::Tensor(format!("{e:?}")))?;
    Ok(distances.iter().map(|&d| f64::from(d)).collect())
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

/// Reconstructs every sequence with `contexts` context views by `renderer`; also returns the
/// render grid (a sequence's frames above its renders, context views in place) of the first
/// few.
pub(super) fn reconstruct<'s>(
    renderer: Renderer<'_>,
    sequences: impl Iterator<Item = &'s [Image]>,
    contexts: usize,
    context: &Context<'_>,
) -> Result<(ReconstructionReport, Vec<Vec<Image>>), EvalError> {
    let mut scores = Vec::new();
    let mut grid = Vec::new();
    for frames in sequences {
        let (views, targets) = layout(frames.len(), contexts);
        if targets.is_empty() {
            continue;
        }
        let renders = render(renderer, frames, &views, &targets, context)?;
        let truth: Vec<Image> = targets.iter().map(|&t| frames[t].clone()).collect();
        let mut sequence = SequenceScores::default();
        for (render, target) in renders.iter().zip(&truth) {
            sequence.psnr.push(psnr(render, target)?);
            sequence.ssim.push(ssim(render, target)?);
        }
        sequence.lpips = lpips_distances(&renders, &truth, context)?;
        scores.push(sequence);
        if grid.len() < 2 * GRID_PAIRS {
            let mut rendered = frames.to_vec();
            for (&t, image) in targets.iter().zip(renders) {
                rendered[t] = image;
            }
            grid.push(frames.to_vec());
            grid.push(rendered);
        }
    }
    let all: Vec<&SequenceScores> = scores.iter().collect();
    let seed = context.spec.seed;
    let lpips = pooled_mean(&all, |s| &s.lpips);
    Ok((
        ReconstructionReport {
            frames: scores.iter().map(|s| s.psnr.len()).sum(),
            psnr: pooled_mean(&all, |s| &s.psnr),
            ssim: pooled_mean(&all, |s| &s.ssim),
            lpips: scores.iter().any(|s| !s.lpips.is_empty()).then_some(lpips),
            psnr_spread: bootstrap_spread(&scores, seed, |s| pooled_mean(s, |s| &s.psnr)),
            ssim_spread: bootstrap_spread(&scores, seed, |s| pooled_mean(s, |s| &s.ssim)),
        },
        grid,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use data::scenes::SceneConfig;

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
        let set = reconstruction_set(&dataset, 2);
        let scenes: Vec<u64> = set.iter().map(|s| s.scene).collect();
        assert_eq!(scenes, [0, 1, 2, 3]);
        let set = reconstruction_set(&dataset, 8);
        let pairs: std::collections::BTreeSet<(u64, u64)> =
            set.iter().map(|s| (s.scene, s.trajectory)).collect();
        assert_eq!(pairs.len(), 8, "no sequence twice: {pairs:?}");
    }
}
