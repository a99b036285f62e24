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
    let mut latents = Vec::with_capacity(frames.len());
    for chunk in frames.chunks(CHUNK) {
        let references = upload(&vec![reference; chunk.len()], device)?;
        let targets = upload(&chunk.iter().collect::<Vec<_>>(), device)?;
        let pairs = Tensor::stack(vec![references, targets], 1);
        let poses = model.pose_enc.forward(pairs);
        let [b, _, cp] = poses.dims();
        let values = poses
            .narrow(1, 1, 1)
            .reshape([b * cp])
            .try_into_vec_as::<f32>()
            .map_err(|e| EvalError::Tensor(format!("{e:?}")))?;
        latents.extend(values.chunks_exact(cp).map(<[f32]>::to_vec));
    }
    Ok(latents)
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

/// Renders `scene`'s first frame (and its other frames as further context views) along the
/// motion of `trajectory` relative to `trajectory[reference]`: the transfer XFactor exists for.
pub fn transfer(
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
