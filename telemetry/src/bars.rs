//! Grouped bar charts (one group per measure, one bar per series, each bar labelled with its
//! value), drawn with `plotters` with a title, a value axis name, the measures named under
//! their groups and a legend naming the series.

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::plot::{Chart, DrawResult, FAMILY, PALETTE, boxed, draw_legend};

/// Values of several series over the same measures.
#[derive(Debug, Clone, PartialEq)]
pub struct BarChart {
    /// The chart's title.
    pub title: String,
    /// The value axis's name and unit.
    pub y_label: String,
    /// The measures' names, one group of bars each.
    pub measures: Vec<String>,
    /// `(name, one value per measure)` for each series (a run, say); a value that is not
    /// finite draws no bar.
    pub series: Vec<(String, Vec<f64>)>,
}

/// Fraction of a group's width its bars take.
const GROUP_FILL: f64 = 0.8;

impl BarChart {
    /// Left and right edge of series `index`'s bar in group `measure` (groups are centred on
    /// whole numbers).
    fn bar_span(&self, measure: usize, index: usize) -> (f64, f64) {
        let width = GROUP_FILL / self.series.len().max(1) as f64;
        let left = measure as f64 - GROUP_FILL / 2.0 + index as f64 * width;
        (left, left + width)
    }
}

impl Chart for BarChart {
    fn title(&self) -> &str {
        &self.title
    }

    fn size(&self) -> (u32, u32) {
        let bars = self.measures.len().max(1) * self.series.len().max(1);
        ((240 + 26 * bars as u32).max(640), 480)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(boxed)?;
        let highest = self
            .series
            .iter()
            .flat_map(|(_, values)| values.iter().copied())
            .filter(|v| v.is_finite())
            .fold(0.0f64, f64::max);
        let top = if highest > 0.0 { highest * 1.2 } else { 1.0 };
        let groups = self.measures.len().max(1);
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, (FAMILY, 22).into_font())
            .margin(14)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(-0.5..groups as f64 - 0.5, 0.0..top)
            .map_err(boxed)?;
        let names = &self.measures;
        let measure_name = |x: &f64| {
            let nearest = x.round();
            match names.get(nearest as usize) {
                Some(name) if (x - nearest).abs() < 1e-6 && nearest >= 0.0 => name.clone(),
                _ => String::new(),
            }
        };
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(groups + 1)
            .x_label_formatter(&measure_name)
            .y_desc(&self.y_label)
            .label_style((FAMILY, 13).into_font())
            .axis_desc_style((FAMILY, 15).into_font())
            .light_line_style(RGBColor(235, 235, 235))
            .draw()
            .map_err(boxed)?;
        let value_style =
            TextStyle::from((FAMILY, 12).into_font()).pos(Pos::new(HPos::Center, VPos::Bottom));
        for (index, (name, values)) in self.series.iter().enumerate() {
            let colour = PALETTE[index % PALETTE.len()];
            let bars: Vec<(usize, f64)> = values
                .iter()
                .copied()
                .enumerate()
                .take(self.measures.len())
                .filter(|(_, v)| v.is_finite())
                .collect();
            chart
                .draw_series(bars.iter().map(|&(measure, value)| {
                    let (left, right) = self.bar_span(measure, index);
                    Rectangle::new([(left, 0.0), (right, value.max(0.0))], colour.filled())
                }))
                .map_err(boxed)?
                .label(name.as_str())
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 6), (x + 14, y + 6)], colour.filled())
                });
            chart
                .draw_series(bars.iter().map(|&(measure, value)| {
                    let (left, right) = self.bar_span(measure, index);
                    Text::new(
                        format!("{value:.1}"),
                        ((left + right) / 2.0, value.max(0.0)),
                        value_style.clone(),
                    )
                }))
                .map_err(boxed)?;
        }
        draw_legend(&mut chart)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chart() -> BarChart {
        BarChart {
            title: "Runs".into(),
            y_label: "score (%)".into(),
            measures: vec!["rot".into(), "trans".into()],
            series: vec![
                ("xfactor".into(), vec![50.0, 100.0]),
                ("autoencode".into(), vec![25.0, f64::NAN]),
            ],
        }
    }

    #[test]
    fn bars_are_as_tall_as_their_values_and_coloured_by_series() {
        let png = image::load_from_memory(&chart().to_png().expect("drawn"))
            .expect("a PNG")
            .to_rgb8();
        let count = |colour: RGBColor| {
            png.pixels()
                .filter(|p| p.0 == [colour.0, colour.1, colour.2])
                .count() as f64
        };
        // Series 0 has bars of 50 and 100, series 1 one bar of 25 (NaN draws none): their
        // areas (same width) are 150 : 25, plus a legend swatch each.
        let ratio = count(PALETTE[0]) / count(PALETTE[1]);
        assert!((4.0..7.0).contains(&ratio), "area ratio {ratio}");
    }

    #[test]
    fn the_svg_names_title_measures_series_and_values() {
        let svg = chart().to_svg().expect("drawn");
        for text in [
            "Runs",
            "score (%)",
            "rot",
            "trans",
            "xfactor",
            "autoencode",
            "50.0",
            "25.0",
        ] {
            assert!(svg.contains(&format!(">\n{text}\n<")), "{text} missing");
        }
        assert!(!svg.contains("NaN"));
    }
}
