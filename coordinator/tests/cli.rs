//! `xfactor-coordinator run --dry-run`: the resolved plan of a real dataset, and a bad YAML
//! refused with the key and line named; every flag of `xfactor-coordinator` and `xfactor-local`
//! in `--help` with its default, and bad values refused by name.

use std::process::Command;

use coordinator::local::{LocalJob, free_port};

#[path = "../../test-support/help.rs"]
mod help;

const COORDINATOR: &str = env!("CARGO_BIN_EXE_xfactor-coordinator");
const LOCAL: &str = env!("CARGO_BIN_EXE_xfactor-local");

fn coordinator() -> Command {
    Command::new(COORDINATOR)
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

#[test]
fn the_coordinators_help_lists_every_flag_with_its_default() {
    help::assert_flags(
        COORDINATOR,
        &["run"],
        &[
            ("--config", None),
            ("--dry-run", None),
            ("--report", None),
            ("--metrics-address", None),
            ("--log-format", Some("human")),
        ],
    );
    help::assert_flags(
        COORDINATOR,
        &["status"],
        &[
            ("--address", None),
            ("--page", None),
            ("--token", None),
            ("--token-env", Some("XFACTOR_TOKEN")),
            ("--tls-ca", None),
            ("--tls-domain", None),
        ],
    );
}

#[test]
fn the_local_harness_help_lists_every_flag_with_its_default() {
    let job = LocalJob::demo(std::path::Path::new("unused"), 0);
    let (workers, stage1, stage2) = (
        job.workers.to_string(),
        job.stage1_steps.to_string(),
        job.stage2_steps.to_string(),
    );
    let (image_size, global_batch, micro_batch, checkpoint_every) = (
        job.image_size.to_string(),
        job.global_batch.to_string(),
        job.micro_batch.to_string(),
        job.checkpoint_every.to_string(),
    );
    let (scenes, paths, seed, peak_lr) = (
        job.scenes.to_string(),
        job.trajectories.to_string(),
        job.seed.to_string(),
        job.stage1_peak_lr.to_string(),
    );
    let evaluation_scenes = job.evaluation.scenes.to_string();
    let (probe_steps, probe_width) = (
        job.evaluation.probe_steps.to_string(),
        job.evaluation.probe_width.to_string(),
    );
    help::assert_flags(
        LOCAL,
        &[],
        &[
            ("--dir", Some("xfactor-local-run")),
            ("--workers", Some(&workers)),
            ("--stage1-steps", Some(&stage1)),
            ("--stage1-schedule-steps", None),
            ("--stage2-steps", Some(&stage2)),
            ("--stage1-only", None),
            ("--preset", Some(&job.preset)),
            ("--scenes", Some(&scenes)),
            ("--paths", Some(&paths)),
            ("--seed", Some(&seed)),
            ("--stage1-peak-lr", Some(&peak_lr)),
            ("--variant", Some("transfer")),
            ("--pose-dim", None),
            ("--evaluation-scenes", Some(&evaluation_scenes)),
            ("--probe-steps", Some(&probe_steps)),
            ("--probe-width", Some(&probe_width)),
            ("--image-size", Some(&image_size)),
            ("--global-batch", Some(&global_batch)),
            ("--micro-batch", Some(&micro_batch)),
            ("--checkpoint-every", Some(&checkpoint_every)),
            ("--device", Some("cpu")),
            ("--allreduce-wire", Some("f32")),
            ("--no-evaluate", None),
            ("--prepare-only", None),
            ("--port", None),
            ("--status-port", None),
            ("--listen-host", Some("127.0.0.1")),
            ("--log-format", Some("human")),
        ],
    );
}

/// The cluster YAML `xfactor-local --prepare-only FLAGS` writes, as text and parsed.
fn prepared_yaml(flags: &[&str]) -> (String, serde_json::Value) {
    let dir = tempfile::tempdir().unwrap();
    let output = Command::new(LOCAL)
        .arg("--dir")
        .arg(dir.path())
        .arg("--prepare-only")
        .args(flags)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{flags:?}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let yaml = std::fs::read_to_string(dir.path().join("cluster.yaml")).unwrap();
    let config = serde_norway::from_str(&yaml).unwrap();
    (yaml, config)
}

#[test]
fn table_3_flags_write_the_variant_latent_last_stage_and_evaluation_into_the_yaml() {
    let (yaml, config) = prepared_yaml(&[
        "--variant",
        "extra_view_encoder_decoder",
        "--pose-dim",
        "4",
        "--evaluation-scenes",
        "64",
        "--stage1-only",
    ]);
    assert_eq!(config["model"]["pose_dim"], 4, "{yaml}");
    assert_eq!(config["stop_after"], "stage1", "{yaml}");
    let training = &config["evaluate"]["notes"][2];
    assert!(
        training
            .as_str()
            .is_some_and(|t| t.starts_with("training: 4000 stage-1 steps")),
        "{yaml}"
    );
    assert_eq!(
        config["stage1"]["objective"]["variant"],
        "extra_view_encoder_decoder"
    );
    // A stage-1-only variant leaves stage 2 to XFactor's objective.
    assert!(config["stage2"]["objective"]["variant"].is_null(), "{yaml}");
    assert_eq!(config["evaluate"]["scenes"], 64);
    assert_eq!(config["evaluate"]["probe"]["test_scenes"], 16);
}

#[test]
fn a_longer_schedule_spans_stage_1s_cosine_and_curriculum_but_not_its_steps() {
    let (yaml, config) = prepared_yaml(&[
        "--stage1-steps",
        "40",
        "--stage1-schedule-steps",
        "120",
        "--stage2-steps",
        "30",
    ]);
    let stage1 = &config["stage1"];
    assert_eq!(stage1["steps"], 40, "{yaml}");
    assert_eq!(stage1["curriculum_steps"], 120, "{yaml}");
    assert_eq!(stage1["schedule"]["total_steps"], 120, "{yaml}");
    // Stage 2 keeps its own span.
    assert_eq!(config["stage2"]["schedule"]["total_steps"], 30, "{yaml}");
    assert_eq!(config["stage2"]["curriculum_steps"], 30, "{yaml}");
    // A span shorter than the steps it trains is refused before anything is written.
    let dir = tempfile::tempdir().unwrap();
    let refused = dir.path().join("refused");
    let output = Command::new(LOCAL)
        .arg("--dir")
        .arg(&refused)
        .args(["--stage1-steps", "40", "--stage1-schedule-steps", "39"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("--stage1-schedule-steps 39"), "{stderr}");
    assert!(
        !refused.exists(),
        "a refused run wrote {}",
        refused.display()
    );
}

#[test]
fn bad_values_are_refused_naming_the_flag() {
    help::assert_refused(
        COORDINATOR,
        &["run", "--config", "c.yaml", "--log-format", "xml"],
        "--log-format",
    );
    help::assert_refused(COORDINATOR, &["run"], "--config");
    help::assert_refused(
        COORDINATOR,
        &[
            "status",
            "--address",
            "http://127.0.0.1:1",
            "--tls-domain",
            "x",
        ],
        "--tls-ca",
    );
    help::assert_refused(COORDINATOR, &["status", "--token", "t"], "--address");
    help::assert_refused(LOCAL, &["--workers", "two"], "--workers");
    help::assert_refused(LOCAL, &["--preset", "huge"], "--preset");
    help::assert_refused(LOCAL, &["--scenes", "0"], "--scenes");
    help::assert_refused(LOCAL, &["--stage1-peak-lr", "0"], "--stage1-peak-lr");
    help::assert_refused(LOCAL, &["--device", "tpu"], "--device");
    help::assert_refused(LOCAL, &["--variant", "bottleneck"], "--variant");
    help::assert_refused(LOCAL, &["--pose-dim", "0"], "--pose-dim");
    help::assert_refused(LOCAL, &["--evaluation-scenes", "3"], "--evaluation-scenes");
    for count in [
        "--workers",
        "--stage1-steps",
        "--stage2-steps",
        "--image-size",
        "--global-batch",
        "--micro-batch",
        "--checkpoint-every",
    ] {
        help::assert_refused(LOCAL, &[count, "0"], count);
    }
}

#[test]
fn status_names_the_token_variable_it_cannot_read() {
    let var = "XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET";
    let status = ["status", "--address", "http://127.0.0.1:1"];
    help::assert_fails(
        COORDINATOR,
        &[&status[..], &["--token-env", var]].concat(),
        1,
        var,
    );
}
