//! The `transfer` command's work: load a checkpoint, a trajectory video and a scene, render the
//! scene along the trajectory's motion, and write the frames as PNG, a strip comparing the
//! trajectory with the renders, an animated GIF and an MP4 (see `video`).

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use data::Image;
use serde::Serialize;
use trainer_core::checkpoint;

use crate::error::{EvalError, io_error};
use crate::figures::{save_gif, save_grid, save_png};
use crate::frames::load_source;
use crate::inference::transfer;
use crate::video::{DEFAULT_VIDEO_FRAMES, Sampling, evenly_spaced, write_transfer_video};

/// Columns of the comparison strip (evenly spaced frames of the trajectory).
const STRIP_COLUMNS: usize = 8;
/// Display time of each GIF frame.
const GIF_DELAY_MS: u32 = 100;

/// What to transfer where.
#[derive(Debug, Clone)]
pub struct TransferRequest {
    /// Model weights (`.safetensors` with its `.json` configuration beside it).
    pub checkpoint: PathBuf,
    /// The video whose camera motion is taken: a video file, a frame directory or an
    /// object-store prefix.
    pub trajectory: String,
    /// The scene to move through: one image (stereo model) or a short video (multi-view model:
    /// every frame becomes a context view, the first the reference).
    pub scene: String,
    /// Frame of the trajectory the motion is measured from.
    pub reference: usize,
    /// Directory the outputs are written to (created if needed).
    pub out_dir: PathBuf,
}

/// Where the outputs went.
#[derive(Debug, Clone, Serialize)]
pub struct TransferOutput {
    /// One PNG per trajectory frame, in order.
    pub frames: Vec<PathBuf>,
    /// Two rows: trajectory frames above, renders below.
    pub strip: PathBuf,
    /// The renders as a looping animation.
    pub gif: PathBuf,
    /// The renders as an MP4; `None` where ffmpeg is not installed.
    pub video: Option<PathBuf>,
}

/// Writes `renders` (and a comparison with `trajectory`) under `out_dir`.
pub fn write_transfer(
    trajectory: &[Image],
    renders: &[Image],
    out_dir: &Path,
) -> Result<TransferOutput, EvalError> {
    let frame_dir = out_dir.join("frames");
    std::fs::create_dir_all(&frame_dir).map_err(|e| io_error(&frame_dir, e))?;
    let mut frames = Vec::with_capacity(renders.len());
    for (index, render) in renders.iter().enumerate() {
        let path = frame_dir.join(format!("{index:03}.png"));
        save_png(render, &path)?;
        frames.push(path);
    }
    let columns = evenly_spaced(renders.len().min(trajectory.len()), STRIP_COLUMNS);
    let strip = out_dir.join("strip.png");
    save_grid(
        &[
            columns.iter().map(|&i| trajectory[i].clone()).collect(),
            columns.iter().map(|&i| renders[i].clone()).collect(),
        ],
        &strip,
    )?;
    let gif = out_dir.join("transfer.gif");
    save_gif(renders, &gif, GIF_DELAY_MS)?;
    let video = write_transfer_video(renders, out_dir)?;
    Ok(TransferOutput {
        frames,
        strip,
        gif,
        video,
    })
}

/// Runs a whole transfer on `device`, with the inputs' frames as [`Sampling::default`] takes
/// them.
pub fn run_transfer(
    request: &TransferRequest,
    device: &Device,
) -> Result<TransferOutput, EvalError> {
    run_transfer_sampled(request, &Sampling::default(), device)
}

/// Runs a whole transfer on `device`, taking as many frames of each input as `sampling` says.
pub fn run_transfer_sampled(
    request: &TransferRequest,
    sampling: &Sampling,
    device: &Device,
) -> Result<TransferOutput, EvalError> {
    let _span =
        tracing::info_span!("transfer", trajectory = %request.trajectory, scene = %request.scene)
            .entered();
    let (model, config) = checkpoint::load(&request.checkpoint, device)?;
    let size = config.image_size;
    let trajectory = load_source(
        &request.trajectory,
        size,
        sampling.frames,
        DEFAULT_VIDEO_FRAMES,
    )?;
    let scene = load_source(&request.scene, size, sampling.scene_frames, 1)?;
    tracing::info!(
        frames = trajectory.len(),
        context_views = scene.len(),
        size = config.image_size,
        "rendering the scene along the trajectory"
    );
    let renders = transfer(&model, &trajectory, request.reference, &scene, device)?;
    write_transfer(&trajectory, &renders, &request.out_dir)
}
