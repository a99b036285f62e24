//! The paper's Table 3 in miniature: five tiny variants (XFactor's transfer objective, plain
//! autoencoding, autoencoding through a smaller pose latent, an extra view for PoseEnc and
//! Render, and explicit cameras with Plücker-ray conditioning) trained and evaluated through
//! the local harness, then laid side by side by `xfactor compare`; and a job that stops after
//! stage 1, the checkpoint the table compares.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use common::{Running, small_job};
use settings::objective::ObjectiveVariant;

/// The variants in the table's order: run name, objective, and the pose latent the run asks for
/// (`None`: the model's default).
const VARIANTS: [(&str, ObjectiveVariant, Option<usize>); 5] = [
    ("xfactor", ObjectiveVariant::Transfer, None),
    ("unconstrained", ObjectiveVariant::Autoencode, None),
    ("bottleneck", ObjectiveVariant::Autoencode, Some(4)),
    (
        "extra-view",
        ObjectiveVariant::ExtraViewEncoderDecoder,
        None,
    ),
    ("se3-plucker", ObjectiveVariant::Se3Plucker, None),
];

#[test]
fn five_variants_train_evaluate_and_compare_in_one_table() {
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let mut evaluations: Vec<PathBuf> = Vec::new();
    let mut stage1_weights = Vec::new();
    for (name, variant, pose_dim) in VARIANTS {
        let (evaluation, weights) = train_and_evaluate(dir.path(), name, variant, pose_dim);
        evaluations.push(evaluation);
        stage1_weights.push(weights);
    }
    // Same seed, same data, same initial weights: only the objective differs.
    assert_ne!(
        stage1_weights[0], stage1_weights[1],
        "the autoencoding run trained differently from the transfer run"
    );
    let out = dir.path().join("compare");
    let table = compare(&evaluations, &out);
    println!(
        "variants=5 seconds={:.1}\n{table}",
        started.elapsed().as_secs_f64()
    );
    for (row, (label, pose_dim)) in [
        ("XFactor", "8"),
        ("Unconstrained", "8"),
        ("Bottleneck", "4"),
        ("ExtraView", "8"),
        ("SE3Plucker", "10 Plücker"),
    ]
    .iter()
    .enumerate()
    {
        let line = format!("| {} | {label} | C=32 h=2 L=1+1 Cp={pose_dim} |", row + 1);
        assert!(table.contains(&line), "{line} missing from\n{table}");
    }
    assert_eq!(
        std::fs::read_to_string(out.join("compare.md")).unwrap(),
        table
    );
    assert!(image::open(out.join("compare.png")).unwrap().width() > 0);
}

#[test]
fn a_job_stopping_after_stage_1_trains_and_evaluates_stage_1_alone() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_only = true;
    job.evaluate = true;
    let checkpoints = job.checkpoint_dir();
    let report = Running::start(job).finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let stages: Vec<&serde_json::Value> = report["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|step| &step["stage"])
        .collect();
    assert_eq!(stages, vec![&serde_json::json!(1); 4], "{report:#}");
    assert!(common::commits(&report, 2).is_empty(), "{report:#}");
    let evaluation = PathBuf::from(report["evaluation"].as_str().expect("an evaluation"));
    let numbers: serde_json::Value =
        serde_json::from_slice(&std::fs::read(evaluation.join("report.json")).unwrap()).unwrap();
    let scored: Vec<&str> = numbers["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|stage| stage["checkpoint"]["label"].as_str().unwrap_or("?"))
        .collect();
    assert_eq!(scored, ["stage1"]);
    assert!(checkpoints.join("curves/stage1.csv").exists());
    assert!(!checkpoints.join("curves/stage2.csv").exists());
}

/// Trains and evaluates one tiny variant under `root/name`, checking that its evaluation
/// report names the model it trained. Returns the evaluation's folder and stage 1's final
/// weights, flattened in name order.
fn train_and_evaluate(
    root: &Path,
    name: &str,
    variant: ObjectiveVariant,
    pose_dim: Option<usize>,
) -> (PathBuf, Vec<f32>) {
    let mut job = small_job(&root.join(name), 1);
    job.stage1_steps = 6;
    job.stage2_steps = 2;
    job.checkpoint_every = 6;
    job.evaluate = true;
    job.objective_variant = Some(variant);
    job.pose_dim = pose_dim;
    let report = Running::start(job).finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{name}: {report:#}");
    let evaluation = PathBuf::from(report["evaluation"].as_str().expect("an evaluation"));
    let numbers: serde_json::Value =
        serde_json::from_slice(&std::fs::read(evaluation.join("report.json")).unwrap()).unwrap();
    let camera = variant == ObjectiveVariant::Se3Plucker;
    assert_eq!(
        numbers["model"]["pose_dim"],
        pose_dim.unwrap_or(if camera { 10 } else { 8 }),
        "{name}"
    );
    assert_eq!(
        numbers["model"]["pose_conditioning"],
        if camera { "plucker_rays" } else { "latent" },
        "{name}"
    );
    let stage1 = common::load_weights(report["stage1_final"].as_str().unwrap());
    let mut names: Vec<&str> = stage1.names_with_prefix("").collect();
    names.sort_unstable();
    let values: Vec<f32> = names
        .iter()
        .flat_map(|n| stage1.get(n).unwrap().values.clone())
        .collect();
    (evaluation, values)
}

/// Runs `xfactor compare` on the `evaluations` with the table's labels, writing under `out`;
/// returns the table it printed once it succeeded.
fn compare(evaluations: &[PathBuf], out: &Path) -> String {
    let xfactor = common::binaries().join("xfactor");
    let output = Command::new(&xfactor)
        .arg("compare")
        .args(evaluations)
        .args([
            "--label",
            "XFactor",
            "--label",
            "Unconstrained",
            "--label",
            "Bottleneck",
            "--label",
            "ExtraView",
            "--label",
            "SE3Plucker",
        ])
        .arg("--out")
        .arg(out)
        .output()
        .unwrap_or_else(|e| panic!("{}: {e}", xfactor.display()));
    let table = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "{table}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    table
}
