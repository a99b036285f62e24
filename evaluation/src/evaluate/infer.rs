//! The evaluation's second phase: every model, and every baseline that knows no pose, run on
//! what [`super::gather`] gathered. Renders and features only; nothing is scored here.

use data::Image;
use trainer_core::XFactor;

use super::gather::{Gathered, layout};
use crate::error::EvalError;
use crate::inference::{Latent, pose_latents, probe_features, render_along, render_targets};

/// What one model produced.
pub(super) struct ModelOutputs {
    /// The target renders of each reconstructed generated sequence, in gathered order.
    pub(super) reconstruction: Vec<Vec<Image>>,
    /// The target renders of each real test sequence (one context view), by protocol set.
    pub(super) sequences: Vec<Vec<Vec<Image>>>,
    /// One render per source frame of each TPS transfer, in gathered order.
    pub(super) transfers: Vec<Vec<Image>>,
    /// PoseEnc's probe input of every frame of every generated sequence against its first.
    pub(super) probe_features: Vec<Vec<Latent>>,
}

/// What the pose-free baselines produce on the same frames and transfers.
pub(super) struct BaselineOutputs {
    /// Each target is the context view nearest to it in its sequence.
    pub(super) copy: Vec<Vec<Image>>,
    /// Each target is the context views' mean colour.
    pub(super) mean_colour: Vec<Vec<Image>>,
    /// Each transfer's renders are B's reference view, unmoved.
    pub(super) still: Vec<Vec<Image>>,
}

/// Runs `model` with `views` context views on everything gathered.
pub(super) fn run_model(
    model: &XFactor,
    views: usize,
    gathered: &Gathered<'_>,
) -> Result<ModelOutputs, EvalError> {
    let device = &gathered.device;
    let reconstruction = {
        let _span = tracing::info_span!("reconstruction_renders", views).entered();
        gathered
            .reconstructed_frames()
            .map(|frames| render_sequence(model, frames, views, gathered))
            .collect::<Result<Vec<_>, _>>()?
    };
    let sequences = gathered
        .protocol_sets
        .iter()
        .map(|set| {
            let _span =
                tracing::info_span!("sequence_renders", dataset = ?set.protocol.kind).entered();
            set.sequences
                .iter()
                .map(|sequence| render_sequence(model, &sequence.frames, 1, gathered))
                .collect::<Result<Vec<_>, _>>()
        })
        .collect::<Result<Vec<_>, _>>()?;
    let transfers = {
        let _span = tracing::info_span!("transfer_renders", views).entered();
        gathered
            .transfers(views)?
            .iter()
            .map(|frames| render_along(model, &frames.source, 0, &frames.contexts, device))
            .collect::<Result<Vec<_>, _>>()?
    };
    let probe_features = {
        let _span = tracing::info_span!("probe_features").entered();
        gathered
            .dataset
            .sequences
            .iter()
            .map(|s| probe_features(model, &s.frames[0], &s.frames, device))
            .collect::<Result<Vec<_>, _>>()?
    };
    Ok(ModelOutputs {
        reconstruction,
        sequences,
        transfers,
        probe_features,
    })
}

/// The targets of `frames` (under [`layout`] with `views` context views) rendered by `model`
/// from the context views, along the poses PoseEnc reads from the sequence itself.
fn render_sequence(
    model: &XFactor,
    frames: &[Image],
    views: usize,
    gathered: &Gathered<'_>,
) -> Result<Vec<Image>, EvalError> {
    let (contexts, targets) = layout(frames.len(), views);
    if targets.is_empty() {
        return Ok(Vec::new());
    }
    let device = &gathered.device;
    let latents = pose_latents(model, &frames[contexts[0]], frames, device)?;
    let pick = |indices: &[usize]| -> Vec<Latent> {
        indices.iter().map(|&i| latents[i].clone()).collect()
    };
    let context_views: Vec<Image> = contexts.iter().map(|&i| frames[i].clone()).collect();
    render_targets(
        model,
        &context_views,
        &pick(&contexts),
        &pick(&targets),
        device,
    )
}

/// The pose-free baselines with `views` context views.
pub(super) fn run_baselines(
    views: usize,
    gathered: &Gathered<'_>,
) -> Result<BaselineOutputs, EvalError> {
    let sequences: Vec<&[Image]> = gathered.reconstructed_frames().collect();
    let copy = sequences
        .iter()
        .map(|frames| copy_nearest_context(frames, views))
        .collect();
    let mean_colour = sequences
        .iter()
        .map(|frames| mean_colour(frames, views))
        .collect();
    let still = gathered
        .transfers(views)?
        .iter()
        .map(|frames| vec![frames.contexts[0].clone(); frames.source.len()])
        .collect();
    Ok(BaselineOutputs {
        copy,
        mean_colour,
        still,
    })
}

/// Every target is the context view nearest to it in the sequence.
fn copy_nearest_context(frames: &[Image], views: usize) -> Vec<Image> {
    let (contexts, targets) = layout(frames.len(), views);
    targets
        .iter()
        .map(|&t| {
            let nearest = contexts.iter().min_by_key(|&&c| c.abs_diff(t)).copied();
            frames[nearest.unwrap_or(0)].clone()
        })
        .collect()
}

/// Every target is one colour: the context views' mean.
fn mean_colour(frames: &[Image], views: usize) -> Vec<Image> {
    let (contexts, targets) = layout(frames.len(), views);
    if targets.is_empty() {
        return Vec::new();
    }
    let mut sum = [0.0f64; 3];
    let mut count = 0usize;
    for &c in &contexts {
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
    vec![flat; targets.len()]
}
