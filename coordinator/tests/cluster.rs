//! The coordinator and worker binaries as real processes on loopback: both stages, checksums,
//! data-parallel equivalence, and lost workers.

mod common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::{
    Running, binaries, commits, last_committed, load_weights, signal, small_job, wait_exit,
    wait_for_first_commit,
};
use coordinator::local::free_port;
use serde_json::Value;
use tempfile::TempDir;
use trainer_core::flax::FlaxTensors;

/// The evaluation report scores stage 1's and stage 2's final weights, each model's figures
/// and the copy baseline are numbers, and the job's own departures reach it.
fn assert_scores_both_stages(numbers: &Value) {
    let stages = numbers["stages"].as_array().expect("scored stages");
    let labels: Vec<&str> = stages
        .iter()
        .map(|s| s["checkpoint"]["label"].as_str().unwrap_or("?"))
        .collect();
    assert_eq!(labels, ["stage1", "stage2"], "both stages' final weights");
    let departures = numbers["departures"].as_array().expect("departures");
    assert!(
        departures.iter().any(|d| d
            .as_str()
            .is_some_and(|d| d.starts_with("data: generated scenes"))),
        "the job's own departures reach the report: {departures:?}"
    );
    for stage in stages {
        assert_eq!(
            stage["checkpoint"]["weights"]
                .as_str()
                .map(|c| c.ends_with("model.safetensors")),
            Some(true)
        );
        for model in ["trained", "untrained"] {
            let numbers = &stage[model];
            let psnr = numbers["reconstruction"]["psnr"].as_f64().unwrap();
            assert!(psnr.is_finite() && psnr > 0.0, "{model} psnr {psnr}");
            assert!(numbers["tps"]["model"]["pairs"].as_u64().unwrap() > 0);
            assert!(numbers["probe"]["metrics"]["pairs"].as_u64().unwrap() > 0);
        }
        let copy = stage["baselines"]["copy"]["psnr"].as_f64().unwrap();
        assert!(copy.is_finite() && copy > 0.0, "copy baseline psnr {copy}");
    }
}

#[test]
fn two_workers_run_both_stages_in_lockstep_then_one_evaluates() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.evaluate = true;
    let report = Running::start(job).finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished");
    assert_eq!(report["checksum_mismatches"].as_array().unwrap().len(), 0);
    let steps = report["steps"].as_array().unwrap();
    assert_eq!(steps.len(), 4 + 3, "{report:#}");
    for record in steps {
        let checksums: Vec<&Value> = record["checksums"].as_object().unwrap().values().collect();
        assert_eq!(checksums.len(), 2, "both ranks report every step: {record}");
        assert_eq!(checksums[0], checksums[1], "ranks differ: {record}");
        assert!(record["loss"].as_f64().unwrap().is_finite());
    }
    let stage1 = commits(&report, 1);
    let stage2 = commits(&report, 2);
    assert_eq!(stage1.iter().map(|c| c.0).collect::<Vec<_>>(), [2, 4]);
    assert_eq!(stage2.iter().map(|c| c.0).collect::<Vec<_>>(), [2, 3]);
    let stage1_final = report["stage1_final"].as_str().unwrap();
    assert_eq!(stage1_final, stage1[1].1);
    let stage2_start = report["generations"]
        .as_array()
        .unwrap()
        .iter()
        .find(|g| g["stage"] == 2)
        .unwrap();
    assert_eq!(stage2_start["init_weights_from"], stage1_final);
    let first = load_weights(stage1_final);
    let last = load_weights(&stage2[1].1);
    let name = first.names_with_prefix("").next().unwrap().to_string();
    assert_ne!(
        first.get(&name).unwrap().values,
        last.get(&name).unwrap().values,
        "stage 2 trained on"
    );
    let evaluation = Path::new(report["evaluation"].as_str().expect("an evaluation report"));
    assert!(evaluation.starts_with(dir.path().join("checkpoints/evaluation")));
    let numbers: Value =
        serde_json::from_slice(&std::fs::read(evaluation.join("report.json")).unwrap()).unwrap();
    assert_scores_both_stages(&numbers);
    let markdown = std::fs::read_to_string(evaluation.join("report.md")).unwrap();
    assert!(markdown.contains('|'), "{markdown}");
    let figures = std::fs::read_dir(evaluation)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "png")
        })
        .count();
    assert!(figures >= 4, "{figures} figures");
}

