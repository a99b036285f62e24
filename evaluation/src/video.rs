//! Video files in and out of `xfactor transfer`, through the `ffmpeg` and `ffprobe` programs
//! (run as subprocesses, so no codec library is linked): frames sampled evenly from any video
//! ffmpeg reads, and the renders written as an H.264 MP4 that plays anywhere.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use data::Image;
use data::decode::to_training_frame;
use image::RgbImage;

/// Trajectory frames taken from a video when `--frames` is not given: the length of the
/// example videos, enough for a smooth clip, cheap to render on a CPU.
pub const DEFAULT_VIDEO_FRAMES: usize = 30;

/// Frame rate of the written MP4 (the GIF's 100 ms per frame).
pub const OUTPUT_FPS: u32 = 10;

/// How many frames `transfer` takes from its inputs, evenly spaced, first and last included.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Sampling {
    /// Trajectory frames; `None`: every frame of a frame directory, [`DEFAULT_VIDEO_FRAMES`]
    /// of a video.
    pub frames: Option<usize>,
    /// Scene frames (context views); `None`: every frame of a directory, the first frame of a
    /// video (the stereo model's one context view).
    pub scene_frames: Option<usize>,
}

/// Why a video could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    /// The input does not exist.
    #[error("{}: no such file or directory", path.display())]
    Missing {
        /// What was given.
        path: PathBuf,
    },
    /// `ffmpeg` or `ffprobe` is not installed (or not on `PATH`).
    #[error(
        "`{program}` could not be run; install ffmpeg (scripts/setup.sh, or apt-get install ffmpeg)"
    )]
    ToolAbsent {
        /// `ffmpeg` or `ffprobe`.
        program: &'static str,
        /// Why it could not be started.
        #[source]
        source: std::io::Error,
    },
    /// ffprobe finds no video stream in the file.
    #[error("{} is not a video ffmpeg can read: {reason}", path.display())]
    NotVideo {
        /// The file.
        path: PathBuf,
        /// What ffprobe said.
        reason: String,
    },
    /// ffmpeg failed while decoding.
    #[error("decoding {} with ffmpeg failed: {reason}", path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// What ffmpeg said.
        reason: String,
    },
    /// ffmpeg failed while encoding.
    #[error("writing {} with ffmpeg failed: {reason}", path.display())]
    Encode {
        /// The file.
        path: PathBuf,
        /// What ffmpeg said.
        reason: String,
    },
    /// A frame count of zero was asked for.
    #[error("a frame count must be at least 1")]
    NoFrames,
}

/// `count` indices spread evenly over `0..len`, first and last included (all of them when
/// `len <= count`).
pub fn evenly_spaced(len: usize, count: usize) -> Vec<usize> {
    match count {
        _ if len <= count => (0..len).collect(),
        0 => Vec::new(),
        1 => vec![0],
        _ => (0..count).map(|k| k * (len - 1) / (count - 1)).collect(),
    }
}

/// Runs `program` with `args` to the end and returns its stdout. A program that cannot be
/// started is [`VideoError::ToolAbsent`]; one that runs and fails becomes `failed(its stderr)`,
/// the error its caller reports for that tool.
fn run_tool(
    program: &'static str,
    args: &[&str],
    failed: impl FnOnce(String) -> VideoError,
) -> Result<String, VideoError> {
    let output = Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .output()
        .map_err(|source| VideoError::ToolAbsent { program, source })?;
    if output.status.success() {
        Ok(String::from_utf8_lossy(&output.stdout).into_owned())
    } else {
        Err(failed(
            String::from_utf8_lossy(&output.stderr).trim().to_string(),
        ))
    }
}

/// Width, height and frame count of the first video stream (`ffprobe -count_packets` reads
/// the container without decoding).
fn probe(path: &Path) -> Result<(usize, usize, usize), VideoError> {
    let not_video = |reason: String| VideoError::NotVideo {
        path: path.to_path_buf(),
        reason,
    };
    let name = path.to_string_lossy();
    let line = run_tool(
        "ffprobe",
        &[
            "-v",
            "error",
            "-select_streams",
            "v:0",
            "-count_packets",
            "-show_entries",
            "stream=width,height,nb_read_packets",
            "-of",
            "csv=p=0",
            &name,
        ],
        not_video,
    )?;
    let numbers: Vec<usize> = line
        .trim()
        .split(',')
        .filter_map(|field| field.trim().parse().ok())
        .collect();
    match numbers[..] {
        [width, height, frames] if width > 0 && height > 0 && frames > 0 => {
            Ok((width, height, frames))
        }
        _ => Err(not_video(format!(
            "no video stream with frames (ffprobe: `{}`)",
            line.trim()
        ))),
    }
}

