//! Figures drawn with `plotters`: a [`Figure`] of stacked panels, each with a title, axis names
//! with units, one line per series, a legend, and a linear or logarithmic value axis; rendered
//! as PNG or SVG. Text uses the DejaVu Sans font shipped in `telemetry/fonts/` (through
//! plotters' `ab_glyph` feature), so no fontconfig or system font is needed.

use std::sync::Once;

use plotters::coord::Shift;
use plotters::coord::cartesian::Cartesian2d;
use plotters::coord::ranged1d::Ranged;
use plotters::prelude::*;

/// The shipped font (see `telemetry/fonts/LICENSE-DejaVu.txt`).
const FONT: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");

/// The family name plots ask for; [`register_font`] binds it to [`FONT`].
pub(crate) const FAMILY: &str = "sans-serif";

/// Colours of successive series (matplotlib's first six).
pub(crate) const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// Why a figure could not be drawn or encoded.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// plotters refused to draw (a backend or layout error).
    #[error("cannot draw the figure {title:?}")]
    Draw {
        /// The figure's title.
        title: String,
        /// What plotters said.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The drawn pixels could not be encoded as PNG.
    #[error("cannot encode the figure {title:?} as PNG")]
    Encode {
        /// The figure's title.
        title: String,
        /// What the encoder said.
        #[source]
        source: image::ImageError,
    },
}

/// Binds [`FAMILY`] to the shipped font, once per process.
pub(crate) fn register_font() {
    static REGISTERED: Once = Once::new();
    REGISTERED.call_once(|| {
        // The font is compiled in and known to parse (the tests draw text with it).
        let _ = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT);
    });
}

/// A drawing error of any backend, boxed for [`PlotError::Draw`].
pub(crate) type DrawResult = Result<(), Box<dyn std::error::Error + Send + Sync>>;

/// Boxes a plotters error.
pub(crate) fn boxed<E: std::error::Error + Send + Sync + 'static>(
    error: DrawingAreaErrorKind<E>,
) -> Box<dyn std::error::Error + Send + Sync> {
    Box::new(error)
}

/// Draws with `draw` on a `width` x `height` bitmap and encodes it as PNG.
fn render_png(
    title: &str,
    (width, height): (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> DrawResult,
) -> Result<Vec<u8>, PlotError> {
    register_font();
    let failed = |source| PlotError::Draw {
        title: title.into(),
        source,
    };
    let mut pixels = vec![255u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (width, height)).into_drawing_area();
        draw(&root).map_err(failed)?;
        root.present().map_err(|e| failed(boxed(e)))?;
    }
    let canvas = image::RgbImage::from_raw(width, height, pixels)
        .ok_or_else(|| failed("the bitmap backend returned a buffer of the wrong size".into()))?;
    let mut png = Vec::new();
    canvas
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|source| PlotError::Encode {
            title: title.into(),
            source,
        })?;
    Ok(png)
}

/// Draws with `draw` as an SVG document of `width` x `height`.
fn render_svg(
    title: &str,
    (width, height): (u32, u32),
    draw: impl FnOnce(&DrawingArea<SVGBackend<'_>, Shift>) -> DrawResult,
) -> Result<String, PlotError> {
    register_font();
    let failed = |source| PlotError::Draw {
        title: title.into(),
        source,
    };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (width, height)).into_drawing_area();
        draw(&root).map_err(failed)?;
        root.present().map_err(|e| failed(boxed(e)))?;
    }
    Ok(svg)
}

/// A figure that draws itself on any plotters backend, and so renders as PNG and as SVG.
pub trait Chart {
    /// The title (also what errors name).
    fn title(&self) -> &str;

    /// Width and height in pixels.
    fn size(&self) -> (u32, u32);

    /// Draws the whole figure on `root`.
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult
    where
        DB::ErrorType: 'static;

    /// The figure as PNG bytes.
    fn to_png(&self) -> Result<Vec<u8>, PlotError> {
        render_png(self.title(), self.size(), |root| self.draw(root))
    }

