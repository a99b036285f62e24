//! `xfactor compare`: the evaluation reports of several runs side by side in the layout of the
//! paper's Table 3: for each run, transferability (TPS: `Rac`, `Tac` and AUC at one threshold)
//! and the pose probe (the same three), as percentages. Runs are only comparable when they
//! were evaluated the same way, so their evaluation specs must match.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use settings::evaluation::EvaluationSpec;
use settings::model::PoseConditioning;
use telemetry::bars::BarChart;
use telemetry::plot::Chart;

use crate::error::{EvalError, io_error};
use crate::evaluate::EvaluationReport;
use crate::metrics::{CameraMetrics, THRESHOLDS};

/// One run's report and the name its row gets.
#[derive(Debug, Clone)]
pub struct ComparedRun {
    /// Row label: the one given, or the run folder's name.
    pub label: String,
    /// Where the report was read.
    pub path: PathBuf,
    /// The report.
    pub report: EvaluationReport,
}

/// The measures of each row, in column order.
pub const MEASURES: [&str; 6] = [
    "transfer Rac",
    "transfer Tac",
    "transfer AUC",
    "probe Rac",
    "probe Tac",
    "probe AUC",
];

/// Reads each run (`report.json`, or a folder holding one) and labels it with `labels[i]`
/// when given, else its folder's name. Refuses runs evaluated with a spec other than the
/// first run's, naming both.
pub fn read_runs(paths: &[PathBuf], labels: &[String]) -> Result<Vec<ComparedRun>, EvalError> {
    if paths.is_empty() {
        return Err(EvalError::Invalid("compare needs at least one run".into()));
    }
    if labels.len() > paths.len() {
        return Err(EvalError::Invalid(format!(
            "{} labels for {} runs",
            labels.len(),
            paths.len()
        )));
    }
    let mut runs: Vec<ComparedRun> = Vec::with_capacity(paths.len());
    for (index, given) in paths.iter().enumerate() {
        let path = if given.is_dir() {
            given.join("report.json")
        } else {
            given.clone()
        };
        let bytes = std::fs::read(&path).map_err(|e| io_error(&path, e))?;
        let report: EvaluationReport = serde_json::from_slice(&bytes)
            .map_err(|e| io_error(&path, format!("not an evaluation report: {e}")))?;
        if report.stages.is_empty() {
            return Err(io_error(&path, "the report scores no checkpoint"));
        }
        if let Some(first) = runs.first()
            && !evaluated_alike(&first.report.spec, &report.spec)
        {
            return Err(EvalError::Invalid(format!(
                "{} was evaluated with another spec than {} (seed, scenes, pairs, probe or oracle differ); compare runs evaluated the same way",
                path.display(),
                first.path.display()
            )));
        }
        let label = labels
            .get(index)
            .cloned()
            .unwrap_or_else(|| run_name(&path));
        runs.push(ComparedRun {
            label,
            path,
            report,
        });
    }
    Ok(runs)
}

/// Whether two specs evaluate the same way: every setting but the jobs' notes on their
/// training, which differ between the variants a comparison is for.
fn evaluated_alike(a: &EvaluationSpec, b: &EvaluationSpec) -> bool {
    let without_notes = |spec: &EvaluationSpec| EvaluationSpec {
        notes: Vec::new(),
        ..spec.clone()
    };
    without_notes(a) == without_notes(b)
}

