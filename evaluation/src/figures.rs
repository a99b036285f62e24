//! Pictures for people: frames as PNG, render grids, strips, animated GIFs and top-down plots of
//! camera paths (the plots through `telemetry::plot`).

use std::path::{Path, PathBuf};

use data::Image;
use data::scenes::CameraPose;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, Rgb, RgbImage, RgbaImage};
use telemetry::plot::{Chart, Figure, Panel, Series};
use telemetry::tiles::{Tile, TileRow, TileSheet};

/// Gap between tiles of grids and strips, in pixels.
const GAP: u32 = 2;
/// The least side of a frame in a labelled sheet, in pixels: 32-pixel frames drawn 1:1 are
/// too small to read.
const SHEET_SIDE: u32 = 96;
/// Side of camera-path plots, in pixels.
const PLOT_SIDE: u32 = 520;

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

/// Writes rows of frames as a PNG sheet a reader can use at a glance: every frame scaled up
/// (nearest neighbour) to at least 96 pixels, each row named on the left (`rows`' labels),
/// each column on top (`columns`), under `title`.
pub fn save_sheet(
    title: &str,
    columns: &[String],
    rows: &[(String, Vec<Image>)],
    path: &Path,
) -> Result<(), FigureError> {
    let sheet = TileSheet {
        title: title.into(),
        columns: columns.to_vec(),
        rows: rows
            .iter()
            .map(|(label, images)| TileRow {
                label: label.clone(),
                tiles: images
                    .iter()
                    .map(|image| {
                        let rgb = to_rgb(image);
                        Tile {
                            width: rgb.width(),
                            height: rgb.height(),
                            rgb: rgb.into_raw(),
                        }
                    })
                    .collect(),
            })
            .collect(),
        min_side: SHEET_SIDE,
    };
    let png = sheet.to_png().map_err(|e| figure_error(path, e))?;
    std::fs::write(path, png).map_err(|e| figure_error(path, e))
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

/// A top-down view of camera centres (world x to the right, world z up), one named line per
/// path, drawn with plotters with equal units on both axes; `title` says what is compared.
pub fn camera_paths(
    title: &str,
    paths: &[(&str, &[CameraPose])],
) -> Result<Vec<u8>, telemetry::plot::PlotError> {
    let series = paths
        .iter()
        .map(|(name, poses)| Series {
            name: (*name).into(),
            points: poses
                .iter()
                .map(|pose| {
                    let centre = pose.center();
                    (centre[0], centre[2])
                })
                .collect(),
        })
        .collect();
    Figure {
        title: title.into(),
        panels: vec![Panel {
            title: "camera centres, top view".into(),
            x_label: "x (scene units)".into(),
            y_label: "z (scene units)".into(),
            log_y: false,
            equal_aspect: true,
            series,
        }],
        panel_size: (PLOT_SIDE, PLOT_SIDE),
    }
    .to_png()
}

/// Writes a camera-path plot (see [`camera_paths`]) as PNG.
pub fn save_camera_paths(
    title: &str,
    paths: &[(&str, &[CameraPose])],
    path: &Path,
) -> Result<(), FigureError> {
    let png = camera_paths(title, paths).map_err(|e| figure_error(path, e))?;
    std::fs::write(path, png).map_err(|e| figure_error(path, e))
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
        let reference = [
            CameraPose::look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
            CameraPose::look_at([1.0, 0.0, 1.0], [1.0, 0.0, 2.0]),
        ];
        let png = camera_paths("paths", &[("reference", &reference[..])]).expect("drawn");
        let plot = image::load_from_memory(&png).expect("a PNG").to_rgb8();
        let inked = plot.pixels().filter(|p| p.0 != [255, 255, 255]).count();
        assert!(inked > 500, "{inked}");
    }
}
