//! Training curves: one row per step, written as CSV (for notebooks) and drawn as PNG and SVG
//! (for reading and publishing) at the end of each stage. Columns are grouped into panels with
//! their own axis, so a learning rate of 1e-4 and a loss of 0.5 are both readable, and losses
//! get a logarithmic axis.

use std::fmt::Write;

use crate::plot::{Chart, Figure, Panel, PlotError, Series};

/// A panel of a [`Curve`]'s figure: which columns it draws and how.
#[derive(Debug, Clone, PartialEq)]
pub struct CurvePanel {
    /// The panel's caption.
    pub title: String,
    /// The value axis's name and unit.
    pub y_label: String,
    /// Whether the value axis is logarithmic.
    pub log_y: bool,
    /// The columns drawn, one line each.
    pub columns: Vec<String>,
}

/// Values of named columns over steps.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// The figure's title, e.g. `local-demo: stage 1`.
    pub title: String,
    /// Column names, e.g. `loss`, `learning_rate`.
    pub columns: Vec<String>,
    /// `(step, one value per column)`, in step order.
    pub rows: Vec<(u64, Vec<f64>)>,
    /// How columns are grouped; a column in no panel gets a linear panel of its own.
    pub panels: Vec<CurvePanel>,
}

/// Width and height of one panel in pixels.
const PANEL_SIZE: (u32, u32) = (900, 330);

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

    /// The column's points over steps.
    fn series(&self, column: &str) -> Option<Series> {
        let index = self.columns.iter().position(|c| c == column)?;
        Some(Series {
            name: column.into(),
            points: self
                .rows
                .iter()
                .filter_map(|(step, values)| Some((*step as f64, *values.get(index)?)))
                .collect(),
        })
    }

    /// The figure: the declared panels, then one per column left over.
    pub fn figure(&self) -> Figure {
        let panel = |title: &str, y_label: &str, log_y: bool, columns: &[String]| Panel {
            title: title.into(),
            x_label: "step".into(),
            y_label: y_label.into(),
            log_y,
            equal_aspect: false,
            series: columns.iter().filter_map(|c| self.series(c)).collect(),
        };
        let mut panels: Vec<Panel> = self
            .panels
            .iter()
            .map(|p| panel(&p.title, &p.y_label, p.log_y, &p.columns))
            .collect();
        for column in &self.columns {
            if !self.panels.iter().any(|p| p.columns.contains(column)) {
                panels.push(panel(column, column, false, std::slice::from_ref(column)));
            }
        }
        Figure {
            title: self.title.clone(),
            panels,
            panel_size: PANEL_SIZE,
        }
    }

    /// The figure as PNG bytes.
    pub fn to_png(&self) -> Result<Vec<u8>, PlotError> {
        self.figure().to_png()
    }

    /// The figure as an SVG document.
    pub fn to_svg(&self) -> Result<String, PlotError> {
        self.figure().to_svg()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curve() -> Curve {
        Curve {
            title: "job: stage 1".into(),
            columns: vec!["loss".into(), "l1".into(), "learning_rate".into()],
            rows: (0..20)
                .map(|s| {
                    let loss = 1.0 / (1.0 + s as f64);
                    (s, vec![loss, loss / 2.0, 1e-4 * s as f64])
                })
                .collect(),
            panels: vec![CurvePanel {
                title: "Loss".into(),
                y_label: "loss".into(),
                log_y: true,
                columns: vec!["loss".into(), "l1".into()],
            }],
        }
    }

    #[test]
    fn csv_has_a_header_and_a_line_per_step() {
        let csv = curve().to_csv();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0], "step,loss,l1,learning_rate");
        assert_eq!(lines.len(), 21);
        assert_eq!(lines[2], "1,0.5,0.25,0.0001");
    }

    #[test]
    fn declared_panels_come_first_and_leftover_columns_get_their_own() {
        let figure = curve().figure();
        let titles: Vec<&str> = figure.panels.iter().map(|p| p.title.as_str()).collect();
        assert_eq!(titles, ["Loss", "learning_rate"]);
        assert!(figure.panels[0].log_y);
        assert_eq!(figure.panels[0].series.len(), 2);
        let (step, rate) = figure.panels[1].series[0].points[3];
        assert_eq!(step, 3.0);
        assert!((rate - 3e-4).abs() < 1e-12);
        let png = image::load_from_memory(&curve().to_png().expect("drawn")).expect("a PNG");
        assert_eq!(png.height(), 40 + 2 * PANEL_SIZE.1);
    }

    #[test]
    fn an_empty_curve_still_draws() {
        let empty = Curve {
            rows: Vec::new(),
            ..curve()
        };
        assert!(empty.to_png().is_ok());
        assert!(empty.to_svg().expect("drawn").contains("<svg"));
    }
}