    /// The figure as an SVG document.
    fn to_svg(&self) -> Result<String, PlotError> {
        render_svg(self.title(), self.size(), |root| self.draw(root))
    }
}

/// One named line of points `(x, y)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Its legend entry.
    pub name: String,
    /// Its points in drawing order; points that are not finite (or not positive on a
    /// logarithmic axis) are left out.
    pub points: Vec<(f64, f64)>,
}

/// One chart of a [`Figure`].
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// Its caption.
    pub title: String,
    /// The horizontal axis's name and unit, e.g. `step`.
    pub x_label: String,
    /// The vertical axis's name and unit, e.g. `loss (L1 + w·LPIPS)`.
    pub y_label: String,
    /// Whether the vertical axis is logarithmic (losses).
    pub log_y: bool,
    /// Whether one unit is as long on both axes (a top-down map of camera centres).
    pub equal_aspect: bool,
    /// The lines.
    pub series: Vec<Series>,
}

/// Panels stacked top to bottom under one title.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// The figure's title.
    pub title: String,
    /// The panels.
    pub panels: Vec<Panel>,
    /// Width and height of each panel in pixels.
    pub panel_size: (u32, u32),
}

const TITLE_HEIGHT: u32 = 40;

impl Chart for Figure {
    fn title(&self) -> &str {
        &self.title
    }

    fn size(&self) -> (u32, u32) {
        let panels = self.panels.len().max(1) as u32;
        (self.panel_size.0, TITLE_HEIGHT + panels * self.panel_size.1)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(boxed)?;
        let body = root
            .titled(&self.title, (FAMILY, 24).into_font())
            .map_err(boxed)?;
        let areas = body.split_evenly((self.panels.len().max(1), 1));
        for (panel, area) in self.panels.iter().zip(&areas) {
            panel.draw(area)?;
        }
        Ok(())
    }
}

