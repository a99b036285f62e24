//! The README's first run (`scripts/run.sh`, `LocalJob::demo`): two workers on generated data,
//! both stages, then the evaluation. Guards that it visibly learns: the trained model is ahead
//! of the untrained one on every number the run prints (reconstruction PSNR and SSIM, TPS and
//! pose-probe AUC@30), each by a stated margin. The run is deterministic (every draw derives
//! from the seed); about two and a half minutes on 2 cores.

mod common;

use std::time::Duration;

use common::Running;
use coordinator::local::{LocalJob, free_port};
use serde_json::Value;

/// A reported number: its name, how to read it from one model's report, and the margin by
/// which the trained model must lead.
type Measure = (&'static str, fn(&Value) -> f64, f64);

/// AUC@30 of a metrics object of the evaluation report.
fn auc30(metrics: &Value) -> f64 {
    metrics["thresholds"]
        .as_array()
        .and_then(|t| t.iter().find(|s| s["threshold"] == 30))
        .and_then(|s| s["auc"].as_f64())
        .unwrap_or_else(|| panic!("no AUC@30 in {metrics}"))
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
    let (trained, untrained) = (&numbers["trained"], &numbers["untrained"]);
    let measures: [Measure; 4] = [
        (
            "reconstruction PSNR (dB)",
            |m| m["reconstruction"]["psnr"].as_f64().unwrap(),
            3.0,
        ),
        (
            "reconstruction SSIM",
            |m| m["reconstruction"]["ssim"].as_f64().unwrap(),
            0.2,
        ),
        ("TPS AUC@30", |m| auc30(&m["tps"]["model"]), 0.05),
        ("probe AUC@30", |m| auc30(&m["probe"]["metrics"]), 0.015),
    ];
    let mut figures = Vec::new();
    for (name, read, margin) in measures {
        let (ours, baseline) = (read(trained), read(untrained));
        figures.push(format!("{name}: {ours:.3} vs {baseline:.3}"));
        assert!(
            ours >= baseline + margin,
            "{name}: trained {ours:.4} is not ahead of untrained {baseline:.4} by {margin}"
        );
    }
    println!("{}", figures.join("; "));
}
