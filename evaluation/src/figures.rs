//! Pictures for people: frames as PNG, render grids, strips, animated GIFs and top-down plots of
//! camera paths, drawn with the `image` crate alone.

use std::path::{Path, PathBuf};

use data::Image;
use data::scenes::CameraPose;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, Rgb, RgbImage, RgbaImage};

/// Gap between tiles of grids and strips, in pixels.
const GAP: u32 = 2;
/// Side of camera-path plots, in pixels.
const PLOT_SIDE: u32 = 320;
/// Empty border around the plotted paths, in pixels.
const PLOT_MARGIN: f64 = 20.0;
/// Colours of successive paths in a plot: reference first (black), then the evaluated ones.
const PATH_COLOURS: [[u8; 3]; 4] = [[0, 0, 0], [220, 40, 40], [40, 90, 220], [30, 160, 60]];

/// Why a figure could not be written.
#[derive(Debug, thiserror::Error)]
#[error("writing {path}: {reason}")]
pub struct FigureError {
    /// File being written.
    pub path: PathBuf,
    /// What the encoder or the file system reported.
    pub reason: String,
}

fn figure_error(path: &Path, reason: impl ToString) -> FigureError {
    FigureError {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

/// A `[-1, 1]` model image as 8-bit RGB.
pub fn to_rgb(image: &Image) -> RgbImage {
    let bytes = image
        .pixels
        .iter()
        .map(|v| ((v + 1.0) * 127.5).round().clamp(0.0, 255.0) as u8)
        .collect();
    RgbImage::from_raw(image.width as u32, image.height as u32, bytes)
        .unwrap_or_else(|| RgbImage::new(image.width as u32, image.height as u32))
}

/// Writes one image as PNG.
pub fn save_png(image: &Image, path: &Path) -> Result<(), FigureError> {
    to_rgb(image).save(path).map_err(|e| figure_error(path, e))
}

/// Tiles rows of images (rows may differ in length) on a white background.
pub fn grid(rows: &[Vec<Image>]) -> RgbImage {
    let tile_w = rows
        .iter()
        .flatten()
        .map(|i| i.width as u32)
        .max()
        .unwrap_or(0);
    let tile_h = rows
        .iter()
        .flatten()
        .map(|i| i.height as u32)
        .max()
        .unwrap_or(0);
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0) as u32;
    let width = columns * (tile_w + GAP) + GAP;
    let height = rows.len() as u32 * (tile_h + GAP) + GAP;
    let mut canvas = RgbImage::from_pixel(width, height, Rgb([255, 255, 255]));
    for (r, row) in rows.iter().enumerate() {
        for (c, tile) in row.iter().enumerate() {
            let x = GAP + c as u32 * (tile_w + GAP);
            let y = GAP + r as u32 * (tile_h + GAP);
            image::imageops::replace(&mut canvas, &to_rgb(tile), i64::from(x), i64::from(y));
        }
    }
    canvas
}

/// Writes a grid (see [`grid`]) as PNG.
pub fn save_grid(rows: &[Vec<Image>], path: &Path) -> Result<(), FigureError> {
    grid(rows).save(path).map_err(|e| figure_error(path, e))
}

/// Writes `frames` as a looping animated GIF, `delay_ms` per frame.
pub fn save_gif(frames: &[Image], path: &Path, delay_ms: u32) -> Result<(), FigureError> {
    let file = std::fs::File::create(path).map_err(|e| figure_error(path, e))?;
    let mut encoder = GifEncoder::new_with_speed(std::io::BufWriter::new(file), 10);
    encoder
        .set_repeat(Repeat::Infinite)
        .map_err(|e| figure_error(path, e))?;
    let frames = frames.iter().map(|image| {
        let rgba = RgbaImage::from_fn(image.width as u32, image.height as u32, {
            let rgb = to_rgb(image);
            move |x, y| {
                let [r, g, b] = rgb.get_pixel(x, y).0;
                image::Rgba([r, g, b, 255])
            }
        });
        Frame::from_parts(rgba, 0, 0, Delay::from_numer_denom_ms(delay_ms, 1))
    });
    encoder
        .encode_frames(frames)
        .map_err(|e| figure_error(path, e))
}

fn put(canvas: &mut RgbImage, x: i64, y: i64, colour: [u8; 3]) {
    if x >= 0 && y >= 0 && x < i64::from(canvas.width()) && y < i64::from(canvas.height()) {
        canvas.put_pixel(x as u32, y as u32, Rgb(colour));
    }
}

fn line(canvas: &mut RgbImage, from: (f64, f64), to: (f64, f64), colour: [u8; 3]) {
    let steps = (to.0 - from.0)
        .abs()
        .max((to.1 - from.1).abs())
        .ceil()
        .max(1.0) as usize;
    for k in 0..=steps {
        let u = k as f64 / steps as f64;
        let x = from.0 + u * (to.0 - from.0);
        let y = from.1 + u * (to.1 - from.1);
        put(canvas, x.round() as i64, y.round() as i64, colour);
    }
}

fn dot(canvas: &mut RgbImage, at: (f64, f64), radius: i64, colour: [u8; 3]) {
    for dy in -radius..=radius {
        for dx in -radius..=radius {
            put(
                canvas,
                at.0.round() as i64 + dx,
                at.1.round() as i64 + dy,
                colour,
            );
        }
    }
}

/// A top-down view (world x to the right, world z up the page) of camera centres: one path per
/// entry, the first drawn black (the reference), the others in colour; each path starts at a
/// larger square and its cameras' viewing directions are short ticks.
pub fn camera_paths(paths: &[Vec<CameraPose>]) -> RgbImage {
    let mut canvas = RgbImage::from_pixel(PLOT_SIDE, PLOT_SIDE, Rgb([255, 255, 255]));
    let centres: Vec<Vec<[f64; 3]>> = paths
        .iter()
        .map(|p| p.iter().map(CameraPose::center).collect())
        .collect();
    let all = centres.iter().flatten();
    let (mut lo_x, mut hi_x, mut lo_z, mut hi_z) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for c in all {
        lo_x = lo_x.min(c[0]);
        hi_x = hi_x.max(c[0]);
        lo_z = lo_z.min(c[2]);
        hi_z = hi_z.max(c[2]);
    }
    let span = (hi_x - lo_x).max(hi_z - lo_z).max(1e-9);
    let usable = f64::from(PLOT_SIDE) - 2.0 * PLOT_MARGIN;
    let scale = usable / span;
    let (mid_x, mid_z) = ((lo_x + hi_x) / 2.0, (lo_z + hi_z) / 2.0);
    let half = f64::from(PLOT_SIDE) / 2.0;
    let project = |x: f64, z: f64| (half + (x - mid_x) * scale, half - (z - mid_z) * scale);
    for (index, (path, poses)) in centres.iter().zip(paths).enumerate() {
        let colour = PATH_COLOURS[index % PATH_COLOURS.len()];
        for pair in path.windows(2) {
            line(
                &mut canvas,
                project(pair[0][0], pair[0][2]),
                project(pair[1][0], pair[1][2]),
                colour,
            );
        }
        for (k, (c, pose)) in path.iter().zip(poses).enumerate() {
            let at = project(c[0], c[2]);
            dot(&mut canvas, at, if k == 0 { 3 } else { 1 }, colour);
            let forward = pose.rotation[2];
            let norm = forward[0].hypot(forward[2]).max(1e-9);
            let tip = (
                at.0 + 8.0 * forward[0] / norm,
                at.1 - 8.0 * forward[2] / norm,
            );
            line(&mut canvas, at, tip, colour);
        }
    }
    canvas
}

/// Writes a camera-path plot (see [`camera_paths`]) as PNG.
pub fn save_camera_paths(paths: &[Vec<CameraPose>], path: &Path) -> Result<(), FigureError> {
    camera_paths(paths)
        .save(path)
        .map_err(|e| figure_error(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(side: usize, value: f32) -> Image {
        Image {
            height: side,
            width: side,
            pixels: vec![value; side * side * 3],
        }
    }

    #[test]
    fn grids_and_plots_have_the_expected_size_and_ink() {
        let g = grid(&[vec![flat(8, -1.0), flat(8, 1.0)], vec![flat(8, 0.0)]]);
        assert_eq!((g.width(), g.height()), (2 * 10 + 2, 2 * 10 + 2));
        assert_eq!(g.get_pixel(2, 2).0, [0, 0, 0]);
        assert_eq!(g.get_pixel(12, 2).0, [255, 255, 255]);
        let reference = vec![
            CameraPose::look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
            CameraPose::look_at([1.0, 0.0, 1.0], [1.0, 0.0, 2.0]),
        ];
        let plot = camera_paths(&[reference]);
        let inked = plot.pixels().filter(|p| p.0 != [255, 255, 255]).count();
        assert!(inked > 50, "{inked}");
    }
}
