//! `xfactor curve`: how transferability grows with training. Every checkpoint a run committed
//! in one stage is evaluated with the run's own evaluation settings (the held-out scenes, the
//! transfers and the oracle of its final evaluation), side by side in one evaluation, so the
//! points differ only in the weights; the curve of TPS `SE3_Auc@30` against steps is written as
//! CSV, PNG and SVG beside the oracle's calibration of an unrelated camera path, the level a
//! transfer must clear to show that pose latents carry a camera path at all.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use settings::evaluation::EvaluationSpec;
use telemetry::plot::{Chart, Figure, Panel, Series};

use crate::error::{EvalError, io_error};
use crate::evaluate::{CheckpointUnderTest, EvaluationReport};
use crate::metrics::CameraMetrics;

/// What the curve's lead over the unrelated path is counted in: the recipe's bar.
pub const LEAD_SPREADS: f64 = 3.0;

/// A run's commits as its job report (`report.json` beside the run's YAML) lists them.
#[derive(Debug, Deserialize)]
struct JobReport {
    commits: Vec<Commit>,
    /// Where the run's own evaluation was committed, when it ran one.
    #[serde(default)]
    evaluation: Option<String>,
}

#[derive(Debug, Deserialize)]
struct Commit {
    stage: u64,
    step: u64,
    location: String,
}

/// One committed checkpoint's figures on the held-out scenes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CurvePoint {
    /// The step it was committed at.
    pub step: u64,
    /// TPS `SE3_Auc@30` of its transfers, and its bootstrap spread.
    pub tps_auc30: (f64, f64),
    /// The oracle's calibration: the target scene rendered along an unrelated camera path.
    pub unrelated_auc30: (f64, f64),
    /// The oracle's calibration: the target scene rendered along the source's own path.
    pub ideal_auc30: f64,
    /// The pose probe's `SE3_Auc@30` on its features.
    pub probe_auc30: (f64, f64),
    /// Reconstruction PSNR (dB).
    pub psnr: (f64, f64),
}

impl CurvePoint {
    /// How far the transfers lead the unrelated path, in their combined spreads.
    pub fn lead_in_spreads(&self) -> f64 {
        let spread = self.tps_auc30.1.hypot(self.unrelated_auc30.1);
        (self.tps_auc30.0 - self.unrelated_auc30.0) / spread.max(f64::EPSILON)
    }
}

/// `SE3_Auc@30` of `metrics` and its spread (0 when none was computed).
fn auc30(metrics: &CameraMetrics) -> (f64, f64) {
    let auc = metrics.at(30).map_or(f64::NAN, |scores| scores.auc);
    (auc, metrics.spread.as_ref().map_or(0.0, |s| s.auc30))
}

/// `location` as written in the job report, or, when the run was started from another folder,
/// the folder of that name under `fallback`.
fn local_folder(location: &str, fallback: &Path) -> Result<PathBuf, EvalError> {
    if location.contains("://") {
        return Err(EvalError::Invalid(format!(
            "{location}: the curve reads checkpoints on this machine's file system"
        )));
    }
    let written = PathBuf::from(location);
    if written.exists() {
        return Ok(written);
    }
    let name = written
        .file_name()
        .ok_or_else(|| EvalError::Invalid(format!("{location}: not a checkpoint folder")))?;
    Ok(fallback.join(name))
}

/// The run folder `run`'s job report.
fn job_report(run: &Path) -> Result<JobReport, EvalError> {
    let path = run.join("report.json");
    let bytes = std::fs::read(&path).map_err(|e| io_error(&path, e))?;
    serde_json::from_slice(&bytes)
        .map_err(|e| EvalError::Invalid(format!("{}: not a job report: {e}", path.display())))
}