/// A small in-memory job of `workers` processes with `micro` samples per micro-batch, each
/// worker started with `--devices devices`; its report, final weights and folder.
fn train_small(workers: usize, micro: u64, devices: usize) -> (Value, FlaxTensors, TempDir) {
    train_small_with(workers, micro, devices, None)
}

/// As [`train_small`], under TLS with the certificates in `tls` when given.
fn train_small_with(
    workers: usize,
    micro: u64,
    devices: usize,
    tls: Option<std::path::PathBuf>,
) -> (Value, FlaxTensors, TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), workers);
    job.tls = tls;
    job.in_memory = true;
    job.micro_batch = micro;
    job.stage1_steps = 2;
    job.stage2_steps = 1;
    job.worker_args = vec![vec!["--devices".into(), devices.to_string()]; workers];
    let report = Running::start(job).finish(Duration::from_secs(300));
    let final_location = commits(&report, 2).last().unwrap().1.clone();
    let weights = load_weights(&final_location);
    (report, weights, dir)
}

/// Two runs with the same global batch, cut differently, trained alike: every step's loss to
/// 1e-5, and the final weights as close as float32 summation order allows.
fn assert_trained_alike(a: (&Value, &FlaxTensors), b: (&Value, &FlaxTensors)) {
    let losses = |report: &Value| -> Vec<f64> {
        report["steps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["loss"].as_f64().unwrap())
            .collect()
    };
    for (x, y) in losses(a.0).iter().zip(losses(b.0)) {
        assert!((x - y).abs() <= 1e-5 * y.abs().max(1.0), "loss {x} vs {y}");
    }
    let (mut worst, mut total, mut count) = (0.0f32, 0.0f64, 0usize);
    for name in b.1.names_with_prefix("") {
        let (x, y) = (a.1.get(name).unwrap(), b.1.get(name).unwrap());
        for (p, q) in x.values.iter().zip(&y.values) {
            worst = worst.max((p - q).abs());
            total += f64::from((p - q).abs());
            count += 1;
        }
    }
    // Adam's first steps move every weight by about the learning rate whatever its gradient's
    // size, so a gradient that sums to nearly zero (where the two summation orders differ
    // most) can move by a visibly different fraction of it. No weight may differ by half the
    // smallest step (1e-4 here: a step the other way or a missing gradient does), and on
    // average the runs agree to float32 rounding.
    let mean = total / count.max(1) as f64;
    println!("weights differ by up to {worst:e}, {mean:e} on average over {count}");
    assert!(worst < 5e-5, "weights differ by up to {worst}");
    assert!(mean < 1e-7, "weights differ by {mean} on average");
}

/// Under `tls:` the coordinator's RPCs and the ring's lanes run TLS; the lanes carry the same
/// sums, so the job trains to the same bits as without.
#[test]
fn a_job_under_tls_trains_on_tls_lanes_to_the_same_bits_as_without() {
    let certificates =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../proto/testdata/tls");
    let (tls_report, tls_weights, tls_dir) = train_small_with(2, 4, 1, Some(certificates));
    let (plain_report, plain_weights, _plain_dir) = train_small(2, 4, 1);
    let losses = |report: &Value| -> Vec<Value> {
        let steps = report["steps"].as_array().unwrap();
        steps.iter().map(|step| step["loss"].clone()).collect()
    };
    assert_eq!(losses(&tls_report), losses(&plain_report));
    for name in plain_weights.names_with_prefix("") {
        let (x, y) = (
            tls_weights.get(name).unwrap(),
            plain_weights.get(name).unwrap(),
        );
        let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&x.values), bits(&y.values), "{name}");
    }
    let worker_log = std::fs::read_to_string(tls_dir.path().join("worker-0.log")).unwrap();
    assert!(!worker_log.contains("refused"), "{worker_log}");
}