/// `count` frames sampled evenly from the video at `path`, centre-cropped and resized to
/// `size x size` like frames from files. ffmpeg hands over just the chosen frames, cropped to
/// a square, as raw RGB, and stops after the last of them.
pub fn decode_video(path: &Path, size: usize, count: usize) -> Result<Vec<Image>, VideoError> {
    if count == 0 {
        return Err(VideoError::NoFrames);
    }
    let (width, height, total) = probe(path)?;
    let chosen = evenly_spaced(total, count);
    let select: Vec<String> = chosen.iter().map(|i| format!("eq(n\\,{i})")).collect();
    let filter = format!(
        "select='{}',crop=w='min(iw\\,ih)':h='min(iw\\,ih)'",
        select.join("+")
    );
    // Rotation metadata swaps width and height, never the shorter side.
    let side = width.min(height);
    let decode_error = |reason: String| VideoError::Decode {
        path: path.to_path_buf(),
        reason,
    };
    let mut child = Command::new("ffmpeg")
        .args(["-v", "error", "-nostdin", "-i"])
        .arg(path)
        .args(["-an", "-sn", "-vf", &filter, "-vsync", "0"])
        .args(["-frames:v", &chosen.len().to_string()])
        .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|source| VideoError::ToolAbsent {
            program: "ffmpeg",
            source,
        })?;
    let stderr = child.stderr.take().map(|mut pipe| {
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = pipe.read_to_string(&mut text);
            text
        })
    });
    let mut frames = Vec::with_capacity(chosen.len());
    if let Some(mut stdout) = child.stdout.take() {
        let mut buffer = vec![0u8; side * side * 3];
        while stdout.read_exact(&mut buffer).is_ok() {
            let rgb = RgbImage::from_raw(side as u32, side as u32, buffer.clone())
                .ok_or_else(|| decode_error("a frame of the wrong size".to_string()))?;
            frames.push(to_training_frame(&rgb, size));
        }
    }
    let status = child.wait().map_err(|e| decode_error(e.to_string()))?;
    let messages = stderr
        .and_then(|thread| thread.join().ok())
        .unwrap_or_default();
    if !status.success() || frames.is_empty() {
        return Err(decode_error(format!(
            "{status}, {} of {} frames: {}",
            frames.len(),
            chosen.len(),
            messages.trim()
        )));
    }
    tracing::info!(video = %path.display(), total, taken = frames.len(), "decoded video frames");
    Ok(frames)
}

fn to_rgb8(image: &Image) -> Vec<u8> {
    image
        .pixels
        .iter()
        .map(|v| ((v + 1.0) * 127.5).round().clamp(0.0, 255.0) as u8)
        .collect()
}

/// Writes `frames` (all the same size) as an H.264 MP4 at [`OUTPUT_FPS`] (yuv420p, padded to
/// even sides as the format requires).
pub fn write_mp4(frames: &[Image], path: &Path) -> Result<(), VideoError> {
    let first = frames.first().ok_or(VideoError::NoFrames)?;
    let encode_error = |reason: String| VideoError::Encode {
        path: path.to_path_buf(),
        reason,
    };
    let size = format!("{}x{}", first.width, first.height);
    let fps = OUTPUT_FPS.to_string();
    let mut child = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24"])
        .args(["-s", &size, "-framerate", &fps, "-i", "pipe:0"])
        .args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-c:v", "libx264"])
        .args(["-pix_fmt", "yuv420p", "-movflags", "+faststart"])
        .arg(path)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|source| VideoError::ToolAbsent {
            program: "ffmpeg",
            source,
        })?;
    let raw: Vec<Vec<u8>> = frames.iter().map(to_rgb8).collect();
    let writer = child.stdin.take().map(|mut stdin| {
        std::thread::spawn(move || raw.iter().try_for_each(|frame| stdin.write_all(frame)))
    });
    let output = child
        .wait_with_output()
        .map_err(|e| encode_error(e.to_string()))?;
    let written = writer.map(|thread| thread.join());
    if !output.status.success() {
        return Err(encode_error(format!(
            "{}: {}",
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        )));
    }
    match written {
        Some(Ok(Err(error))) => Err(encode_error(error.to_string())),
        Some(Err(_)) => Err(encode_error("the frame writer panicked".to_string())),
        _ => Ok(()),
    }
}

/// Writes `renders` as `out_dir/transfer.mp4`. Without ffmpeg on this machine the video is
/// left out with a warning (the PNGs and the GIF are still there): a frame-directory transfer
/// needs no ffmpeg otherwise. Any other failure is an error.
pub fn write_transfer_video(
    renders: &[Image],
    out_dir: &Path,
) -> Result<Option<PathBuf>, VideoError> {
    let path = out_dir.join("transfer.mp4");
    match write_mp4(renders, &path) {
        Ok(()) => Ok(Some(path)),
        Err(VideoError::ToolAbsent { program, source }) => {
            tracing::warn!(%program, %source, "ffmpeg is not installed: transfer.mp4 not written");
            Ok(None)
        }
        Err(error) => Err(error),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_are_evenly_spaced_with_both_ends() {
        assert_eq!(evenly_spaced(30, 8), vec![0, 4, 8, 12, 16, 20, 24, 29]);
        assert_eq!(evenly_spaced(3, 8), vec![0, 1, 2]);
        assert_eq!(evenly_spaced(10, 1), vec![0]);
        assert_eq!(evenly_spaced(10, 0), Vec::<usize>::new());
    }

    #[test]
    fn files_that_are_not_videos_are_named_in_the_error() {
        let text =
            std::env::temp_dir().join(format!("xfactor-not-a-video-{}.mp4", std::process::id()));
        std::fs::write(&text, "plain text").unwrap();
        let error = decode_video(&text, 8, 4).unwrap_err();
        std::fs::remove_file(&text).unwrap();
        assert!(
            matches!(
                error,
                VideoError::NotVideo { .. } | VideoError::ToolAbsent { .. }
            ),
            "{error}"
        );
        assert!(
            error.to_string().contains("ffprobe")
                || error.to_string().contains("xfactor-not-a-video"),
            "{error}"
        );
    }
}