/// The checkpoints `run` committed in `stage`, in step order, as checkpoints under test that
/// render from `context_views` views.
pub fn committed_checkpoints(
    run: &Path,
    stage: u64,
    context_views: usize,
) -> Result<Vec<CheckpointUnderTest>, EvalError> {
    let report = job_report(run)?;
    let folder = run.join("checkpoints").join(format!("stage{stage}"));
    let mut commits: Vec<&Commit> = report.commits.iter().filter(|c| c.stage == stage).collect();
    commits.sort_by_key(|c| c.step);
    if commits.is_empty() {
        return Err(EvalError::Invalid(format!(
            "{}: the run committed nothing in stage {stage}",
            run.display()
        )));
    }
    commits
        .into_iter()
        .map(|commit| {
            Ok(CheckpointUnderTest {
                label: format!("step{}", commit.step),
                weights: local_folder(&commit.location, &folder)?.join("model.safetensors"),
                step: Some(commit.step),
                context_views,
            })
        })
        .collect()
}

/// The settings `run`'s own evaluation ran with, and the context views it gave `stage`.
pub fn run_evaluation_settings(
    run: &Path,
    stage: u64,
) -> Result<(EvaluationSpec, usize), EvalError> {
    let location = job_report(run)?.evaluation.ok_or_else(|| {
        EvalError::Invalid(format!(
            "{}: the run has no evaluation of its own; give --spec and --context-views",
            run.display()
        ))
    })?;
    let folder = local_folder(&location, &run.join("checkpoints").join("evaluation"))?;
    let path = folder.join("report.json");
    let bytes = std::fs::read(&path).map_err(|e| io_error(&path, e))?;
    let report: EvaluationReport = serde_json::from_slice(&bytes)
        .map_err(|e| EvalError::Invalid(format!("{}: {e}", path.display())))?;
    let views = usize::try_from(stage.saturating_sub(1))
        .ok()
        .and_then(|index| report.stages.get(index))
        .map_or(1, |s| s.checkpoint.context_views);
    Ok((report.spec, views))
}

/// One point per checkpoint of `report`, in its order.
pub fn points(report: &EvaluationReport) -> Vec<CurvePoint> {
    report
        .stages
        .iter()
        .map(|stage| {
            let trained = &stage.trained;
            CurvePoint {
                step: stage.checkpoint.step.unwrap_or(0),
                tps_auc30: auc30(&trained.tps.model),
                unrelated_auc30: auc30(&trained.tps.unrelated_trajectory),
                ideal_auc30: auc30(&trained.tps.ideal_transfer).0,
                probe_auc30: auc30(&trained.probe.metrics),
                psnr: (
                    trained.reconstruction.psnr,
                    trained.reconstruction.psnr_spread,
                ),
            }
        })
        .collect()
}

/// The points as CSV, one row per checkpoint.
pub fn csv(points: &[CurvePoint]) -> String {
    let mut text = String::from(
        "step,tps_auc30,tps_auc30_spread,unrelated_auc30,unrelated_auc30_spread,lead_in_spreads,ideal_auc30,probe_auc30,probe_auc30_spread,psnr,psnr_spread\n",
    );
    for p in points {
        let _ = writeln!(
            text,
            "{},{:.4},{:.4},{:.4},{:.4},{:.2},{:.4},{:.4},{:.4},{:.3},{:.3}",
            p.step,
            p.tps_auc30.0,
            p.tps_auc30.1,
            p.unrelated_auc30.0,
            p.unrelated_auc30.1,
            p.lead_in_spreads(),
            p.ideal_auc30,
            p.probe_auc30.0,
            p.probe_auc30.1,
            p.psnr.0,
            p.psnr.1
        );
    }
    text
}

