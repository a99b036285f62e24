//! The two model calls evaluation needs, batched on host images: pose latents of frames
//! relative to a reference frame (PoseEnc on pairs), and renders of target latents from
//! context views (Render).

use burn::tensor::{Device, Tensor, TensorData};
use data::Image;
use trainer_core::XFactor;
use trainer_core::model::PoseLatents;

use crate::error::EvalError;

/// Pairs or renders per forward pass: bounds memory on large models.
const CHUNK: usize = 16;

/// One latent vector per frame.
pub type Latent = Vec<f32>;

fn upload(images: &[&Image], device: &Device) -> Result<Tensor<4>, EvalError> {
    let first = images
        .first()
        .ok_or_else(|| EvalError::Invalid("no images to upload".to_string()))?;
    if images
        .iter()
        .any(|i| (i.height, i.width) != (first.height, first.width))
    {
        return Err(EvalError::Invalid(
            "images of one batch differ in size".to_string(),
        ));
    }
    let values: Vec<f32> = images
        .iter()
        .flat_map(|i| i.pixels.iter().copied())
        .collect();
    Ok(Tensor::from_data(
        TensorData::new(values, [images.len(), first.height, first.width, 3]),
        device,
    ))
}

fn download(tensor: Tensor<4>) -> Result<Vec<Image>, EvalError> {
    let [b, height, width, _] = tensor.dims();
    let values = tensor
        .try_into_vec_as::<f32>()
        .map_err(|e| EvalError::Tensor(format!("{e:?}")))?;
    Ok(values
        .chunks_exact(height * width * 3)
        .take(b)
        .map(|pixels| Image {
            height,
            width,
            pixels: pixels.to_vec(),
        })
        .collect())
}

/// The pose latent of each of `frames` relative to `reference` (PoseEnc on the pair
/// `(reference, frame)`, unmasked): the reference itself maps to zero.
pub fn pose_latents(
    model: &XFactor,
    reference: &Image,
    frames: &[Image],
    device: &Device,
) -> Result<Vec<Latent>, EvalError> {
    per_pair(model, reference, frames, device, |model, pairs| {
        model.pose_enc.forward(pairs)
    })
}

/// PoseEnc's probe input `concat(z0, z)` (`2C` wide) for each pair `(reference, frame)`,
/// unmasked: what the release's pose probe reads.
pub fn probe_features(
    model: &XFactor,
    reference: &Image,
    frames: &[Image],
    device: &Device,
) -> Result<Vec<Latent>, EvalError> {
    per_pair(model, reference, frames, device, |model, pairs| {
        model.pose_enc.probe_features(pairs)
    })
}

/// `encode` of the pairs `(reference, frame)` (`[B, 2, H, W, 3]` to `[B, 2, width]`), in
/// chunks; the second slot of each pair, the frame's, as one vector per frame.
fn per_pair(
    model: &XFactor,
    reference: &Image,
    frames: &[Image],
    device: &Device,
    encode: impl Fn(&XFactor, Tensor<5>) -> Tensor<3>,
) -> Result<Vec<Latent>, EvalError> {
    let mut out = Vec::with_capacity(frames.len());
    for chunk in frames.chunks(CHUNK) {
        let references = upload(&vec![reference; chunk.len()], device)?;
        let targets = upload(&chunk.iter().collect::<Vec<_>>(), device)?;
        let encoded = encode(model, Tensor::stack(vec![references, targets], 1));
        let [b, _, width] = encoded.dims();
        let values = encoded
            .narrow(1, 1, 1)
            .reshape([b * width])
            .try_into_vec_as::<f32>()
            .map_err(|e| EvalError::Tensor(format!("{e:?}")))?;
        out.extend(values.chunks_exact(width).map(<[f32]>::to_vec));
    }
    Ok(out)
}

