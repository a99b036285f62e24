//! `xfactor compare`: the evaluation reports of several runs side by side in the layout of the
//! paper's Table 3: for each variant, transferability (TPS: `Rac`, `Tac` and AUC at one
//! threshold), the pose probe (the same three) and reconstruction PSNR, each with its spread.
//! Runs given the same label are seeds of one variant and share a row (their mean, and their
//! standard deviation over seeds); a second table lists every run with its own bootstrap
//! spreads and its transfers' lead over the unrelated-path calibration. Runs are only
//! comparable when they were evaluated the same way: their evaluation specs must match in all
//! but the seed (each seed's held-out scenes are its own) and the notes on training.

mod markdown;

use std::path::{Path, PathBuf};

use settings::evaluation::EvaluationSpec;
use telemetry::bars::BarChart;
use telemetry::plot::Chart;

use crate::error::{EvalError, io_error};
use crate::evaluate::{EvaluationReport, StageReport};
use crate::metrics::{CameraMetrics, THRESHOLDS};

pub use markdown::markdown;

/// One run's report, the checkpoint of it that is compared, and the name its row gets.
#[derive(Debug, Clone)]
pub struct ComparedRun {
    /// Row label: the one given, or the run folder's name.
    pub label: String,
    /// Where the report was read.
    pub path: PathBuf,
    /// The report.
    pub report: EvaluationReport,
    /// Index into `report.stages` of the compared checkpoint.
    pub stage: usize,
}

impl ComparedRun {
    /// The compared checkpoint's numbers.
    pub fn scored(&self) -> &StageReport {
        &self.report.stages[self.stage]
    }

    /// The seed of the held-out scenes this run was evaluated on.
    pub fn seed(&self) -> u64 {
        self.report.spec.seed
    }
}

/// The measures of each row, in column order: six camera scores in percent, then PSNR in dB.
pub const MEASURES: [&str; 7] = [
    "transfer Rac",
    "transfer Tac",
    "transfer AUC",
    "probe Rac",
    "probe Tac",
    "probe AUC",
    "PSNR",
];

/// The measures drawn in the chart (the percentages; PSNR is on another scale).
const CHARTED: usize = 6;

