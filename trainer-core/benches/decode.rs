//! Benchmark of the frame path (decode, centre-crop, resize, map to `[-1, 1]`) on JPEGs of
//! generated scenes: 256x256 kept at 256, and 640x360 resized to 256.
//!
//! `cargo bench -p trainer-core --bench decode -- [--frames N]`.

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

/// Frames per second decoding every frame `rounds` times on `threads` threads.
fn frames_per_second(frames: &[Vec<u8>], rounds: usize, threads: usize) -> f64 {
    let start = Instant::now();
    std::thread::scope(|scope| {
        for thread in 0..threads {
            scope.spawn(move || {
                for round in 0..rounds {
                    for (i, bytes) in frames.iter().enumerate() {
                        if (round * frames.len() + i) % threads == thread {
                            let frame = decode_frame(bytes, "bench.jpg", 256).expect("valid JPEG");
                            std::hint::black_box(frame);
                        }
                    }
                }
            });
        }
    });
    (frames.len() * rounds) as f64 / start.elapsed().as_secs_f64()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let count = args
        .iter()
        .position(|a| a == "--frames")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(64);
    trainer_core::allocator::keep_freed_memory();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
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