/// Renders one image per target latent from the context views, whose own latents are given
/// (the first context is the reference, latent zero). One context view is the stereo
/// (monocular-render) model; several are the multi-view model.
pub fn render_targets(
    model: &XFactor,
    contexts: &[Image],
    context_latents: &[Latent],
    targets: &[Latent],
    device: &Device,
) -> Result<Vec<Image>, EvalError> {
    if contexts.is_empty() || contexts.len() != context_latents.len() {
        return Err(EvalError::Invalid(format!(
            "{} context views with {} latents",
            contexts.len(),
            context_latents.len()
        )));
    }
    let cp = context_latents[0].len();
    let views = contexts.len();
    let context = upload(&contexts.iter().collect::<Vec<_>>(), device)?;
    let [_, height, width, _] = context.dims();
    let mut renders = Vec::with_capacity(targets.len());
    for chunk in targets.chunks(CHUNK) {
        let b = chunk.len();
        let batch = context
            .clone()
            .reshape([1, views, height, width, 3])
            .expand([b, views, height, width, 3]);
        let mut poses = Vec::with_capacity(b * (views + 1) * cp);
        for target in chunk {
            if target.len() != cp {
                return Err(EvalError::Invalid(format!(
                    "pose latent of size {} for a model with Cp = {cp}",
                    target.len()
                )));
            }
            context_latents
                .iter()
                .for_each(|l| poses.extend_from_slice(l));
            poses.extend_from_slice(target);
        }
        let poses = Tensor::<3>::from_data(TensorData::new(poses, [b, views + 1, cp]), device);
        let images = model
            .render
            .forward(batch, PoseLatents::Single(poses), None);
        renders.extend(download(images)?);
    }
    Ok(renders)
}

/// The release's `proximity_permutation`: positions of `frame_indices` sorted (stably) by
/// `max(|f - first|, |f - last|)`, where `first` and `last` are the first and last entries, so
/// the middlest frame leads and the ends come last.
pub fn proximity_permutation(frame_indices: &[i64]) -> Vec<usize> {
    let (Some(&first), Some(&last)) = (frame_indices.first(), frame_indices.last()) else {
        return Vec::new();
    };
    let mut order: Vec<usize> = (0..frame_indices.len()).collect();
    order.sort_by_key(|&i| {
        (frame_indices[i] - first)
            .abs()
            .max((frame_indices[i] - last).abs())
    });
    order
}

/// Renders `scene` along the motion of `trajectory` relative to `trajectory[reference]`: the
/// transfer XFactor exists for. A one-frame scene is the stereo case; a multi-frame scene gives
/// every frame as a context view, ordered middlest-first as the release's multi-view inference
/// does (the middlest frame is the reference).
pub fn transfer(
    model: &XFactor,
    trajectory: &[Image],
    reference: usize,
    scene: &[Image],
    device: &Device,
) -> Result<Vec<Image>, EvalError> {
    let positions: Vec<i64> = (0..scene.len() as i64).collect();
    let scene: Vec<Image> = proximity_permutation(&positions)
        .into_iter()
        .map(|i| scene[i].clone())
        .collect();
    render_along(model, trajectory, reference, &scene, device)
}

/// Renders the context views `scene` (in the order given; the first is the reference, seen from
/// where `trajectory[reference]` was taken) along `trajectory`'s motion.
pub fn render_along(
    model: &XFactor,
    trajectory: &[Image],
    reference: usize,
    scene: &[Image],
    device: &Device,
) -> Result<Vec<Image>, EvalError> {
    let anchor = trajectory.get(reference).ok_or_else(|| {
        EvalError::Invalid(format!(
            "reference frame {reference} of a {}-frame trajectory",
            trajectory.len()
        ))
    })?;
    let scene_reference = scene
        .first()
        .ok_or_else(|| EvalError::Invalid("the scene has no frames".to_string()))?;
    let targets = pose_latents(model, anchor, trajectory, device)?;
    let context_latents = pose_latents(model, scene_reference, scene, device)?;
    render_targets(model, scene, &context_latents, &targets, device)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn context_is_ordered_middlest_first() {
        // Frames 0..5: distances to the ends are 4, 3, 2, 3, 4 -> 2, then 1 and 3, then the ends.
        assert_eq!(proximity_permutation(&[0, 1, 2, 3, 4]), vec![2, 1, 3, 0, 4]);
        // Six frames: 2 and 3 tie (distance 3) and keep their order.
        assert_eq!(
            proximity_permutation(&[0, 1, 2, 3, 4, 5]),
            vec![2, 3, 1, 4, 0, 5]
        );
        // Uneven indices, reversed in time: first 30, last 0; 12 is 18 from 30, 20 is 20 from 0.
        assert_eq!(proximity_permutation(&[30, 20, 12, 0]), vec![2, 1, 0, 3]);
        assert!(proximity_permutation(&[]).is_empty());
    }
}