/// Reads each run (`report.json`, or a folder holding one) and labels it with `labels[i]`
/// when given, else its folder's name. `stage` picks the compared checkpoint by its place in
/// each report (1: the first scored, as `xfactor-local`'s stage 1); `None`: the last.
/// Refuses runs evaluated with a spec other than the first run's, naming both.
pub fn read_runs(
    paths: &[PathBuf],
    labels: &[String],
    stage: Option<usize>,
) -> Result<Vec<ComparedRun>, EvalError> {
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
        let stage = compared_stage(&report, stage, &path)?;
        if let Some(first) = runs.first()
            && !evaluated_alike(&first.report.spec, &report.spec)
        {
            return Err(EvalError::Invalid(format!(
                "{} was evaluated with another spec than {} (scenes, pairs, probe or oracle differ); compare runs evaluated the same way",
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
            stage,
        });
    }
    Ok(runs)
}

/// The index of the checkpoint `stage` (1-based; `None`: the last) names in `report`, read
/// from `path`.
fn compared_stage(
    report: &EvaluationReport,
    stage: Option<usize>,
    path: &Path,
) -> Result<usize, EvalError> {
    let scored = report.stages.len();
    match stage {
        _ if scored == 0 => Err(io_error(path, "the report scores no checkpoint")),
        None => Ok(scored - 1),
        Some(n) if (1..=scored).contains(&n) => Ok(n - 1),
        Some(n) => Err(io_error(
            path,
            format!("--stage {n}: the report scores {scored} checkpoint(s)"),
        )),
    }
}

/// Whether two specs evaluate the same way: every setting but the seed (seeds of one variant
/// are each evaluated on their own held-out draws), the jobs' notes on their training, which
/// differ between the variants a comparison is for, and whether an untrained model was scored
/// beside the trained one (it adds rows and changes no trained figure; the table shows n/a).
fn evaluated_alike(a: &EvaluationSpec, b: &EvaluationSpec) -> bool {
    let settings = |spec: &EvaluationSpec| EvaluationSpec {
        notes: Vec::new(),
        seed: 0,
        compare_untrained: false,
        ..spec.clone()
    };
    settings(a) == settings(b)
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

/// The runs under one label: the seeds of one variant, one row of the table.
#[derive(Debug)]
pub struct VariantRow<'a> {
    /// The label they share.
    pub label: &'a str,
    /// Its runs, in the order given.
    pub runs: Vec<&'a ComparedRun>,
}

/// The runs grouped by label, in the order each label first appears.
pub fn variant_rows(runs: &[ComparedRun]) -> Vec<VariantRow<'_>> {
    let mut rows: Vec<VariantRow<'_>> = Vec::new();
    for run in runs {
        match rows.iter_mut().find(|row| row.label == run.label) {
            Some(row) => row.runs.push(run),
            None => rows.push(VariantRow {
                label: &run.label,
                runs: vec![run],
            }),
        }
    }
    rows
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

/// The bootstrap spread of `metrics`'s AUC at `threshold`, in percent, where one was measured.
fn auc_spread(metrics: &CameraMetrics, threshold: u32) -> Option<f64> {
    let spread = metrics.spread?;
    match threshold {
        20 => Some(100.0 * spread.auc20),
        30 => Some(100.0 * spread.auc30),
        _ => None,
    }
}

/// One run's values in [`MEASURES`] order, of its compared checkpoint.
pub fn run_values(run: &ComparedRun, threshold: u32) -> [f64; 7] {
    let trained = &run.scored().trained;
    let [a, b, c] = scores(&trained.tps.model, threshold);
    let [d, e, f] = scores(&trained.probe.metrics, threshold);
    [a, b, c, d, e, f, trained.reconstruction.psnr]
}

/// One run's bootstrap spreads in [`MEASURES`] order, where measured (the AUCs at 20 and 30
/// degrees, PSNR).
pub fn run_spreads(run: &ComparedRun, threshold: u32) -> [Option<f64>; 7] {
    let trained = &run.scored().trained;
    [
        None,
        None,
        auc_spread(&trained.tps.model, threshold),
        None,
        None,
        auc_spread(&trained.probe.metrics, threshold),
        Some(trained.reconstruction.psnr_spread),
    ]
}

/// A row's value of each measure with its spread: one run's value and bootstrap spread, or
/// several runs' mean and standard deviation over them.
pub fn row(row: &VariantRow<'_>, threshold: u32) -> [(f64, Option<f64>); 7] {
    let values: Vec<[f64; 7]> = row.runs.iter().map(|r| run_values(r, threshold)).collect();
    if let [only] = row.runs.as_slice() {
        let spreads = run_spreads(only, threshold);
        return std::array::from_fn(|m| (values[0][m], spreads[m]));
    }
    std::array::from_fn(|m| {
        let column: Vec<f64> = values.iter().map(|v| v[m]).collect();
        let (mean, sd) = mean_and_sd(&column);
        (mean, Some(sd))
    })
}

/// The mean and the sample standard deviation of `values` (at least two).
fn mean_and_sd(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let variance = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, variance.sqrt())
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

/// The bar chart of the rows' camera scores: one group per measure, one bar per variant.
pub fn chart(runs: &[ComparedRun], threshold: u32) -> BarChart {
    BarChart {
        title: format!("Runs compared at {threshold}°"),
        y_label: "score (%)".into(),
        measures: MEASURES[..CHARTED]
            .iter()
            .map(|m| (*m).to_string())
            .collect(),
        series: variant_rows(runs)
            .iter()
            .map(|r| {
                let values = row(r, threshold);
                (
                    r.label.to_string(),
                    values[..CHARTED].iter().map(|v| v.0).collect(),
                )
            })
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

    /// `report` evaluated on the held-out scenes of `seed`.
    fn seeded(mut report: EvaluationReport, seed: u64) -> EvaluationReport {
        report.spec.seed = seed;
        report
    }

    #[test]
    fn runs_are_rows_in_table_3_layout_with_their_own_numbers() {
        let dir = tempfile::tempdir().unwrap();
        let xfactor = write_run(dir.path(), "xfactor", &report(1.0, 12.0, 8));
        let bottleneck = write_run(dir.path(), "bottleneck", &report(25.0, 2.0, 16));
        let runs = read_runs(&[xfactor, bottleneck.join("report.json")], &[], None).unwrap();
        let text = write_comparison(&runs, 20, &dir.path().join("out")).unwrap();
        // Half the pairs under 20 degrees for every measure but the bottleneck's transfer.
        // AUC@20 of errors of 1 degree: histogram bin 1 of 31 (width 30/31) holds half the
        // pairs, so the cumulative share is 0 in bin 0 and 0.5 in bins 1..19: 19/20 * 0.5.
        let auc_of_1_degree = 100.0 * 0.5 * 19.0 / 20.0;
        assert_eq!(run_values(&runs[0], 20)[..2], [50.0, 50.0]);
        assert!((run_values(&runs[0], 20)[2] - auc_of_1_degree).abs() < 1e-9);
        assert_eq!(run_values(&runs[1], 20)[..2], [0.0, 0.0]);
        assert!(text.contains(
            "| 1 | xfactor | C=32 h=2 L=1+1 Cp=8 | 0 | 50.0 | 50.0 | 47.5 | 50.0 | 50.0 |"
        ));
        assert!(text.contains("| 2 | bottleneck | C=32 h=2 L=1+1 Cp=16 | 0 | 0.0 | 0.0 | 0.0 |"));
        assert!(
            text.contains("| 20.00 ± 0.00 |"),
            "PSNR with its spread:\n{text}"
        );
        assert_eq!(
            std::fs::read_to_string(dir.path().join("out/compare.md")).unwrap(),
            text
        );
        let png = image::open(dir.path().join("out/compare.png")).unwrap();
        assert!(png.width() > 100);
    }

    #[test]
    fn seeds_of_one_label_share_a_row_with_their_mean_and_deviation() {
        let dir = tempfile::tempdir().unwrap();
        // Transfers erring by 1 and 25 degrees: Tac@20 of 50% and 0%.
        let a = write_run(dir.path(), "a", &seeded(report(1.0, 1.0, 8), 8));
        let b = write_run(dir.path(), "b", &seeded(report(25.0, 1.0, 8), 9));
        let labels = ["XFactor".to_string(), "XFactor".to_string()];
        let runs = read_runs(&[a, b], &labels, None).unwrap();
        let rows = variant_rows(&runs);
        assert_eq!(rows.len(), 1);
        let values = row(&rows[0], 20);
        // Mean 25, sample standard deviation sqrt(2 * 25^2) = 35.36.
        assert_eq!(values[1].0, 25.0);
        assert!((values[1].1.unwrap() - 35.355).abs() < 1e-3, "{values:?}");
        let text = markdown(&runs, 20);
        assert!(
            text.contains(
                "| 1 | XFactor | C=32 h=2 L=1+1 Cp=8 | 8, 9 | 25.0 ± 35.4 | 25.0 ± 35.4 |"
            ),
            "{text}"
        );
        assert!(text.contains("seeds 8, 9"), "{text}");
        // Each run keeps its own line, seed and checkpoint.
        assert!(text.contains("| XFactor | 8 | checkpoint1 |"), "{text}");
        assert!(text.contains("| XFactor | 9 | checkpoint1 |"), "{text}");
    }

    #[test]
    fn a_run_line_states_the_lead_over_the_unrelated_path_in_spreads() {
        let dir = tempfile::tempdir().unwrap();
        let mut transfer = report(1.0, 1.0, 8);
        let tps = &mut transfer.stages[0].trained.tps;
        tps.model.spread = Some(crate::metrics::CameraSpread {
            auc20: 0.0,
            auc30: 0.03,
        });
        tps.unrelated_trajectory.spread = Some(crate::metrics::CameraSpread {
            auc20: 0.0,
            auc30: 0.04,
        });
        let auc30 = |m: &CameraMetrics| 100.0 * m.at(30).unwrap().auc;
        let lead = (auc30(&tps.model) - auc30(&tps.unrelated_trajectory)) / 5.0;
        let run = write_run(dir.path(), "xfactor", &transfer);
        let text = markdown(&read_runs(&[run], &[], None).unwrap(), 20);
        assert!(
            text.contains(&format!(" | {lead:.1} | ")),
            "lead {lead}:\n{text}"
        );
    }

    #[test]
    fn stage_picks_the_checkpoint_compared_and_names_a_missing_one() {
        let dir = tempfile::tempdir().unwrap();
        let mut two = report(1.0, 1.0, 8);
        let mut second = report(25.0, 1.0, 8).stages.remove(0);
        second.checkpoint.label = "stage2".into();
        two.stages.push(second);
        let run = write_run(dir.path(), "two", &two);
        let first = read_runs(std::slice::from_ref(&run), &[], Some(1)).unwrap();
        assert_eq!(first[0].scored().checkpoint.label, "checkpoint1");
        let last = read_runs(std::slice::from_ref(&run), &[], None).unwrap();
        assert_eq!(last[0].scored().checkpoint.label, "stage2");
        let error = read_runs(&[run], &[], Some(3)).unwrap_err().to_string();
        assert!(
            error.contains("--stage 3") && error.contains("2 checkpoint") && error.contains("two"),
            "{error}"
        );
    }

    #[test]
    fn runs_evaluated_differently_or_a_missing_report_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let first = write_run(dir.path(), "a", &report(1.0, 1.0, 8));
        let mut noted = seeded(report(1.0, 1.0, 8), 7);
        noted.spec.notes = vec!["another objective".into()];
        noted.spec.compare_untrained = !noted.spec.compare_untrained;
        let alike = write_run(dir.path(), "noted", &noted);
        read_runs(&[first.clone(), alike], &[], None).expect(
            "notes on training, the seed and the untrained comparison are not evaluation settings",
        );
        let mut other = report(1.0, 1.0, 8);
        other.spec.scenes += 1;
        let second = write_run(dir.path(), "b", &other);
        let error = read_runs(&[first.clone(), second], &[], None)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("b/report.json") && error.contains("a/report.json"),
            "{error}"
        );
        let missing = read_runs(&[first, dir.path().join("c")], &[], None)
            .unwrap_err()
            .to_string();
        assert!(missing.contains("c"), "{missing}");
        assert!(check_threshold(25).is_err());
    }
}
