//! Grouped bar charts drawn to PNG: one group per measure, one bar per series (a run, say),
//! each bar labelled with its value in small digits and the series told apart by colour and by
//! their number in the legend (the caller's table names them).

use image::{Rgb, RgbImage};

use crate::curves::CurveError;
use crate::draw::{PALETTE, encode_png, line, swatch, text};

/// Values of several series over the same measures.
#[derive(Debug, Clone, PartialEq)]
pub struct BarChart {
    /// How many measures (groups of bars) there are.
    pub measures: usize,
    /// One value per measure for each series; a value that is not finite draws no bar.
    pub series: Vec<Vec<f64>>,
}

const BAR_WIDTH: u32 = 14;
const BAR_GAP: u32 = 2;
const GROUP_GAP: u32 = 24;
const PLOT_HEIGHT: u32 = 240;
const MARGIN: u32 = 40;
const BACKGROUND: Rgb<u8> = Rgb([255, 255, 255]);
const AXIS: Rgb<u8> = Rgb([60, 60, 60]);

impl BarChart {
    /// The PNG: bars scaled to the largest value, each with its value written above it (one
    /// decimal), a legend of numbered swatches (series 1, 2, ...) and the measure number
    /// under each group.
    pub fn to_png(&self) -> Result<Vec<u8>, CurveError> {
        let bars = self.series.len().max(1) as u32;
        let group_width = bars * (BAR_WIDTH + BAR_GAP) + GROUP_GAP;
        let width = 2 * MARGIN + self.measures.max(1) as u32 * group_width;
        let height = PLOT_HEIGHT + 3 * MARGIN;
        let mut canvas = RgbImage::from_pixel(width, height, BACKGROUND);
        let top = (2 * MARGIN) as i64;
        let bottom = top + PLOT_HEIGHT as i64;
        let highest = self
            .series
            .iter()
            .flatten()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0f64, f64::max);
        let scale = if highest > 0.0 {
            PLOT_HEIGHT as f64 / highest
        } else {
            0.0
        };
        line(
            &mut canvas,
            (MARGIN as i64, bottom),
            ((width - MARGIN) as i64, bottom),
            AXIS,
        );
        for (index, values) in self.series.iter().enumerate() {
            let colour = PALETTE[index % PALETTE.len()];
            let legend_x = MARGIN as i64 + index as i64 * 40;
            swatch(&mut canvas, (legend_x, MARGIN as i64 / 2), colour);
            text(
                &mut canvas,
                (legend_x + 11, MARGIN as i64 / 2 + 2),
                &(index + 1).to_string(),
                AXIS,
            );
            for (measure, value) in values.iter().enumerate().take(self.measures) {
                if !value.is_finite() {
                    continue;
                }
                let left = (MARGIN + measure as u32 * group_width) as i64
                    + index as i64 * (BAR_WIDTH + BAR_GAP) as i64;
                let bar_top = bottom - (value.max(0.0) * scale).round() as i64;
                for x in left..left + BAR_WIDTH as i64 {
                    line(&mut canvas, (x, bar_top), (x, bottom), colour);
                }
                text(
                    &mut canvas,
                    (left, bar_top - 8),
                    &format!("{value:.1}"),
                    AXIS,
                );
            }
        }
        for measure in 0..self.measures {
            let x = (MARGIN + measure as u32 * group_width) as i64;
            text(
                &mut canvas,
                (x, bottom + 6),
                &(measure + 1).to_string(),
                AXIS,
            );
        }
        encode_png(&canvas).map_err(CurveError::from)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bars_are_as_tall_as_their_values_and_coloured_by_series() {
        let chart = BarChart {
            measures: 2,
            series: vec![vec![50.0, 100.0], vec![25.0, f64::NAN]],
        };
        let png = image::load_from_memory(&chart.to_png().unwrap())
            .unwrap()
            .to_rgb8();
        let group_width = 2 * (BAR_WIDTH + BAR_GAP) + GROUP_GAP;
        assert_eq!(png.width(), 2 * MARGIN + 2 * group_width);
        let bottom = 2 * MARGIN + PLOT_HEIGHT;
        // Height of the bar whose left column is `x`: pixels of `colour` above the axis.
        let height = |x: u32, colour: Rgb<u8>| {
            (2 * MARGIN..bottom)
                .filter(|&y| *png.get_pixel(x + BAR_WIDTH / 2, y) == colour)
                .count() as u32
        };
        let second = MARGIN + BAR_WIDTH + BAR_GAP;
        assert_eq!(height(MARGIN, PALETTE[0]), PLOT_HEIGHT / 2);
        assert_eq!(height(MARGIN + group_width, PALETTE[0]), PLOT_HEIGHT);
        assert_eq!(height(second, PALETTE[1]), PLOT_HEIGHT / 4);
        assert_eq!(
            height(second + group_width, PALETTE[1]),
            0,
            "NaN draws no bar"
        );
    }
}