#[test]
fn two_workers_of_four_equal_one_worker_of_eight() {
    let (two, two_weights, _a) = train_small(2, 4, 1);
    let (one, one_weights, _b) = train_small(1, 8, 1);
    assert_trained_alike((&two, &two_weights), (&one, &one_weights));
}

#[test]
fn two_workers_of_two_devices_equal_one_worker_of_four_devices() {
    let (two, two_weights, two_dir) = train_small(2, 2, 2);
    let (one, one_weights, one_dir) = train_small(1, 2, 4);
    assert_trained_alike((&two, &two_weights), (&one, &one_weights));
    // Every step names the device it ran on, so the coordinator knows each worker's replicas.
    for (dir, workers, replicas) in [(&two_dir, 2, 2), (&one_dir, 1, 4)] {
        let log = std::fs::read_to_string(dir.path().join("coordinator.log")).unwrap();
        let seen = log
            .lines()
            .filter(|line| line.contains("worker device"))
            .filter(|line| line.contains(&format!("backend=cpu device=cpu replicas={replicas}")))
            .count();
        assert_eq!(seen, workers, "{log}");
    }
}

fn kill_one_mid_stage(workers: usize, minimum: usize) {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), workers);
    job.minimum = minimum;
    job.global_batch = 12;
    job.micro_batch = 2;
    job.stage1_steps = 10;
    job.stage2_steps = 3;
    let marker = job.checkpoint_dir().join("job.json");
    let mut running = Running::start(job);
    let deadline = Instant::now() + Duration::from_secs(240);
    while !marker.exists() {
        assert!(Instant::now() < deadline, "no commit\n{}", running.logs());
        std::thread::sleep(Duration::from_millis(50));
    }
    running.workers[1].kill().unwrap();
    let report = running.finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(report["restarts"].as_u64().unwrap() >= 1, "{report:#}");
    let generations = report["generations"].as_array().unwrap();
    let after = generations
        .iter()
        .find(|g| g["world_size"] == (workers - 1) as u64)
        .unwrap_or_else(|| panic!("no smaller group: {report:#}"));
    if after["stage"] == 1 {
        assert_ne!(after["resume_from"], "", "resumed from the last commit");
    }
    for stage in [1, 2] {
        let stage_commits = commits(&report, stage);
        let steps: Vec<u64> = stage_commits.iter().map(|c| c.0).collect();
        assert!(steps.windows(2).all(|w| w[0] <= w[1]), "{steps:?}");
        let last = stage_commits.last().unwrap();
        assert_eq!(last.0, if stage == 1 { 10 } else { 3 });
        load_weights(&last.1);
    }
    for record in report["steps"].as_array().unwrap() {
        let checksums: Vec<&Value> = record["checksums"].as_object().unwrap().values().collect();
        assert!(checksums.windows(2).all(|w| w[0] == w[1]), "{record}");
    }
}

#[test]
fn a_killed_worker_of_two_does_not_stop_the_job() {
    kill_one_mid_stage(2, 1);
}

#[test]
fn a_killed_worker_of_three_does_not_stop_the_job() {
    kill_one_mid_stage(3, 2);
}

/// Every `name{labels} value` line of a Prometheus text page.
fn scrape(port: u16) -> Option<Vec<(String, f64)>> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .ok()?;
    let address = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let (status, body) = runtime
        .block_on(telemetry::http::get(address, "/metrics"))
        .ok()?;
    (status == 200).then(|| {
        body.lines()
            .filter(|l| !l.starts_with('#'))
            .filter_map(|l| l.rsplit_once(' '))
            .filter_map(|(series, value)| Some((series.to_string(), value.parse().ok()?)))
            .collect()
    })
}

/// The value of the first series of family `name`.
fn sample(page: &[(String, f64)], name: &str) -> Option<f64> {
    page.iter()
        .find(|(series, _)| series == name || series.starts_with(&format!("{name}{{")))
        .map(|(_, value)| *value)
}

