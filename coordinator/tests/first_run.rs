//! The README's first run (`scripts/run.sh`, `LocalJob::demo`): two workers on generated data,
//! both stages, then the evaluation. Guards that it visibly learns: the trained model is ahead
//! of the untrained one on every number of the evaluation report (reconstruction PSNR and SSIM;
//! for TPS and for the pose probe Rac@5, Tac@5, the rotation, translation and SE(3) AUCs, and
//! the trajectory errors), each by a stated margin. The run is deterministic (every draw
//! derives from the seed); about two and a half minutes on 2 cores.

mod common;

use std::time::Duration;

use common::Running;
use coordinator::local::{LocalJob, free_port};
use serde_json::Value;

/// Whether a larger number is better.
#[derive(Clone, Copy, PartialEq)]
enum Better {
    Higher,
    Lower,
}

/// The scores at `threshold` degrees of a metrics object of the evaluation report.
fn at(metrics: &Value, threshold: u64) -> &Value {
    metrics["thresholds"]
        .as_array()
        .and_then(|t| t.iter().find(|s| s["threshold"] == threshold))
        .unwrap_or_else(|| panic!("no scores at {threshold} degrees in {metrics}"))
}

fn number(value: &Value) -> f64 {
    value
        .as_f64()
        .unwrap_or_else(|| panic!("{value} is not a number"))
}

/// Every camera measure of the report's table for `metrics`, named after `label`: its value,
/// which direction is better and the margin the trained model must lead by.
fn camera_measures(
    label: &str,
    metrics: &Value,
    se3_margin: f64,
) -> Vec<(String, f64, Better, f64)> {
    let twenty = at(metrics, 20);
    vec![
        (
            format!("{label} Rac@5"),
            number(&at(metrics, 5)["rotation_accuracy"]),
            Better::Higher,
            0.01,
        ),
        (
            format!("{label} Tac@5"),
            number(&at(metrics, 5)["translation_accuracy"]),
            Better::Higher,
            0.01,
        ),
        (
            format!("{label} Rot_Auc@20"),
            number(&twenty["rotation_auc"]),
            Better::Higher,
            0.01,
        ),
        (
            format!("{label} Trans_Auc@20"),
            number(&twenty["translation_auc"]),
            Better::Higher,
            0.01,
        ),
        (
            format!("{label} SE3_Auc@20"),
            number(&twenty["auc"]),
            Better::Higher,
            0.01,
        ),
        (
            format!("{label} SE3_Auc@30"),
            number(&at(metrics, 30)["auc"]),
            Better::Higher,
            se3_margin,
        ),
        (
            format!("{label} trajectory error (scale-invariant)"),
            number(&metrics["trajectory_error_scale_invariant"]),
            Better::Lower,
            0.01,
        ),
        (
            format!("{label} trajectory error (unscaled)"),
            number(&metrics["trajectory_error_unscaled"]),
            Better::Lower,
            0.01,
        ),
    ]
}

/// Every measure of one model's report.
fn measures(model: &Value) -> Vec<(String, f64, Better, f64)> {
    let reconstruction = &model["reconstruction"];
    let mut all = vec![
        (
            "reconstruction PSNR (dB)".to_string(),
            number(&reconstruction["psnr"]),
            Better::Higher,
            3.0,
        ),
        (
            "reconstruction SSIM".to_string(),
            number(&reconstruction["ssim"]),
            Better::Higher,
            0.2,
        ),
    ];
    all.extend(camera_measures("TPS", &model["tps"]["model"], 0.05));
    all.extend(camera_measures("probe", &model["probe"]["metrics"], 0.015));
    all
}

#[test]
fn the_first_run_puts_the_trained_model_ahead_on_every_metric() {
    let dir = tempfile::tempdir().unwrap();
    let job = LocalJob::demo(dir.path(), free_port().unwrap());
    let report = Running::start(job).finish(Duration::from_secs(900));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let location = std::path::Path::new(report["evaluation"].as_str().expect("an evaluation"));
    let numbers: Value =
        serde_json::from_slice(&std::fs::read(location.join("report.json")).unwrap()).unwrap();
    let trained = measures(&numbers["trained"]);
    let untrained = measures(&numbers["untrained"]);
    assert_eq!(trained.len(), 18);
    let mut behind = Vec::new();
    for ((name, ours, better, margin), (_, baseline, _, _)) in trained.iter().zip(&untrained) {
        println!("{name}: trained {ours:.4} untrained {baseline:.4}");
        let lead = match better {
            Better::Higher => ours - baseline,
            Better::Lower => baseline - ours,
        };
        if lead < *margin {
            behind.push(format!(
                "{name}: trained {ours:.4} vs untrained {baseline:.4}, lead {lead:.4} < {margin}"
            ));
        }
    }
    assert!(
        behind.is_empty(),
        "not ahead by the margin:\n{}",
        behind.join("\n")
    );
}
