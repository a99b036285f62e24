//! The README's first run (`scripts/run.sh`, `LocalJob::demo`): two workers on generated data,
//! both stages, then the evaluation of both stages' final weights on held-out scenes. Guards
//! that what the run learns holds on scenes no training step read: for stage 1 (one context
//! view) and stage 2 (two), the trained model leads the best pose-free baseline on
//! reconstruction PSNR (copy the nearest context view, or paint its mean colour), on TPS
//! SE3_Auc@30 (no camera motion) and on the probe's SE3_Auc@30 (no camera motion), and leads
//! the untrained model on PSNR and TPS.
//!
//! Margins: each lead must exceed the larger of a floor and [`SPREADS`] times its spread (the
//! bootstrap spreads of the two figures the report prints, combined as independent:
//! `sqrt(a^2 + b^2)`). Measured
//! on this 2-core machine on 2026-11-26 with two workers (and, in brackets, one worker, whose
//! different float sums take training down another path): PSNR leads over the best baseline
//! 1.53 dB [1.52] at stage 1 and 0.65 dB [0.62] at stage 2 with spreads of 0.13-0.18 dB per
//! figure; TPS AUC@30 0.081 [0.102] and 0.072 [0.091] against 0 for no motion and the untrained
//! model, spreads 0.012-0.014; probe AUC@30 0.168 [0.156] and 0.160 [0.157], spreads
//! 0.018-0.026. The two runs agree within about one combined spread on every figure. The floors
//! sit under the smallest measured lead and above two spreads: 0.3 dB, 0.03 and 0.05.
//!
//! Not guarded, because it does not hold and the README says so: the probe does not beat an
//! untrained model's random features on held-out scenes (0.168 vs 0.212 at stage 1), and TPS
//! stays below the oracle's unrelated-trajectory calibration (0.144). About three minutes on
//! 2 cores.

mod common;

use std::time::Duration;

use common::Running;
use coordinator::local::{LocalJob, figures, free_port};
use serde_json::Value;

/// Spreads a lead must exceed.
const SPREADS: f64 = 2.0;

/// `SE3_Auc@30` of a camera-metrics object of the report, with its spread.
fn auc30(metrics: &Value) -> (f64, f64) {
    figures::auc30(metrics).unwrap_or_else(|| panic!("no AUC@30 or its spread in {metrics}"))
}

/// A reconstruction's PSNR with its spread.
fn psnr(reconstruction: &Value) -> (f64, f64) {
    figures::psnr(reconstruction)
        .unwrap_or_else(|| panic!("no psnr or psnr_spread in {reconstruction}"))
}

/// One lead the guard asserts: what, ours and theirs (value, spread), and the floor.
struct Lead {
    name: String,
    ours: (f64, f64),
    theirs: (f64, f64),
    floor: f64,
}

impl Lead {
    /// Why the lead is short of its margin, if it is.
    fn shortfall(&self) -> Option<String> {
        let lead = self.ours.0 - self.theirs.0;
        let spread = self.ours.1.hypot(self.theirs.1);
        let margin = self.floor.max(SPREADS * spread);
        println!(
            "{}: ours {:.4} theirs {:.4} lead {lead:.4} spread {spread:.4} margin {margin:.4}",
            self.name, self.ours.0, self.theirs.0
        );
        (lead < margin).then(|| {
            format!(
                "{}: ours {:.4} vs {:.4}, lead {lead:.4} < margin {margin:.4}",
                self.name, self.ours.0, self.theirs.0
            )
        })
    }
}

/// Every lead of one scored stage.
fn leads(stage: &Value) -> Vec<Lead> {
    let label = stage["checkpoint"]["label"].as_str().unwrap_or("?");
    let (trained, untrained, baselines) =
        (&stage["trained"], &stage["untrained"], &stage["baselines"]);
    let (copy, mean_colour) = (psnr(&baselines["copy"]), psnr(&baselines["mean_colour"]));
    let best = if copy.0 >= mean_colour.0 {
        copy
    } else {
        mean_colour
    };
    let ours = psnr(&trained["reconstruction"]);
    let tps = auc30(&trained["tps"]["model"]);
    let lead = |name: &str, ours, theirs, floor| Lead {
        name: format!("{label} {name}"),
        ours,
        theirs,
        floor,
    };
    vec![
        lead("PSNR over the best baseline", ours, best, 0.3),
        lead(
            "PSNR over the untrained model",
            ours,
            psnr(&untrained["reconstruction"]),
            3.0,
        ),
        lead(
            "TPS AUC@30 over no motion",
            tps,
            auc30(&baselines["tps_no_motion"]),
            0.03,
        ),
        lead(
            "TPS AUC@30 over the untrained model",
            tps,
            auc30(&untrained["tps"]["model"]),
            0.03,
        ),
        lead(
            "probe AUC@30 over no motion",
            auc30(&trained["probe"]["metrics"]),
            auc30(&baselines["probe_no_motion"]),
            0.05,
        ),
    ]
}

#[test]
fn the_first_run_leads_every_baseline_on_held_out_scenes_at_both_stages() {
    let dir = tempfile::tempdir().unwrap();
    let job = LocalJob::demo(dir.path(), free_port().unwrap());
    let report = Running::start(job).finish(Duration::from_secs(900));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let location = std::path::Path::new(report["evaluation"].as_str().expect("an evaluation"));
    let numbers: Value =
        serde_json::from_slice(&std::fs::read(location.join("report.json")).unwrap()).unwrap();
    assert_eq!(numbers["scenes"]["split"], "test", "held-out scenes");
    let stages = numbers["stages"].as_array().expect("scored stages");
    let scored: Vec<(&str, u64)> = stages
        .iter()
        .map(|s| {
            let checkpoint = &s["checkpoint"];
            let views = checkpoint["context_views"].as_u64().unwrap_or(0);
            (checkpoint["label"].as_str().unwrap_or("?"), views)
        })
        .collect();
    assert_eq!(
        scored,
        [("stage1", 1), ("stage2", 2)],
        "each stage as it trained"
    );
    let short: Vec<String> = stages
        .iter()
        .flat_map(leads)
        .filter_map(|lead| lead.shortfall())
        .collect();
    assert!(
        short.is_empty(),
        "not ahead by the margin:\n{}",
        short.join("\n")
    );
}
