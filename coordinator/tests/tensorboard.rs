//! The TensorBoard event files of a real two-worker job, read back by TensorBoard's own
//! `EventAccumulator` (Python, installed by `scripts/setup.sh`; no TensorFlow): every step
//! series of both stages, the resolved configuration as text, and the evaluation's numbers and
//! figures.

mod common;

use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use common::{Running, small_job};
use serde_json::Value;

/// The Python that has the `tensorboard` package: `XFACTOR_TENSORBOARD_PYTHON`, or the
/// virtual environment `scripts/setup.sh` makes in the persistent cache.
fn tensorboard_python() -> PathBuf {
    if let Some(python) = std::env::var_os("XFACTOR_TENSORBOARD_PYTHON") {
        return PathBuf::from(python);
    }
    settings::cache::project_cache().join("tensorboard-env/bin/python")
}

/// What `read_tensorboard.py` finds under `logdir`.
fn read_runs(logdir: &std::path::Path) -> Value {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/read_tensorboard.py");
    let python = tensorboard_python();
    let output = Command::new(&python)
        .arg(&script)
        .arg(logdir)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "{} cannot run (scripts/setup.sh installs it): {e}",
                python.display()
            )
        });
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("JSON from the reader")
}

const STEP_TAGS: [&str; 11] = [
    "loss/total",
    "loss/l1",
    "optimizer/learning_rate",
    "optimizer/grad_norm",
    "optimizer/skipped_steps",
    "time/step_s",
    "time/allreduce_s",
    "time/data_wait_s",
    "time/communication_share",
    "throughput/pairs_per_s",
    "cluster/world_size",
];

#[test]
fn tensorboard_reads_every_step_series_the_configuration_and_the_evaluation() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.evaluate = true;
    let token = job.token();
    let report = Running::start(job).finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let runs = read_runs(&dir.path().join("checkpoints/tensorboard"));
    let names: Vec<&String> = runs.as_object().unwrap().keys().collect();
    assert_eq!(names, ["evaluate", "stage1", "stage2"]);

    let steps = report["steps"].as_array().unwrap();
    for (run, stage, count) in [("stage1", 1, 4), ("stage2", 2, 3)] {
        let scalars = &runs[run]["scalars"];
        for tag in STEP_TAGS {
            let series = scalars[tag]
                .as_array()
                .unwrap_or_else(|| panic!("{run} {tag}"));
            let at: Vec<u64> = series.iter().map(|p| p[0].as_u64().unwrap()).collect();
            assert_eq!(at, (0..count).collect::<Vec<_>>(), "{run} {tag}");
        }
        // The losses are the report's, to f32 precision.
        for point in scalars["loss/total"].as_array().unwrap() {
            let step = point[0].as_u64().unwrap();
            let record = steps
                .iter()
                .find(|r| r["stage"] == stage && r["step"] == step)
                .unwrap();
            let expected = record["loss"].as_f64().unwrap();
            let read = point[1].as_f64().unwrap();
            assert!(
                (read - expected).abs() <= 1e-6 * expected.abs(),
                "{run} step {step}"
            );
            assert!(read > 0.0);
        }
        for point in scalars["cluster/world_size"].as_array().unwrap() {
            assert_eq!(point[1], 2.0);
        }
        for point in scalars["time/communication_share"].as_array().unwrap() {
            let share = point[1].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&share), "{run}: share {share}");
        }
        for point in scalars["throughput/pairs_per_s"].as_array().unwrap() {
            assert!(point[1].as_f64().unwrap() > 0.0);
        }
        assert!(
            scalars.get("loss/lpips").is_none(),
            "the local job trains without LPIPS"
        );
        let config = runs[run]["texts"]["config"][0].as_str().unwrap();
        assert!(config.contains("job: local-demo"), "{config}");
        assert!(config.contains("global_batch"), "{config}");
        assert!(
            config.contains("<redacted>") && !config.contains(token),
            "{config}"
        );
    }

    let evaluation = &runs["evaluate"];
    for model in [
        "stage1/trained/reconstruction",
        "stage2/trained/reconstruction",
        "stage2/untrained/reconstruction",
        "stage2/baselines/copy",
    ] {
        let psnr = &evaluation["scalars"][format!("{model}/psnr")];
        let value = psnr[0][1]
            .as_f64()
            .unwrap_or_else(|| panic!("{model} psnr: {evaluation:#}"));
        assert!(value.is_finite() && value > 0.0);
    }
    let images = evaluation["images"].as_object().unwrap();
    assert!(images.len() >= 2, "{:?}", images.keys());
    for (tag, events) in images {
        let event = &events[0];
        assert_eq!(event["png"], true, "{tag}: {event}");
        assert!(event["width"].as_u64().unwrap() > 10, "{tag}");
    }
}
