//! Loss curves: one row per step, written as CSV (for notebooks) and drawn as PNG (for a
//! glance) at the end of each stage. Each column gets its own panel with its own scale, so a
//! learning rate of 1e-4 and a loss of 0.5 are both readable.

use std::fmt::Write;

use image::{Rgb, RgbImage};

use crate::draw::{PALETTE, encode_png, line, swatch, text};

/// Why a curve could not be drawn.
#[derive(Debug, thiserror::Error)]
pub enum CurveError {
    /// PNG encoding failed.
    #[error("cannot encode the curve PNG: {0}")]
    Encode(#[from] image::ImageError),
}

/// Values of named columns over steps.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// Column names, e.g. `loss`, `learning_rate`.
    pub columns: Vec<String>,
    /// `(step, one value per column)`, in step order.
    pub rows: Vec<(u64, Vec<f64>)>,
}

const PANEL_WIDTH: u32 = 640;
const PANEL_HEIGHT: u32 = 200;
const MARGIN: u32 = 40;
const BACKGROUND: Rgb<u8> = Rgb([255, 255, 255]);
const AXIS: Rgb<u8> = Rgb([60, 60, 60]);
const GRID: Rgb<u8> = Rgb([225, 225, 225]);

impl Curve {
    /// The CSV text: a `step,<columns>` header, then one line per row.
    pub fn to_csv(&self) -> String {
        let mut text = format!("step,{}\n", self.columns.join(","));
        for (step, values) in &self.rows {
            let cells: Vec<String> = values.iter().map(|v| format!("{v}")).collect();
            let _ = writeln!(text, "{step},{}", cells.join(","));
        }
        text
    }

    /// A PNG with one panel per column: the curve, a light grid, and the value range and last
    /// step written in small digits.
    pub fn to_png(&self) -> Result<Vec<u8>, CurveError> {
        let panels = self.columns.len().max(1) as u32;
        let height = panels * (PANEL_HEIGHT + MARGIN) + MARGIN;
        let mut canvas = RgbImage::from_pixel(PANEL_WIDTH + 2 * MARGIN, height, BACKGROUND);
        for column in 0..self.columns.len() {
            let top = MARGIN + column as u32 * (PANEL_HEIGHT + MARGIN);
            self.draw_panel(&mut canvas, column, top);
        }
        encode_png(&canvas).map_err(CurveError::from)
    }

    fn draw_panel(&self, canvas: &mut RgbImage, column: usize, top: u32) {
        let (left, bottom) = (MARGIN as i64, (top + PANEL_HEIGHT) as i64);
        let (right, top) = ((MARGIN + PANEL_WIDTH) as i64, top as i64);
        for fraction in [0.25, 0.5, 0.75] {
            let y = bottom - ((bottom - top) as f64 * fraction) as i64;
            line(canvas, (left, y), (right, y), GRID);
        }
        line(canvas, (left, top), (left, bottom), AXIS);
        line(canvas, (left, bottom), (right, bottom), AXIS);
        let points: Vec<(u64, f64)> = self
            .rows
            .iter()
            .filter_map(|(step, values)| values.get(column).map(|v| (*step, *v)))
            .filter(|(_, v)| v.is_finite())
            .collect();
        let (Some(first), Some(last)) = (points.first(), points.last()) else {
            return;
        };
        let (low, high) = points
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), (_, v)| {
                (lo.min(*v), hi.max(*v))
            });
        let span = if high > low { high - low } else { 1.0 };
        let steps = (last.0 - first.0).max(1) as f64;
        let place = |(step, value): (u64, f64)| {
            let x = left + ((step - first.0) as f64 / steps * (right - left) as f64) as i64;
            let y = bottom - ((value - low) / span * (bottom - top) as f64) as i64;
            (x, y)
        };
        let colour = PALETTE[column % PALETTE.len()];
        for pair in points.windows(2) {
            line(canvas, place(pair[0]), place(pair[1]), colour);
        }
        if points.len() == 1 {
            let (x, y) = place(points[0]);
            line(canvas, (x - 2, y), (x + 2, y), colour);
        }
        swatch(canvas, (right - 12, top + 4), colour);
        text(canvas, (left + 4, top + 2), &format!("{high:.4e}"), AXIS);
        text(canvas, (left + 4, bottom - 8), &format!("{low:.4e}"), AXIS);
        text(
            canvas,
            (right - 40, bottom + 6),
            &format!("{}", last.0),
            AXIS,
        );
        text(canvas, (left, bottom + 6), &format!("{}", first.0), AXIS);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curve() -> Curve {
        Curve {
            columns: vec!["loss".into(), "learning_rate".into()],
            rows: (0..20)
                .map(|s| (s, vec![1.0 / (1.0 + s as f64), 1e-4 * s as f64]))
                .collect(),
        }
    }

    #[test]
    fn csv_has_a_header_and_a_line_per_step() {
        let csv = curve().to_csv();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0], "step,loss,learning_rate");
        assert_eq!(lines.len(), 21);
        assert_eq!(lines[2], "1,0.5,0.0001");
    }

    #[test]
    fn png_has_one_panel_per_column_and_draws_the_curves() {
        let png = curve().to_png().expect("encode");
        let image = image::load_from_memory(&png).expect("decode").to_rgb8();
        assert_eq!(image.width(), PANEL_WIDTH + 2 * MARGIN);
        assert_eq!(image.height(), 2 * (PANEL_HEIGHT + MARGIN) + MARGIN);
        for colour in &PALETTE[..2] {
            let drawn = image.pixels().filter(|p| *p == colour).count();
            assert!(
                drawn > PANEL_WIDTH as usize,
                "{colour:?} drew {drawn} pixels"
            );
        }
    }

    #[test]
    fn an_empty_curve_still_draws_axes() {
        let empty = Curve {
            columns: vec!["loss".into()],
            rows: Vec::new(),
        };
        let image = image::load_from_memory(&empty.to_png().expect("encode"))
            .expect("decode")
            .to_rgb8();
        assert!(image.pixels().any(|p| *p == AXIS));
    }
}