/// TPS and the unrelated-path calibration against steps (with the bar `LEAD_SPREADS` spreads
/// above it), and the probe's AUC beside them.
pub fn figure(points: &[CurvePoint], title: &str) -> Figure {
    let series = |name: &str, value: &dyn Fn(&CurvePoint) -> f64| Series {
        name: name.to_string(),
        points: points.iter().map(|p| (p.step as f64, value(p))).collect(),
    };
    let bar = |p: &CurvePoint| {
        p.unrelated_auc30.0 + LEAD_SPREADS * p.tps_auc30.1.hypot(p.unrelated_auc30.1)
    };
    Figure {
        title: title.to_string(),
        panels: vec![Panel {
            title: "SE3_Auc@30 on held-out scenes".into(),
            x_label: "training step".into(),
            y_label: "AUC@30".into(),
            log_y: false,
            equal_aspect: false,
            series: vec![
                series("transfer (TPS)", &|p| p.tps_auc30.0),
                series("unrelated path (oracle)", &|p| p.unrelated_auc30.0),
                series("unrelated path + 3 spreads", &bar),
                series("pose probe", &|p| p.probe_auc30.0),
            ],
        }],
        panel_size: (900, 480),
    }
}

/// Writes `points` as `name.csv`, `name.png` and `name.svg` in `out`.
pub fn write_curve(
    points: &[CurvePoint],
    title: &str,
    out: &Path,
    name: &str,
) -> Result<(), EvalError> {
    std::fs::create_dir_all(out).map_err(|e| io_error(out, e))?;
    let path = out.join(format!("{name}.csv"));
    std::fs::write(&path, csv(points)).map_err(|e| io_error(&path, e))?;
    let chart = figure(points, title);
    let path = out.join(format!("{name}.png"));
    let png = chart.to_png().map_err(|e| io_error(&path, e))?;
    std::fs::write(&path, png).map_err(|e| io_error(&path, e))?;
    let path = out.join(format!("{name}.svg"));
    let svg = chart.to_svg().map_err(|e| io_error(&path, e))?;
    std::fs::write(&path, svg).map_err(|e| io_error(&path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(step: u64, tps: f64) -> CurvePoint {
        CurvePoint {
            step,
            tps_auc30: (tps, 0.02),
            unrelated_auc30: (0.14, 0.015),
            ideal_auc30: 0.9,
            probe_auc30: (0.2, 0.02),
            psnr: (17.0, 0.1),
        }
    }

    #[test]
    fn the_lead_is_counted_in_combined_spreads() {
        // (0.265 - 0.14) / sqrt(0.02^2 + 0.015^2) = 0.125 / 0.025 = 5.
        assert!((point(4000, 0.265).lead_in_spreads() - 5.0).abs() < 1e-9);
        let text = csv(&[point(500, 0.1), point(4000, 0.265)]);
        let rows: Vec<&str> = text.lines().collect();
        assert_eq!(rows.len(), 3);
        assert!(
            rows[2].starts_with("4000,0.2650,0.0200,0.1400,0.0150,5.00,"),
            "{}",
            rows[2]
        );
    }

    #[test]
    fn commits_are_read_in_step_order_and_found_beside_the_run() {
        let run = std::env::temp_dir().join(format!("xfactor-curve-{}", std::process::id()));
        std::fs::create_dir_all(&run).unwrap();
        let report = r#"{"commits": [
            {"stage": 1, "step": 1000, "location": "elsewhere/checkpoints/stage1/step-00001000-g1"},
            {"stage": 2, "step": 10, "location": "elsewhere/checkpoints/stage2/step-00000010-g2"},
            {"stage": 1, "step": 500, "location": "elsewhere/checkpoints/stage1/step-00000500-g1"}
        ]}"#;
        std::fs::write(run.join("report.json"), report).unwrap();
        let found = committed_checkpoints(&run, 1, 1).unwrap();
        let steps: Vec<Option<u64>> = found.iter().map(|c| c.step).collect();
        assert_eq!(steps, [Some(500), Some(1000)]);
        assert_eq!(
            found[0].weights,
            run.join("checkpoints/stage1/step-00000500-g1/model.safetensors")
        );
        let none = committed_checkpoints(&run, 3, 1).unwrap_err().to_string();
        assert!(none.contains("committed nothing in stage 3"), "{none}");
        let unevaluated = run_evaluation_settings(&run, 1).unwrap_err().to_string();
        assert!(unevaluated.contains("--spec"), "{unevaluated}");
        std::fs::remove_dir_all(&run).unwrap();
    }
}