/// A tick label: whole numbers without decimals, very small or large ones in scientific
/// notation, others to three decimals without trailing zeros.
pub(crate) fn tick(value: f64) -> String {
    let magnitude = value.abs();
    // A tick at zero computed in floating point (-5.6e-17) reads as zero.
    if magnitude < 1e-12 {
        return "0".into();
    }
    if value == value.round() && magnitude < 1e6 {
        format!("{value:.0}")
    } else if !(1e-2..1e6).contains(&magnitude) {
        format!("{value:.1e}")
    } else {
        let text = format!("{value:.3}");
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

/// Share of an equal-aspect panel's height kept free of points for the legend.
const LEGEND_ROOM: f64 = 0.25;

/// Lowest and highest finite value of `values`, widened when they are equal.
fn bounds(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (low, high) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if low > high {
        return None;
    }
    if high > low {
        Some((low, high))
    } else {
        let pad = if low == 0.0 { 1.0 } else { low.abs() * 0.1 };
        Some((low - pad, high + pad))
    }
}

impl Panel {
    /// The series that have points the axes can show, with each point's height as drawn:
    /// `log10(y)` on a logarithmic axis (drawn linearly, labelled with `10^y`, so every
    /// range gets tick labels, also one narrower than a decade).
    fn drawable(&self) -> Vec<(&str, Vec<(f64, f64)>)> {
        self.series
            .iter()
            .map(|series| {
                let points: Vec<(f64, f64)> = series
                    .points
                    .iter()
                    .copied()
                    .filter(|(x, y)| x.is_finite() && y.is_finite() && (!self.log_y || *y > 0.0))
                    .map(|(x, y)| (x, if self.log_y { y.log10() } else { y }))
                    .collect();
                (series.name.as_str(), points)
            })
            .filter(|(_, points)| !points.is_empty())
            .collect()
    }

    fn draw<DB: DrawingBackend>(&self, area: &DrawingArea<DB, Shift>) -> DrawResult
    where
        DB::ErrorType: 'static,
    {
        let lines = self.drawable();
        let all = || lines.iter().flat_map(|(_, points)| points.iter());
        let (x_low, x_high) = bounds(all().map(|p| p.0)).unwrap_or((0.0, 1.0));
        let (y_low, y_high) = bounds(all().map(|p| p.1)).unwrap_or((0.0, 1.0));
        let (x, y) = if self.equal_aspect {
            // Equal units on both axes, the points in the lower part and the top
            // [`LEGEND_ROOM`] left to the legend, which must never cover a point (a camera
            // path's last pose once hid a whole series under it).
            let half = (x_high - x_low).max(y_high - y_low) * 0.55;
            let side = 2.0 * half / (1.0 - LEGEND_ROOM);
            let (x_mid, y_mid) = ((x_low + x_high) / 2.0, (y_low + y_high) / 2.0);
            (
                x_mid - side / 2.0..x_mid + side / 2.0,
                y_mid - half..y_mid - half + side,
            )
        } else {
            let pad = (y_high - y_low) * 0.05;
            (x_low..x_high, y_low - pad..y_high + pad)
        };
        self.draw_lines(area, &lines, x, y)
    }

    fn draw_lines<DB>(
        &self,
        area: &DrawingArea<DB, Shift>,
        lines: &[(&str, Vec<(f64, f64)>)],
        x: std::ops::Range<f64>,
        y: std::ops::Range<f64>,
    ) -> DrawResult
    where
        DB: DrawingBackend,
        DB::ErrorType: 'static,
    {
        let mut chart = ChartBuilder::on(area)
            .caption(&self.title, (FAMILY, 18).into_font())
            .margin(12)
            .x_label_area_size(44)
            .y_label_area_size(80)
            .build_cartesian_2d(x, y)
            .map_err(boxed)?;
        let log_y = self.log_y;
        let y_label = |y: &f64| {
            if log_y {
                tick(significant(10f64.powf(*y)))
            } else {
                tick(*y)
            }
        };
        let y_desc = if log_y {
            format!("{} (log scale)", self.y_label)
        } else {
            self.y_label.clone()
        };
        chart
            .configure_mesh()
            .x_desc(&self.x_label)
            .y_desc(y_desc)
            .x_label_formatter(&|x| tick(*x))
            .y_label_formatter(&y_label)
            .label_style((FAMILY, 13).into_font())
            .axis_desc_style((FAMILY, 15).into_font())
            .light_line_style(RGBColor(235, 235, 235))
            .draw()
            .map_err(boxed)?;
        for (index, (name, points)) in lines.iter().enumerate() {
            let colour = PALETTE[index % PALETTE.len()];
            chart
                .draw_series(LineSeries::new(
                    points.iter().copied(),
                    colour.stroke_width(2),
                ))
                .map_err(boxed)?
                .label(*name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            // Markers where lines alone could hide a series: a single point, or a path (whose
            // points may coincide).
            if points.len() == 1 || self.equal_aspect {
                chart
                    .draw_series(PointSeries::of_element(
                        points.iter().copied(),
                        3,
                        colour.filled(),
                        &|at, size, style| Circle::new(at, size, style),
                    ))
                    .map_err(boxed)?;
            }
        }
        draw_legend(&mut chart)
    }
}

/// The legend of a chart's labelled series, in its upper right corner.
pub(crate) fn draw_legend<'a, DB, X, Y>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<X, Y>>,
) -> DrawResult
where
    DB: DrawingBackend + 'a,
    DB::ErrorType: 'static,
    X: Ranged,
    Y: Ranged,
{
    chart
        .configure_series_labels()
        .label_font((FAMILY, 13).into_font())
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(160, 160, 160))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(boxed)?;
    Ok(())
}

/// `value` rounded to two significant digits (tick labels of a logarithmic axis).
fn significant(value: f64) -> f64 {
    if value == 0.0 || !value.is_finite() {
        return value;
    }
    let scale = 10f64.powf(value.abs().log10().floor() - 1.0);
    (value / scale).round() * scale
}

#[cfg(test)]
mod tests {
    use super::*;

    fn figure(log_y: bool) -> Figure {
        Figure {
            title: "Stage 1".into(),
            panels: vec![Panel {
                title: "Loss".into(),
                x_label: "step".into(),
                y_label: "loss".into(),
                log_y,
                equal_aspect: false,
                series: vec![
                    Series {
                        name: "total".into(),
                        points: (1..50).map(|s| (s as f64, 1.0 / s as f64)).collect(),
                    },
                    Series {
                        name: "l1".into(),
                        points: (1..50).map(|s| (s as f64, 0.5 / s as f64)).collect(),
                    },
                ],
            }],
            panel_size: (640, 320),
        }
    }

    fn pixels_of(png: &[u8], colour: RGBColor) -> usize {
        image::load_from_memory(png)
            .expect("a PNG")
            .to_rgb8()
            .pixels()
            .filter(|p| p.0 == [colour.0, colour.1, colour.2])
            .count()
    }

    #[test]
    fn a_figure_draws_every_series_in_its_colour_with_text() {
        for log_y in [false, true] {
            let png = figure(log_y).to_png().expect("drawn");
            let decoded = image::load_from_memory(&png).expect("a PNG").to_rgb8();
            assert_eq!(decoded.dimensions(), (640, TITLE_HEIGHT + 320));
            for colour in &PALETTE[..2] {
                assert!(pixels_of(&png, *colour) > 100, "log_y={log_y} {colour:?}");
            }
            // Titles, axis names and tick labels are text: dark anti-aliased pixels.
            let dark = decoded
                .pixels()
                .filter(|p| p.0.iter().all(|&c| c < 90))
                .count();
            assert!(dark > 500, "log_y={log_y}: only {dark} dark pixels");
        }
    }

    #[test]
    fn ticks_read_like_numbers_people_write() {
        let ticks: Vec<String> = [5.0, 0.25, 0.1 + 0.2, 1e-4, 2.5e7, -3.0, -5.6e-17]
            .iter()
            .map(|v| tick(*v))
            .collect();
        assert_eq!(ticks, ["5", "0.25", "0.3", "1.0e-4", "2.5e7", "-3", "0"]);
    }

    #[test]
    fn the_svg_names_the_title_axes_and_legend() {
        let svg = figure(true).to_svg().expect("drawn");
        for text in ["Stage 1", "Loss", "step", "total", "l1"] {
            assert!(svg.contains(&format!(">\n{text}\n<")), "{text} missing");
        }
    }

    #[test]
    fn a_log_axis_leaves_out_points_it_cannot_show_and_an_empty_panel_still_draws() {
        let mut figure = figure(true);
        figure.panels[0].series[0].points.push((60.0, 0.0));
        figure.panels[0].series[1].points.clear();
        assert!(figure.to_png().is_ok());
        let drawable = figure.panels[0].drawable();
        assert_eq!(
            drawable.len(),
            1,
            "a series with no point is left out, legend too"
        );
        assert_eq!(drawable[0].1.len(), 49);
        assert_eq!(
            drawable[0].1[9],
            (10.0, -1.0),
            "heights are log10 on a log axis"
        );
        figure.panels[0].series.clear();
        assert!(figure.to_png().is_ok());
    }

    #[test]
    fn a_log_axis_narrower_than_a_decade_still_has_tick_labels() {
        let mut figure = figure(true);
        figure.panels[0].series = vec![Series {
            name: "loss".into(),
            points: (0..100)
                .map(|s| (s as f64, 0.5 - 0.003 * s as f64))
                .collect(),
        }];
        let svg = figure.to_svg().expect("drawn");
        assert!(
            svg.contains(">\n0.3\n<") || svg.contains(">\n0.25\n<"),
            "{svg}"
        );
        assert!(svg.contains("loss (log scale)"));
        assert_eq!(significant(0.2512), 0.25);
    }
}
