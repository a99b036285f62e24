//! Benchmark of the frame path (decode, centre-crop, resize as the release does, map to
//! `[-1, 1]`) on JPEGs of generated scenes (256x256 kept at 256, and 640x360 resized to 256),
//! or with `--dir DIR` on the real frames of a directory, compared in the same run with the
//! release's Python path (PIL + numpy, `benches/pil_decode.py`) on one core.
//!
//! `cargo bench -p trainer-core --bench decode -- [--frames N] [--dir DIR [--size 256]]`.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use data::decode::decode_frame;
use data::scenes::{Scene, SceneConfig, Trajectory};
use image::RgbImage;
use image::codecs::jpeg::JpegEncoder;

fn jpeg_frames(width: u32, height: u32, count: usize) -> Vec<Vec<u8>> {
    let side = width.max(height) as usize;
    let scene = Scene::random(
        0,
        0,
        &SceneConfig {
            image_size: side,
            ..SceneConfig::default()
        },
    );
    let trajectory = Trajectory::random(0, 0, count);
    scene
        .render_trajectory(&trajectory)
        .into_iter()
        .map(|frame| {
            let top = (side - height as usize) / 2;
            let rgb = RgbImage::from_fn(width, height, |x, y| {
                let i = ((top + y as usize) * side + x as usize) * 3;
                let channel = |c: usize| ((frame.pixels[i + c] + 1.0) * 127.5) as u8;
                image::Rgb([channel(0), channel(1), channel(2)])
            });
            let mut bytes = Vec::new();
            JpegEncoder::new_with_quality(&mut bytes, 90)
                .encode_image(&rgb)
                .expect("in-memory JPEG encoding");
            bytes
        })
        .collect()
}

/// Frames per second decoding every frame `rounds` times on `threads` threads at 256.
fn frames_per_second(frames: &[Vec<u8>], rounds: usize, threads: usize) -> f64 {
    frames_per_second_at(frames, rounds, threads, 256)
}

/// Frames per second decoding every frame `rounds` times on `threads` threads at `size`.
fn frames_per_second_at(frames: &[Vec<u8>], rounds: usize, threads: usize, size: usize) -> f64 {
    let start = Instant::now();
    std::thread::scope(|scope| {
        for thread in 0..threads {
            scope.spawn(move || {
                for round in 0..rounds {
                    for (i, bytes) in frames.iter().enumerate() {
                        if (round * frames.len() + i) % threads == thread {
                            let frame =
                                decode_frame(bytes, "bench.jpg", size).expect("valid frame");
                            std::hint::black_box(frame);
                        }
                    }
                }
            });
        }
    });
    (frames.len() * rounds) as f64 / start.elapsed().as_secs_f64()
}

/// The value of `--name` in `args`.
fn flag<'a>(args: &'a [String], name: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

/// The interpreter `scripts/setup.sh` installs Pillow and NumPy for: the system's (apt
/// packages), even where a version manager puts another `python3` first on `PATH`.
fn system_python() -> &'static str {
    const SYSTEM: &str = "/usr/bin/python3";
    if Path::new(SYSTEM).is_file() {
        SYSTEM
    } else {
        "python3"
    }
}

/// Why the Python peer gave no frame rate.
#[derive(Debug, thiserror::Error)]
enum PeerError {
    /// The interpreter could not be started.
    #[error("cannot run {python}")]
    Start {
        /// The interpreter.
        python: &'static str,
        /// Why it did not start.
        #[source]
        source: std::io::Error,
    },
    /// The script ran and failed.
    #[error("{python} {} failed (pillow and numpy installed?): {stderr}", script.display())]
    Failed {
        /// The interpreter.
        python: &'static str,
        /// The peer script.
        script: PathBuf,
        /// What it wrote on stderr.
        stderr: String,
    },
    /// The script printed no `fps=` field.
    #[error("unexpected peer output `{stdout}`")]
    Output {
        /// What it wrote on stdout.
        stdout: String,
    },
}

