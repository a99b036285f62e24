//! The comparison as Markdown: what the runs were evaluated on, the variants' table (Table 3's
//! layout, one row per label), then every run with the figures a transfer claim rests on.

use std::fmt::Write;

use settings::model::PoseConditioning;

use super::{ComparedRun, MEASURES, row, variant_rows};
use crate::metrics::CameraMetrics;

/// The threshold of the per-run table's AUCs: the one the transfer recipe's claim is made at.
const RUN_THRESHOLD: u32 = 30;

/// The Markdown: a header naming the evaluation data, the variants' numbered rows (the numbers
/// match the PNG's legend), then one line per run.
pub fn markdown(runs: &[ComparedRun], threshold: u32) -> String {
    let mut text = String::new();
    if let Some(first) = runs.first() {
        let spec = &first.report.spec;
        let mut seeds: Vec<u64> = runs.iter().map(ComparedRun::seed).collect();
        seeds.sort_unstable();
        seeds.dedup();
        let seeds: Vec<String> = seeds.iter().map(u64::to_string).collect();
        let _ = writeln!(
            text,
            "Evaluation: generated held-out scenes (seeds {}; {} scenes x {} trajectories each), {} TPS pairs ({} oracle), probe on {} held-out scenes ({}); camera scores in %, at {threshold} degrees; the checkpoint compared: {}.\n",
            seeds.join(", "),
            spec.scenes,
            spec.trajectories,
            spec.tps_pairs,
            first.scored().trained.tps.oracle,
            spec.probe.test_scenes,
            spec.probe.budget(),
            first.scored().checkpoint.label,
        );
    }
    variants_table(&mut text, runs, threshold);
    runs_table(&mut text, runs);
    text
}

/// `value ± spread` at one decimal, `value` alone without a spread, `n/a` when not measured.
fn cell(value: f64, spread: Option<f64>, decimals: usize) -> String {
    match (value.is_finite(), spread) {
        (false, _) => "n/a".into(),
        (true, Some(s)) if s.is_finite() => format!("{value:.decimals$} ± {s:.decimals$}"),
        (true, _) => format!("{value:.decimals$}"),
    }
}

/// One numbered row per label: the model, its seeds, and each measure with its spread.
fn variants_table(text: &mut String, runs: &[ComparedRun], threshold: u32) {
    let headers: Vec<String> = MEASURES
        .iter()
        .map(|m| match *m {
            "PSNR" => "PSNR (dB)".to_string(),
            m => format!("{m}@{threshold}"),
        })
        .collect();
    let _ = writeln!(
        text,
        "| # | run | model | seeds | {} |",
        headers.join(" | ")
    );
    let _ = writeln!(text, "|---|---|---|---|{}", "---:|".repeat(MEASURES.len()));
    for (index, variant) in variant_rows(runs).iter().enumerate() {
        let model = &variant.runs[0].report.model;
        let seeds: Vec<String> = variant.runs.iter().map(|r| r.seed().to_string()).collect();
        let cells: Vec<String> = row(variant, threshold)
            .iter()
            .zip(MEASURES)
            .map(|(&(value, spread), measure)| {
                cell(value, spread, if measure == "PSNR" { 2 } else { 1 })
            })
            .collect();
        let _ = writeln!(
            text,
            "| {} | {} | C={} h={} L={}+{} Cp={}{} | {} | {} |",
            index + 1,
            variant.label,
            model.width,
            model.num_heads,
            model.pose_layers,
            model.render_layers,
            model.pose_dim,
            match model.pose_conditioning {
                PoseConditioning::Latent => "",
                PoseConditioning::PluckerRays => " Plücker",
            },
            seeds.join(", "),
            cells.join(" | ")
        );
    }
    let _ = writeln!(
        text,
        "\n`±`: for one seed, the bootstrap spread (over transfers, held-out sequences, frames); for several, the standard deviation over seeds.\n"
    );
}

/// AUC@[`RUN_THRESHOLD`] of `metrics` and its spread, in percent.
fn auc(metrics: &CameraMetrics) -> (f64, Option<f64>) {
    let value = metrics
        .at(RUN_THRESHOLD)
        .map_or(f64::NAN, |s| 100.0 * s.auc);
    (value, metrics.spread.map(|s| 100.0 * s.auc30))
}

/// Every run: its transfers against the unrelated-path calibration (and the lead in their
/// combined spreads), its probe against an untrained model's, its PSNR.
fn runs_table(text: &mut String, runs: &[ComparedRun]) {
    let t = RUN_THRESHOLD;
    let _ = writeln!(
        text,
        "| run | seed | checkpoint | TPS AUC@{t} | unrelated path AUC@{t} | lead (spreads) | probe AUC@{t} | untrained probe AUC@{t} | PSNR (dB) |"
    );
    let _ = writeln!(text, "|---|---:|---|---:|---:|---:|---:|---:|---:|");
    for run in runs {
        let stage = run.scored();
        let (tps, tps_spread) = auc(&stage.trained.tps.model);
        let (unrelated, unrelated_spread) = auc(&stage.trained.tps.unrelated_trajectory);
        let lead = match (tps_spread, unrelated_spread) {
            (Some(a), Some(b)) if a.hypot(b) > 0.0 => {
                format!("{:.1}", (tps - unrelated) / a.hypot(b))
            }
            _ => "n/a".into(),
        };
        let untrained = stage.untrained.as_ref().map_or("n/a".into(), |u| {
            let (value, spread) = auc(&u.probe.metrics);
            cell(value, spread, 1)
        });
        let (probe, probe_spread) = auc(&stage.trained.probe.metrics);
        let reconstruction = &stage.trained.reconstruction;
        let _ = writeln!(
            text,
            "| {} | {} | {} | {} | {} | {lead} | {} | {untrained} | {} |",
            run.label,
            run.seed(),
            stage.checkpoint.label,
            cell(tps, tps_spread, 1),
            cell(unrelated, unrelated_spread, 1),
            cell(probe, probe_spread, 1),
            cell(reconstruction.psnr, Some(reconstruction.psnr_spread), 2),
        );
    }
}
