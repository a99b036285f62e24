//! `transfer` straight from video files: 30-frame MP4s made with ffmpeg from the example
//! videos' frames, one's camera path rendered in the other's first frame, and the written MP4
//! measured with ffprobe; and the command line's `--frames` and `--help`. Needs ffmpeg, which
//! `scripts/setup.sh` installs.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use burn::tensor::Device;
use evaluation::{Sampling, TransferRequest, run_transfer_sampled};
use trainer_core::XFactorConfig;

/// Encodes `frames/%03d.jpg` as an H.264 MP4 at 10 frames per second.
fn make_mp4(frames: &Path, out: &Path) -> PathBuf {
    let status = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-framerate", "10", "-i"])
        .arg(frames.join("%03d.jpg"))
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p"])
        .arg(out)
        .status()
        .unwrap_or_else(|e| panic!("ffmpeg could not be run ({e}): run scripts/setup.sh"));
    assert!(status.success(), "ffmpeg failed on {}", frames.display());
    out.to_path_buf()
}

/// `(frames, width, height)` of a video's first stream, frames counted by decoding.
fn measure(video: &Path) -> (usize, u32, u32) {
    let output = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-count_frames"])
        .args(["-show_entries", "stream=nb_read_frames,width,height"])
        .args(["-of", "csv=p=0"])
        .arg(video)
        .output()
        .expect("ffprobe (installed with ffmpeg by scripts/setup.sh)");
    assert!(
        output.status.success(),
        "ffprobe failed on {}",
        video.display()
    );
    let text = String::from_utf8_lossy(&output.stdout);
    let fields: Vec<&str> = text.trim().split(',').collect();
    match fields[..] {
        [width, height, frames] => (
            frames.parse().unwrap(),
            width.parse().unwrap(),
            height.parse().unwrap(),
        ),
        _ => panic!("ffprobe said `{text}`"),
    }
}

#[test]
fn a_video_is_transferred_onto_another_and_written_as_an_mp4() {
    let videos = common::shared_fixture("example_videos");
    let scratch = tempfile::tempdir().unwrap();
    let trajectory = make_mp4(&videos.join("target"), &scratch.path().join("target.mp4"));
    let scene = make_mp4(
        &videos.join("transfer"),
        &scratch.path().join("transfer.mp4"),
    );
    assert_eq!(measure(&trajectory), (30, 256, 256));
    let config = XFactorConfig::tiny(32);
    let checkpoint = common::untrained_checkpoint(&config, 5, scratch.path());
    let request = TransferRequest {
        checkpoint,
        trajectory: trajectory.to_string_lossy().into_owned(),
        scene: scene.to_string_lossy().into_owned(),
        reference: 0,
        out_dir: scratch.path().join("out"),
    };
    let sampling = Sampling {
        frames: Some(30),
        scene_frames: None,
    };
    let started = Instant::now();
    let output = run_transfer_sampled(&request, &sampling, &Device::flex()).unwrap();
    let seconds = started.elapsed().as_secs_f64();
    let video = output.video.expect("transfer.mp4 written");
    let (frames, width, height) = measure(&video);
    eprintln!(
        "transfer of a 30-frame MP4 onto an MP4: {seconds:.2} s; {} -> {frames} frames of {width}x{height}",
        video.display()
    );
    assert_eq!(video, request.out_dir.join("transfer.mp4"));
    assert_eq!((frames, width, height), (30, 32, 32));
    assert_eq!(output.frames.len(), 30);
    assert!(output.gif.exists() && output.strip.exists());
}

#[test]
fn the_command_line_samples_frames_and_its_help_shows_an_example() {
    let binary = env!("CARGO_BIN_EXE_xfactor");
    let help = Command::new(binary).arg("--help").output().unwrap();
    let text = String::from_utf8_lossy(&help.stdout);
    assert!(help.status.success());
    assert!(
        text.contains("Example") && text.contains("--frames") && text.contains(".mp4"),
        "{text}"
    );
    let videos = common::shared_fixture("example_videos");
    let scratch = tempfile::tempdir().unwrap();
    let trajectory = make_mp4(&videos.join("target"), &scratch.path().join("target.mp4"));
    let checkpoint = common::untrained_checkpoint(&XFactorConfig::tiny(32), 5, scratch.path());
    let out = scratch.path().join("out");
    let run = Command::new(binary)
        .arg("transfer")
        .arg("--checkpoint")
        .arg(&checkpoint)
        .arg("--trajectory")
        .arg(&trajectory)
        .arg("--scene")
        .arg(videos.join("transfer/000.jpg"))
        .args(["--frames", "12", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert_eq!(measure(&out.join("transfer.mp4")), (12, 32, 32));
    let missing = Command::new(binary)
        .arg("transfer")
        .arg("--checkpoint")
        .arg(&checkpoint)
        .args(["--trajectory", "/no/such/walk.mp4", "--scene"])
        .arg(&trajectory)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!missing.status.success());
    let message = String::from_utf8_lossy(&missing.stderr);
    assert!(message.contains("/no/such/walk.mp4"), "{message}");
}