/// Frames per second of the Python peer on `dir`, or why it could not run.
fn pil_peer(dir: &str, size: usize, rounds: usize) -> Result<f64, PeerError> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/pil_decode.py");
    let python = system_python();
    let output = Command::new(python)
        .arg(&script)
        .arg(dir)
        .args(["--size", &size.to_string(), "--rounds", &rounds.to_string()])
        .output()
        .map_err(|source| PeerError::Start { python, source })?;
    let stdout = String::from_utf8_lossy(&output.stdout);
    if !output.status.success() {
        return Err(PeerError::Failed {
            python,
            script,
            stderr: String::from_utf8_lossy(&output.stderr).trim().to_string(),
        });
    }
    stdout
        .split_whitespace()
        .find_map(|field| field.strip_prefix("fps="))
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| PeerError::Output {
            stdout: stdout.trim().to_string(),
        })
}

/// Every frame file under `dir`, sub-folders included, each folder's in frame-number order.
fn frame_files(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut entries: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .filter_map(|entry| Some(entry.ok()?.path()))
        .collect();
    entries.sort_by(|a, b| {
        data::frame_order::compare_frames(&a.to_string_lossy(), &b.to_string_lossy())
    });
    let mut files = Vec::new();
    for path in entries {
        if path.is_dir() {
            files.extend(frame_files(&path));
        } else if [".jpg", ".jpeg", ".png"]
            .iter()
            .any(|ext| path.to_string_lossy().to_ascii_lowercase().ends_with(ext))
        {
            files.push(path);
        }
    }
    files
}

/// `--dir`: this crate's frame path on the frames under a directory against the Python peer.
fn directory_benchmark(dir: &str, size: usize, cores: usize) {
    let frames: Vec<Vec<u8>> = frame_files(Path::new(dir))
        .iter()
        .map(|path| std::fs::read(path).expect("readable frame"))
        .collect();
    assert!(!frames.is_empty(), "{dir}: no frames");
    let rounds = 4;
    let decode = |threads: usize| frames_per_second_at(&frames, rounds, threads, size);
    decode(1);
    let per_core = decode(1);
    let total = decode(cores);
    let peer = pil_peer(dir, size, rounds);
    let (pil, ratio) = match &peer {
        Ok(fps) => (format!("{fps:.0}"), format!("{:.2}", per_core / fps)),
        Err(error) => {
            let cause = std::error::Error::source(error)
                .map(|cause| format!(": {cause}"))
                .unwrap_or_default();
            eprintln!("PIL peer unavailable: {error}{cause}");
            ("unavailable".to_string(), "unavailable".to_string())
        }
    };
    println!(
        "dir={dir} frames={} size={size} rounds={rounds} fps_per_core={per_core:.0} fps_total={total:.0} cores={cores} pil_fps_per_core={pil} ratio_per_core={ratio}",
        frames.len()
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if let Some(dir) = flag(&args, "--dir") {
        trainer_core::allocator::keep_freed_memory();
        let size = flag(&args, "--size")
            .and_then(|v| v.parse().ok())
            .unwrap_or(256);
        directory_benchmark(dir, size, cores);
        return;
    }
    let count = args
        .iter()
        .position(|a| a == "--frames")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(64);
    trainer_core::allocator::keep_freed_memory();
    let small = jpeg_frames(256, 256, count);
    let large = jpeg_frames(640, 360, count);
    println!(
        "config: frames={count} rounds=4 jpeg_quality=90 output=256x256 cores={cores} (PIL peer, one core: 1317 fps at 256, 267 fps at 640x360)"
    );
    frames_per_second(&small, 1, 1);
    frames_per_second(&large, 1, 1);
    let fps_256 = frames_per_second(&small, 4, 1);
    let fps_640 = frames_per_second(&large, 4, 1);
    let total_256 = frames_per_second(&small, 4, cores);
    let total_640 = frames_per_second(&large, 4, cores);
    println!(
        "fps_per_core_256={fps_256:.0} fps_per_core_640={fps_640:.0} fps_total_256={total_256:.0} fps_total_640={total_640:.0} cores={cores}"
    );
}
