//! `report.md`: the evaluation as tables a reviewer reads top to bottom: what was scored on
//! what, then per checkpoint the model beside its untrained twin and the pose-free baselines,
//! each figure with its spread.

use std::fmt::Write as _;

use super::{EvaluationReport, ModelReport, StageReport};
use crate::metrics::{CameraMetrics, ReconstructionReport};

fn camera_cells(metrics: &CameraMetrics) -> String {
    let at =
        |t: u32, f: fn(&crate::metrics::ThresholdScores) -> f64| metrics.at(t).map_or(f64::NAN, f);
    let optional = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{v:.3}"));
    let spread = metrics
        .spread
        .map_or_else(|| "-".to_string(), |s| format!("{:.3}", s.auc30));
    format!(
        "{:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {spread} | {} | {}",
        at(5, |s| s.rotation_accuracy),
        at(5, |s| s.translation_accuracy),
        at(20, |s| s.rotation_auc),
        at(20, |s| s.translation_auc),
        at(20, |s| s.auc),
        at(30, |s| s.auc),
        optional(metrics.trajectory_error_scale_invariant),
        optional(metrics.trajectory_error_unscaled),
    )
}

fn reconstruction_cells(r: &ReconstructionReport) -> String {
    let lpips = r.lpips.map_or("-".to_string(), |v| format!("{v:.4}"));
    format!(
        "{} | {:.2} ± {:.2} | {:.4} ± {:.4} | {lpips}",
        r.frames, r.psnr, r.psnr_spread, r.ssim, r.ssim_spread
    )
}

/// The models of a stage's rows: the checkpoint, then its untrained twin.
fn models(stage: &StageReport) -> Vec<(&'static str, &ModelReport)> {
    let mut rows = vec![("trained", &stage.trained)];
    if let Some(untrained) = &stage.untrained {
        rows.push(("untrained", untrained));
    }
    rows
}

/// A stage's name as its rows show it: label, step and context views.
fn stage_name(stage: &StageReport) -> String {
    let c = &stage.checkpoint;
    let step = c.step.map_or_else(String::new, |s| format!(" step {s}"));
    format!("{}{step}, {} context view(s)", c.label, c.context_views)
}

fn reconstruction_table(report: &EvaluationReport, text: &mut String) {
    text.push_str("## Reconstruction (autoencoding)\n\nTargets are the frames that are not context views; baselines render the same targets.\n\n| checkpoint | renderer | frames | PSNR ± spread | SSIM ± spread | LPIPS |\n| --- | --- | --- | --- | --- | --- |\n");
    for stage in &report.stages {
        let name = stage_name(stage);
        for (model, r) in models(stage) {
            let cells = reconstruction_cells(&r.reconstruction);
            let _ = writeln!(text, "| {name} | {model} | {cells} |");
        }
        let b = &stage.baselines;
        for (baseline, r) in [
            ("copy nearest context", &b.copy),
            ("mean colour", &b.mean_colour),
        ] {
            let _ = writeln!(
                text,
                "| {name} | {baseline} | {} |",
                reconstruction_cells(r)
            );
        }
        let (best, r) = b.best_reconstruction();
        let _ = writeln!(
            text,
            "| {name} | **lead over {best}** | | {:+.2} dB | {:+.4} | |",
            stage.trained.reconstruction.psnr - r.psnr,
            stage.trained.reconstruction.ssim - r.ssim
        );
    }
}

fn camera_table(report: &EvaluationReport, text: &mut String) {
    let _ = write!(
        text,
        "\n## Transferability (TPS) and pose probe\n\n`±` is the bootstrap spread of SE3_Auc@30 over transfers (TPS) or held-out sequences (probe). The probe: {}.\n\n",
        report.spec.probe.budget()
    );
    text.push_str("| checkpoint | model | measure | Rac@5 | Tac@5 | Rot_Auc@20 | Trans_Auc@20 | SE3_Auc@20 | SE3_Auc@30 | ± | traj err (scale-inv.) | traj err (unscaled) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
    for stage in &report.stages {
        let name = stage_name(stage);
        for (model, r) in models(stage) {
            let _ = writeln!(
                text,
                "| {name} | {model} | TPS | {} |",
                camera_cells(&r.tps.model)
            );
            let _ = writeln!(
                text,
                "| {name} | {model} | probe | {} |",
                camera_cells(&r.probe.metrics)
            );
        }
        let (b, tps) = (&stage.baselines, &stage.trained.tps);
        let references = [
            ("no camera motion", "TPS", &b.tps_no_motion),
            ("no camera motion", "probe", &b.probe_no_motion),
            ("oracle: true rendering", "TPS", &tps.ideal_transfer),
            ("oracle: unrelated motion", "TPS", &tps.unrelated_trajectory),
        ];
        for (model, measure, metrics) in references {
            let cells = camera_cells(metrics);
            let _ = writeln!(text, "| {name} | {model} | {measure} | {cells} |");
        }
    }
    text.push_str("\nTransfers that copy the source video (most renders closer to the source's frames than to the target scene's) score as failed:\n\n| checkpoint | model | transfers | copied | renders copying the source | unreadable by the oracle |\n| --- | --- | --- | --- | --- | --- |\n");
    for stage in &report.stages {
        let name = stage_name(stage);
        for (model, r) in models(stage) {
            let t = &r.tps;
            let _ = writeln!(
                text,
                "| {name} | {model} | {} | {} | {:.1}% | {} |",
                t.pairs,
                t.copied_transfers,
                100.0 * t.copy_share,
                t.failures
            );
        }
    }
}

fn sequences_table(report: &EvaluationReport, text: &mut String) {
    if report.stages.iter().all(|s| s.trained.sequences.is_empty()) {
        return;
    }
    text.push_str("\n## Real test sequences (E-RayZer's protocol: fixed length, equally spaced frames, first and last included)\n\n| checkpoint | model | dataset | length | sequences | skipped (short) | frames | PSNR ± spread | SSIM ± spread | LPIPS |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
    for stage in &report.stages {
        let name = stage_name(stage);
        for (model, r) in models(stage) {
            for set in &r.sequences {
                let _ = writeln!(
                    text,
                    "| {name} | {model} | {} | {} | {} | {} | {} |",
                    set.kind.name(),
                    set.length,
                    set.sequences,
                    set.skipped_short,
                    reconstruction_cells(&set.reconstruction)
                );
            }
        }
    }
}

/// The report as Markdown: what was scored on what, then the tables and the figures.
pub fn markdown(report: &EvaluationReport) -> String {
    let s = &report.scenes;
    let mut text = format!(
        "# XFactor evaluation\n\nHeld-out scenes (split `{}`): {} scenes x {} camera paths x {} frames, seed {}; {:.1} s.\n\n",
        s.split, s.scenes, s.trajectories, s.frames, s.seed, report.seconds
    );
    for stage in &report.stages {
        let _ = writeln!(
            text,
            "- `{}`: `{}`",
            stage_name(stage),
            stage.checkpoint.weights.display()
        );
    }
    text.push_str("\nDepartures from the release (evaluation, then training):\n\n");
    for note in &report.departures {
        let _ = writeln!(text, "- {note}");
    }
    text.push('\n');
    reconstruction_table(report, &mut text);
    camera_table(report, &mut text);
    sequences_table(report, &mut text);
    text.push_str("\n## Figures\n\n");
    for figure in &report.figures {
        let _ = writeln!(text, "![{figure}]({figure})");
    }
    text
}
