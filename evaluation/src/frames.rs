//! Reading videos and scenes: one image file, a directory of frames, or an object-store prefix
//! (`s3://`, `gs://`, `az://`, `file://`), frames ordered by the number in their names, centre-cropped
//! and resized to the model's size as the release does; or a video file, decoded by ffmpeg.

use std::path::Path;

use data::Image;
use data::decode::decode_frame;
use data::frame_order::sort_frames;
use data::store::DataRoot;

use crate::error::{EvalError, io_error};
use crate::video::{VideoError, decode_video, evenly_spaced};

/// File name endings read as frames.
const FRAME_EXTENSIONS: [&str; 3] = [".jpg", ".jpeg", ".png"];

/// Whether `name` ends like an image file (`.jpg`, `.jpeg`, `.png`, any case).
pub(crate) fn is_frame(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    FRAME_EXTENSIONS.iter().any(|ext| lower.ends_with(ext))
}

/// The frames at `source` as `size x size` model images: a local image file gives one frame;
/// a local directory or an object-store prefix gives its image files (not recursing into
/// sub-folders) ordered by the number in their names (`frame9` before `frame10`).
pub async fn load_frames_async(source: &str, size: usize) -> Result<Vec<Image>, EvalError> {
    let local = Path::new(source);
    if !source.contains("://") && local.is_file() {
        let bytes = std::fs::read(local).map_err(|e| io_error(local, e))?;
        return Ok(vec![decode_frame(&bytes, source, size)?]);
    }
    let root = DataRoot::open(source)?;
    let mut names: Vec<String> = root
        .list()
        .await?
        .into_iter()
        .map(|listed| listed.path)
        .filter(|path| !path.contains('/') && is_frame(path))
        .collect();
    sort_frames(&mut names);
    if names.is_empty() {
        return Err(EvalError::Invalid(format!(
            "{source}: no .jpg, .jpeg or .png frames"
        )));
    }
    let mut frames = Vec::with_capacity(names.len());
    for name in &names {
        let bytes = root.read(name).await?;
        frames.push(decode_frame(&bytes, &format!("{source}/{name}"), size)?);
    }
    Ok(frames)
}

/// [`load_frames_async`] for callers outside an async runtime (the command-line tools).
pub fn load_frames(source: &str, size: usize) -> Result<Vec<Image>, EvalError> {
    block_on(load_frames_async(source, size))
}

/// `count` of `items` spread evenly, first and last included (all of them without a count or
/// when there are no more).
fn sample<T: Clone>(items: Vec<T>, count: Option<usize>) -> Vec<T> {
    match count {
        Some(count) if count < items.len() => evenly_spaced(items.len(), count)
            .into_iter()
            .map(|i| items[i].clone())
            .collect(),
        _ => items,
    }
}

/// The frames of `source` as `size x size` model images: a video file (anything but a
/// `.jpg`/`.jpeg`/`.png` file) is decoded by ffmpeg and `count.unwrap_or(video_default)`
/// frames are sampled from it; an image, a frame directory or an object-store prefix is read
/// as [`load_frames`] does and sampled to `count` when given.
pub fn load_source(
    source: &str,
    size: usize,
    count: Option<usize>,
    video_default: usize,
) -> Result<Vec<Image>, EvalError> {
    if count == Some(0) {
        return Err(VideoError::NoFrames.into());
    }
    if !source.contains("://") {
        let path = Path::new(source);
        if !path.exists() {
            return Err(VideoError::Missing {
                path: path.to_path_buf(),
            }
            .into());
        }
        if path.is_file() && !is_frame(source) {
            return Ok(decode_video(path, size, count.unwrap_or(video_default))?);
        }
    }
    Ok(sample(load_frames(source, size)?, count))
}

/// Runs a store read to completion on a runtime of its own, for callers outside one (the
/// command-line tools and the worker's evaluation step).
pub(crate) fn block_on<T>(
    read: impl std::future::Future<Output = Result<T, EvalError>>,
) -> Result<T, EvalError> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| EvalError::Invalid(format!("cannot start an async runtime: {e}")))?
        .block_on(read)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_read_in_numeric_name_order_and_resized() {
        let dir = std::env::temp_dir().join(format!("xfactor-frames-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("nested")).unwrap();
        for (name, value) in [
            ("frame10.png", 200u8),
            ("frame9.png", 10),
            ("notes.txt", 0),
            ("nested/c.png", 0),
        ] {
            let path = dir.join(name);
            if name.ends_with(".png") {
                image::RgbImage::from_pixel(12, 8, image::Rgb([value; 3]))
                    .save(&path)
                    .unwrap();
            } else {
                std::fs::write(&path, "x").unwrap();
            }
        }
        let frames = load_frames(dir.to_str().unwrap(), 4).unwrap();
        assert_eq!(frames.len(), 2);
        assert_eq!(frames[0].pixels.len(), 4 * 4 * 3);
        assert!(frames[0].pixels[0] < frames[1].pixels[0]);
        let single = load_frames(dir.join("frame10.png").to_str().unwrap(), 4).unwrap();
        assert_eq!(single.len(), 1);
        assert!(load_frames(dir.join("nested/missing").to_str().unwrap(), 4).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn samples_keep_both_ends_and_a_missing_count_keeps_all() {
        assert_eq!(
            sample(vec!['a', 'b', 'c', 'd', 'e'], Some(3)),
            ['a', 'c', 'e']
        );
        assert_eq!(sample(vec!['a', 'b'], None), ['a', 'b']);
    }

    #[test]
    fn missing_inputs_and_zero_counts_are_refused() {
        let missing = load_source("/no/such/video.mp4", 8, None, 4).unwrap_err();
        assert!(
            missing.to_string().contains("/no/such/video.mp4"),
            "{missing}"
        );
        assert!(matches!(
            load_source("/", 8, Some(0), 4),
            Err(EvalError::Video(VideoError::NoFrames))
        ));
    }
}