#[test]
fn metrics_are_scraped_from_the_coordinator_and_both_workers_mid_run() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 12;
    job.coordinator_metrics_port = Some(free_port().unwrap());
    job.worker_metrics_ports = vec![free_port().unwrap(), free_port().unwrap()];
    let ports: Vec<u16> = std::iter::once(job.coordinator_metrics_port.unwrap())
        .chain(job.worker_metrics_ports.iter().copied())
        .collect();
    let running = Running::start(job);
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut pages: Vec<Option<Vec<(String, f64)>>> = vec![None; 3];
    while pages.iter().any(Option::is_none) {
        assert!(
            Instant::now() < deadline,
            "no page with a finished step from every process\n{}",
            running.logs()
        );
        for (page, port) in pages.iter_mut().zip(&ports) {
            if page.is_none()
                && let Some(scraped) = scrape(*port)
                && sample(&scraped, "xfactor_step").is_some_and(|s| s >= 1.0)
                && sample(&scraped, "xfactor_heartbeats_total").is_some_and(|h| h >= 1.0)
            {
                *page = Some(scraped);
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let pages: Vec<Vec<(String, f64)>> = pages.into_iter().flatten().collect();
    let coordinator = &pages[0];
    let value = |page: &[(String, f64)], name: &str| {
        sample(page, name).unwrap_or_else(|| panic!("{name} missing from {page:?}"))
    };
    assert_eq!(value(coordinator, "xfactor_workers"), 2.0);
    assert_eq!(value(coordinator, "xfactor_stage"), 1.0);
    assert_eq!(value(coordinator, "xfactor_stage_steps"), 12.0);
    assert_eq!(value(coordinator, "xfactor_restarts_total"), 0.0);
    assert!(value(coordinator, "xfactor_loss") > 0.0);
    assert!(value(coordinator, "xfactor_learning_rate") > 0.0);
    assert!(value(coordinator, "xfactor_samples_per_second") > 0.0);
    assert!(value(coordinator, "xfactor_worker_allreduce_seconds") > 0.0);
    for worker in &pages[1..] {
        let loss = value(worker, "xfactor_loss");
        assert!(loss.is_finite() && loss > 0.0, "loss {loss}");
        assert!(value(worker, "xfactor_learning_rate") > 0.0);
        assert!(value(worker, "xfactor_samples_per_second") > 0.0);
        assert!(value(worker, "xfactor_allreduce_seconds") > 0.0);
        assert!(value(worker, "xfactor_allreduce_bytes_per_second") > 1e5);
        assert!(value(worker, "xfactor_loader_queue_depth") >= 0.0);
        assert_eq!(value(worker, "xfactor_skipped_frames_total"), 0.0);
        assert_eq!(
            value(worker, "xfactor_generation"),
            value(coordinator, "xfactor_generation")
        );
    }
    let report = running.finish(Duration::from_secs(120));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let curves = dir.path().join("checkpoints/curves");
    for stage in [1, 2] {
        let csv = std::fs::read_to_string(curves.join(format!("stage{stage}.csv"))).unwrap();
        let steps = if stage == 1 { 12 } else { 3 };
        assert_eq!(csv.lines().count(), steps + 1, "{csv}");
        assert!(csv.starts_with("step,loss,learning_rate,l1,lpips,grad_norm\n"));
        let png = image::open(curves.join(format!("stage{stage}.png"))).unwrap();
        assert!(png.width() > 100 && png.height() > 100);
    }
}

/// Grace a worker gets after SIGTERM in the test below.
const GRACE_S: u64 = 3;

/// A worker frozen mid-stage (SIGSTOP) while its peer waits on it in the all-reduce, then
/// thawed (SIGCONT) and sent one SIGTERM, leaves the job and exits 0 within its grace period
/// (plus the 5 s its farewell may wait for the coordinator); the job finishes without it.
#[test]
fn one_sigterm_ends_a_worker_stopped_mid_step_within_its_grace() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 400;
    job.checkpoint_every = 100;
    job.worker_args = vec![
        Vec::new(),
        vec!["--shutdown-grace-s".into(), GRACE_S.to_string()],
    ];
    let mut running = Running::start(job);
    wait_for_first_commit(&running);
    signal(&running.workers[1], "STOP");
    std::thread::sleep(Duration::from_secs(2));
    signal(&running.workers[1], "CONT");
    signal(&running.workers[1], "TERM");
    let signalled = Instant::now();
    let status = wait_exit(&mut running.workers[1], Duration::from_secs(60));
    let took = signalled.elapsed();
    println!(
        "fault=sigstop_then_sigterm exit_s={:.1} status={status}",
        took.as_secs_f64()
    );
    assert!(status.success(), "{status}\n{}", running.logs());
    assert!(
        took < Duration::from_secs(GRACE_S + 6),
        "one SIGTERM took {took:?}\n{}",
        running.logs()
    );
    let log = std::fs::read_to_string(dir.path().join("worker-1.log")).unwrap();
    assert!(log.contains("left the job"), "{log}");
    let report = running.finish(Duration::from_secs(600));
    assert_eq!(report["outcome"], "finished", "{report:#}");
}

#[test]
fn sigterm_to_a_worker_leaves_cleanly_and_the_job_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 10;
    let mut running = Running::start(job);
    wait_for_first_commit(&running);
    signal(&running.workers[1], "TERM");
    let status = wait_exit(&mut running.workers[1], Duration::from_secs(60));
    assert!(
        status.success(),
        "the worker failed on SIGTERM: {status}\n{}",
        running.logs()
    );
    let log = std::fs::read_to_string(dir.path().join("worker-1.log")).unwrap();
    assert!(log.contains("left the job"), "{log}");
    load_weights(&last_committed(&running.job.checkpoint_dir()));
    let report = running.finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(report["restarts"].as_u64().unwrap() >= 1, "{report:#}");
    for stage in [1, 2] {
        load_weights(&commits(&report, stage).last().unwrap().1);
    }
}