/// The run folder's name: the parent of `report.json`, or the file's stem.
fn run_name(report: &Path) -> String {
    let named = if report.file_name().is_some_and(|n| n == "report.json") {
        report.parent().and_then(Path::file_name)
    } else {
        report.file_stem()
    };
    named.map_or_else(
        || report.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// `Rac`, `Tac` and AUC at `threshold` of `metrics`, as percentages.
fn scores(metrics: &CameraMetrics, threshold: u32) -> [f64; 3] {
    metrics.at(threshold).map_or([f64::NAN; 3], |s| {
        [
            100.0 * s.rotation_accuracy,
            100.0 * s.translation_accuracy,
            100.0 * s.auc,
        ]
    })
}

/// A row's six values in [`MEASURES`] order, of the run's last checkpoint (its final model).
pub fn row(run: &ComparedRun, threshold: u32) -> [f64; 6] {
    let Some(last) = run.report.last() else {
        return [f64::NAN; 6];
    };
    let [a, b, c] = scores(&last.trained.tps.model, threshold);
    let [d, e, f] = scores(&last.trained.probe.metrics, threshold);
    [a, b, c, d, e, f]
}

/// Checks that `threshold` is one the reports score at.
pub fn check_threshold(threshold: u32) -> Result<(), EvalError> {
    if THRESHOLDS.contains(&threshold) {
        Ok(())
    } else {
        Err(EvalError::Invalid(format!(
            "--threshold {threshold}: reports score at {THRESHOLDS:?} degrees only"
        )))
    }
}

/// The Markdown table: a header naming the evaluation data, then one numbered row per run
/// (the numbers match the PNG's legend).
pub fn markdown(runs: &[ComparedRun], threshold: u32) -> String {
    let mut text = String::new();
    if let Some(first) = runs.first() {
        let spec = &first.report.spec;
        let _ = writeln!(
            text,
            "Evaluation: generated scenes (seed {}, {} scenes x {} trajectories), {} TPS pairs ({} oracle), probe on {} held-out scenes ({}); values in %, at {threshold} degrees.\n",
            spec.seed,
            spec.scenes,
            spec.trajectories,
            spec.tps_pairs,
            first
                .report
                .last()
                .map_or("?", |stage| stage.trained.tps.oracle.as_str()),
            spec.probe.test_scenes,
            spec.probe.budget()
        );
    }
    let _ = writeln!(
        text,
        "| # | run | model | transfer Rac@{threshold} | transfer Tac@{threshold} | transfer AUC@{threshold} | probe Rac@{threshold} | probe Tac@{threshold} | probe AUC@{threshold} |"
    );
    let _ = writeln!(text, "|---|---|---|---:|---:|---:|---:|---:|---:|");
    for (index, run) in runs.iter().enumerate() {
        let model = &run.report.model;
        let cells: Vec<String> = row(run, threshold)
            .iter()
            .map(|v| {
                if v.is_finite() {
                    format!("{v:.1}")
                } else {
                    "n/a".into()
                }
            })
            .collect();
        let _ = writeln!(
            text,
            "| {} | {} | C={} h={} L={}+{} Cp={}{} | {} |",
            index + 1,
            run.label,
            model.width,
            model.num_heads,
            model.pose_layers,
            model.render_layers,
            model.pose_dim,
            match model.pose_conditioning {
                PoseConditioning::Latent => "",
                PoseConditioning::PluckerRays => " Plücker",
            },
            cells.join(" | ")
        );
    }
    text
}

/// The bar chart of the same numbers: one group per measure in [`MEASURES`] order, one bar
/// per run.
pub fn chart(runs: &[ComparedRun], threshold: u32) -> BarChart {
    BarChart {
        title: format!("Runs compared at {threshold}°"),
        y_label: "score (%)".into(),
        measures: MEASURES.iter().map(|m| (*m).to_string()).collect(),
        series: runs
            .iter()
            .map(|r| (r.label.clone(), row(r, threshold).to_vec()))
            .collect(),
    }
}

/// Writes `compare.md`, `compare.png` and `compare.svg` into `out` (created if needed); returns the Markdown.
pub fn write_comparison(
    runs: &[ComparedRun],
    threshold: u32,
    out: &Path,
) -> Result<String, EvalError> {
    check_threshold(threshold)?;
    std::fs::create_dir_all(out).map_err(|e| io_error(out, e))?;
    let text = markdown(runs, threshold);
    let md = out.join("compare.md");
    std::fs::write(&md, &text).map_err(|e| io_error(&md, e))?;
    let chart = chart(runs, threshold);
    let png = out.join("compare.png");
    let bytes = chart.to_png().map_err(|e| io_error(&png, e))?;
    std::fs::write(&png, bytes).map_err(|e| io_error(&png, e))?;
    let svg = out.join("compare.svg");
    let document = chart.to_svg().map_err(|e| io_error(&svg, e))?;
    std::fs::write(&svg, document).map_err(|e| io_error(&svg, e))?;
    Ok(text)
}

#[cfg(test)]
mod tests {
    use settings::XFactorConfig;

    use super::*;
    use crate::evaluate::{
        Baselines, CheckpointUnderTest, EvaluationScenes, ModelReport, StageReport,
    };
    use crate::metrics::{PairError, ReconstructionReport};
    use crate::probe::ProbeReport;
    use crate::tps::TpsReport;

    /// Metrics of four pairs: two erring by `degrees`, two by 45 degrees.
    fn metrics(degrees: f64) -> CameraMetrics {
        let mut errors = vec![
            PairError {
                rotation: degrees,
                translation: degrees,
            };
            2
        ];
        errors.extend(
            [PairError {
                rotation: 45.0,
                translation: 45.0,
            }; 2],
        );
        CameraMetrics::from_errors(&errors)
    }

    /// A report whose transfers err by `transfer` degrees and whose probe by `probe` (half
    /// the pairs each; the other half err by 45 degrees).
    fn report(transfer: f64, probe: f64, pose_dim: usize) -> EvaluationReport {
        let mut model = XFactorConfig::tiny(32);
        model.pose_dim = pose_dim;
        let trained = ModelReport {
            reconstruction: ReconstructionReport {
                frames: 1,
                psnr: 20.0,
                ssim: 0.5,
                lpips: None,
                psnr_spread: 0.0,
                ssim_spread: 0.0,
            },
            tps: TpsReport {
                oracle: "ground-truth".into(),
                pairs: 4,
                frames_per_pair: 5,
                skipped: 0,
                failures: 0,
                context_views: 1,
                copied_transfers: 0,
                copy_share: 0.0,
                model: metrics(transfer),
                ideal_transfer: metrics(0.0),
                unrelated_trajectory: metrics(90.0),
            },
            probe: ProbeReport {
                train_samples: 8,
                test_sequences: 1,
                final_loss: 0.1,
                metrics: metrics(probe),
            },
            sequences: Vec::new(),
        };
        let baselines = Baselines {
            copy: trained.reconstruction.clone(),
            mean_colour: trained.reconstruction.clone(),
            tps_no_motion: metrics(90.0),
            probe_no_motion: metrics(90.0),
        };
        EvaluationReport {
            spec: EvaluationSpec::default(),
            scenes: EvaluationScenes {
                split: "test".into(),
                scenes: 6,
                trajectories: 8,
                frames: 8,
                seed: 0,
            },
            model,
            stages: vec![StageReport {
                checkpoint: CheckpointUnderTest {
                    label: "checkpoint1".into(),
                    weights: PathBuf::from("model.safetensors"),
                    step: None,
                    context_views: 1,
                },
                trained,
                untrained: None,
                baselines,
            }],
            departures: Vec::new(),
            figures: Vec::new(),
            seconds: 1.0,
        }
    }

    fn write_run(dir: &Path, name: &str, report: &EvaluationReport) -> PathBuf {
        let run = dir.join(name);
        std::fs::create_dir_all(&run).unwrap();
        std::fs::write(run.join("report.json"), serde_json::to_vec(report).unwrap()).unwrap();
        run
    }

    #[test]
    fn runs_are_rows_in_table_3_layout_with_their_own_numbers() {
        let dir = tempfile::tempdir().unwrap();
        let xfactor = write_run(dir.path(), "xfactor", &report(1.0, 12.0, 8));
        let bottleneck = write_run(dir.path(), "bottleneck", &report(25.0, 2.0, 16));
        let runs = read_runs(&[xfactor, bottleneck.join("report.json")], &[]).unwrap();
        let text = write_comparison(&runs, 20, &dir.path().join("out")).unwrap();
        // Half the pairs under 20 degrees for every measure but the bottleneck's transfer.
        // AUC@20 of errors of 1 degree: histogram bin 1 of 31 (width 30/31) holds half the
        // pairs, so the cumulative share is 0 in bin 0 and 0.5 in bins 1..19: 19/20 * 0.5.
        let auc_of_1_degree = 100.0 * 0.5 * 19.0 / 20.0;
        assert_eq!(row(&runs[0], 20)[..2], [50.0, 50.0]);
        assert!((row(&runs[0], 20)[2] - auc_of_1_degree).abs() < 1e-9);
        assert_eq!(row(&runs[1], 20)[..2], [0.0, 0.0]);
        assert!(text.contains("| 1 | xfactor | C=32 h=2 L=1+1 Cp=8 | 50.0 | 50.0 | 47.5 |"));
        assert!(text.contains("| 2 | bottleneck | C=32 h=2 L=1+1 Cp=16 | 0.0 | 0.0 | 0.0 |"));
        assert_eq!(
            std::fs::read_to_string(dir.path().join("out/compare.md")).unwrap(),
            text
        );
        let png = image::open(dir.path().join("out/compare.png")).unwrap();
        assert!(png.width() > 100);
    }

    #[test]
    fn runs_evaluated_differently_or_a_missing_report_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let first = write_run(dir.path(), "a", &report(1.0, 1.0, 8));
        let mut noted = report(1.0, 1.0, 8);
        noted.spec.notes = vec!["another objective".into()];
        let alike = write_run(dir.path(), "noted", &noted);
        read_runs(&[first.clone(), alike], &[])
            .expect("notes on training are not evaluation settings");
        let mut other = report(1.0, 1.0, 8);
        other.spec.seed = 7;
        let second = write_run(dir.path(), "b", &other);
        let error = read_runs(&[first.clone(), second], &[])
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("b/report.json") && error.contains("a/report.json"),
            "{error}"
        );
        let missing = read_runs(&[first, dir.path().join("c")], &[])
            .unwrap_err()
            .to_string();
        assert!(missing.contains("c"), "{missing}");
        assert!(check_threshold(25).is_err());
    }
}
