//! `xfactor-coordinator run --dry-run`: the resolved plan of a real dataset, and a bad YAML
//! refused with the key and line named.

use std::process::Command;

use coordinator::local::{LocalJob, free_port};

fn coordinator() -> Command {
    Command::new(env!("CARGO_BIN_EXE_xfactor-coordinator"))
}

/// A local job's data and YAML in a temporary folder (kept alive by the returned guard).
fn prepared_job() -> (tempfile::TempDir, LocalJob) {
    let dir = tempfile::tempdir().unwrap();
    let job = LocalJob::new(dir.path(), free_port().unwrap());
    tokio::runtime::Runtime::new()
        .unwrap()
        .block_on(job.prepare())
        .unwrap();
    (dir, job)
}

#[test]
fn dry_run_prints_ranks_shards_and_steps_and_reuses_the_manifest_cache() {
    let (_dir, job) = prepared_job();
    let run = || {
        coordinator()
            .args(["run", "--dry-run", "--config"])
            .arg(job.config_path())
            .output()
            .unwrap()
    };
    let output = run();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    let plan = String::from_utf8_lossy(&output.stdout);
    for expected in [
        "job: local-demo",
        "stage1: steps=20 global_batch=8 micro_batch=4",
        "stage2: steps=10",
        "rank 0: samples 0..4",
        "rank 1: samples 4..8",
        "re10k",
        "16 train sequences",
        "shards of epoch 0",
    ] {
        assert!(
            plan.contains(expected),
            "`{expected}` missing from:\n{plan}"
        );
    }
    assert!(stderr.contains("cache=\"rebuilt\""), "{stderr}");
    let again = run();
    assert!(String::from_utf8_lossy(&again.stderr).contains("cache=\"reused\""));
    assert_eq!(String::from_utf8_lossy(&again.stdout), plan);
}

#[test]
fn a_bad_yaml_fails_before_anything_starts() {
    let (_dir, job) = prepared_job();
    let text = std::fs::read_to_string(job.config_path()).unwrap();
    std::fs::write(
        job.config_path(),
        text.replace("  threads: 1", "  thread: 1"),
    )
    .unwrap();
    let output = coordinator()
        .args(["run", "--dry-run", "--config"])
        .arg(job.config_path())
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("workers: unknown field `thread`"),
        "{stderr}"
    );
    assert!(stderr.contains("line"), "{stderr}");
    let missing = coordinator()
        .args(["run", "--config", "/nonexistent/cluster.yaml"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&missing.stderr).contains("/nonexistent/cluster.yaml"));
}