#[test]
fn a_coordinator_stopped_by_sigterm_and_restarted_resumes_and_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 10;
    let mut running = Running::start(job);
    wait_for_first_commit(&running);
    signal(&running.coordinator, "TERM");
    let status = wait_exit(&mut running.coordinator, Duration::from_secs(30));
    assert!(
        status.success(),
        "coordinator failed on SIGTERM: {status}\n{}",
        running.logs()
    );
    let stopped: Value =
        serde_json::from_slice(&std::fs::read(running.job.report_path()).unwrap()).unwrap();
    assert!(
        stopped["outcome"].as_str().unwrap().starts_with("stopped"),
        "{stopped:#}"
    );
    let resume_point = last_committed(&running.job.checkpoint_dir());
    load_weights(&resume_point);
    running.coordinator = running.job.spawn_coordinator(&binaries()).unwrap();
    let running_dir = running.job.dir.clone();
    let report = running.finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let first = &report["generations"][0];
    assert!(
        first["stage"] == 2 || first["resume_from"] != "",
        "the restarted coordinator began stage 1 afresh: {report:#}"
    );
    let final_stage2 = commits(&report, 2);
    assert_eq!(final_stage2.last().unwrap().0, 3, "{report:#}");
    load_weights(&final_stage2.last().unwrap().1);
    // The history of the run before the restart is read back: the report and the curves
    // start at stage 1's first step.
    let first_stage1 = report["steps"]
        .as_array()
        .and_then(|steps| steps.iter().find(|s| s["stage"] == 1))
        .map(|s| s["step"].clone());
    assert_eq!(first_stage1, Some(Value::from(0)), "{report:#}");
    let curve = std::fs::read_to_string(running_dir.join("checkpoints/curves/stage1.csv")).unwrap();
    let rows: Vec<&str> = curve.lines().skip(1).collect();
    assert_eq!(rows.len(), 10, "{curve}");
    assert!(rows[0].starts_with("0,"), "{curve}");
}
