//! Faults injected into real coordinator and worker processes on loopback, each with its
//! expected end state: frames deleted after indexing, a coordinator stopped while its workers
//! long-poll, a SIGSTOPped worker, rank 0 SIGKILLed before the first commit, a late joiner, a
//! SIGKILLed and restarted coordinator, a second coordinator on the same checkpoint URI, a
//! `job.json` that is not a job state, a final commit the store refuses, and a worker stuck in
//! a data read while its heartbeats go on, and `xfactor-local` on a device its workers lack.
//! Each prints `fault=... key=value` figures.

mod common;

use std::time::{Duration, Instant};

use common::{
    Running, commits, job_whose_stage1_store_refuses_writes, last_committed, signal, small_job,
    wait_exit, wait_for_first_commit, walk,
};
use coordinator::local::{LocalJob, free_port};

#[test]
fn frames_deleted_after_indexing_are_skipped_and_counted_and_the_job_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 8;
    let running = Running::start(job);
    wait_for_first_commit(&running);
    let data = dir.path().join("data");
    let mut frames: Vec<_> = walk(&data)
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "png" || e == "jpg"))
        .collect();
    frames.sort();
    let deleted: Vec<_> = frames.iter().step_by(10).collect();
    for frame in &deleted {
        std::fs::remove_file(frame).unwrap();
    }
    let started = Instant::now();
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=frames_deleted deleted={} skipped={} restarts={} seconds_after_fault={:.1}",
        deleted.len(),
        report["skipped_frames"],
        report["restarts"],
        started.elapsed().as_secs_f64()
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(report["restarts"], 0, "no generation failed: {report:#}");
    assert!(report["skipped_frames"].as_u64().unwrap() > 0, "{report:#}");
    let example = report["skipped_examples"][0].as_str().unwrap();
    assert!(example.starts_with("re10k "), "{example}");
    assert!(example.contains("does not exist"), "{example}");
}

#[test]
fn a_coordinator_stops_within_5_s_of_sigterm_while_workers_long_poll() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = LocalJob::new(dir.path(), free_port().unwrap());
    job.workers = 2;
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(job.prepare()).unwrap();
    let binaries = common::binaries();
    let mut coordinator = job.spawn_coordinator(&binaries).unwrap();
    let mut worker = job.spawn_worker(&binaries, 0).unwrap();
    let log = dir.path().join("coordinator.log");
    let deadline = Instant::now() + Duration::from_secs(120);
    while !std::fs::read_to_string(&log)
        .unwrap_or_default()
        .contains("worker registered")
    {
        assert!(Instant::now() < deadline, "the worker never registered");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(500));
    let stopping = Instant::now();
    signal(&coordinator, "TERM");
    let status = wait_exit(&mut coordinator, Duration::from_secs(5));
    let seconds = stopping.elapsed().as_secs_f64();
    println!("fault=coordinator_sigterm_long_poll stop_seconds={seconds:.2}");
    assert!(status.success(), "{status}");
    let _ = worker.kill();
    let _ = worker.wait();
}

/// A device no retry can bring (libtorch, never in a test build): each worker leaves the job
/// with the reason, and `xfactor-local`, their supervisor here, stops naming it, where the
/// workers used to sit out generation after generation.
#[test]
fn a_local_job_on_a_device_its_workers_lack_stops_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let mut local = std::process::Command::new(common::binaries().join("xfactor-local"))
        .arg("--dir")
        .arg(dir.path())
        .args([
            "--device",
            "libtorch",
            "--stage1-steps",
            "2",
            "--stage2-steps",
            "1",
        ])
        .args(["--no-evaluate", "--port"])
        .arg(free_port().unwrap().to_string())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let status = wait_exit(&mut local, Duration::from_secs(120));
    let seconds = started.elapsed().as_secs_f64();
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut local.stderr.take().unwrap(), &mut stderr).unwrap();
    println!("fault=local_device_missing stop_seconds={seconds:.2}");
    assert!(!status.success(), "{stderr}");
    for expected in [
        "worker local-",
        "so the job stopped",
        "`libtorch` cargo feature",
    ] {
        assert!(
            stderr.contains(expected),
            "`{expected}` missing from:\n{stderr}"
        );
    }
    let coordinator_log = std::fs::read_to_string(dir.path().join("coordinator.log")).unwrap();
    assert!(
        coordinator_log.contains("worker left") && coordinator_log.contains("libtorch"),
        "{coordinator_log}"
    );
}

#[test]
fn a_sigstopped_worker_is_dropped_and_the_job_finishes_without_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 20;
    let running = Running::start(job);
    wait_for_first_commit(&running);
    signal(&running.workers[1], "STOP");
    let stopped = Instant::now();
    let log = dir.path().join("coordinator.log");
    let deadline = Instant::now() + Duration::from_secs(60);
    while !std::fs::read_to_string(&log)
        .unwrap_or_default()
        .contains("worker lost: no heartbeat")
    {
        assert!(
            Instant::now() < deadline,
            "the stopped worker was never dropped\n{}",
            running.logs()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let dropped = stopped.elapsed().as_secs_f64();
    // Woken again, it finds itself unknown and registers anew (or hears the job ended).
    signal(&running.workers[1], "CONT");
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=worker_sigstop dropped_after_s={dropped:.1} finished_after_s={:.1} restarts={}",
        stopped.elapsed().as_secs_f64(),
        report["restarts"]
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(report["restarts"].as_u64().unwrap() >= 1, "{report:#}");
    assert_eq!(commits(&report, 1).last().unwrap().0, 20, "{report:#}");
}

#[test]
fn a_sigkilled_coordinator_restarts_after_its_lease_and_resumes_from_its_commit() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 20;
    let mut running = Running::start(job);
    wait_for_first_commit(&running);
    let committed = last_committed(&running.job.checkpoint_dir());
    let history = running.job.checkpoint_dir().join("history");
    let first_segment = history.join("steps-000000.jsonl");
    let deadline = Instant::now() + Duration::from_secs(60);
    while !first_segment.exists() {
        assert!(
            Instant::now() < deadline,
            "no step history\n{}",
            running.logs()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    signal(&running.coordinator, "KILL");
    let written = std::fs::read_to_string(&first_segment)
        .unwrap()
        .lines()
        .count();
    let _ = wait_exit(&mut running.coordinator, Duration::from_secs(10));
    let killed = Instant::now();
    running.coordinator = running.job.spawn_coordinator(&common::binaries()).unwrap();
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=coordinator_sigkill finished_after_s={:.1} generations={}",
        killed.elapsed().as_secs_f64(),
        report["generations"].as_array().map_or(0, Vec::len)
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let first = &report["generations"][0];
    assert!(
        first["stage"] == 2 || first["resume_from"] != "",
        "the restarted coordinator began stage 1 afresh (last commit {committed}): {report:#}"
    );
    // The history survived the kill: the first coordinator's segment, then the second's.
    let kept = std::fs::read_to_string(&first_segment)
        .unwrap()
        .lines()
        .count();
    assert!(
        kept >= written.max(1),
        "{kept} of {written} history lines kept"
    );
    assert!(
        history.join("steps-000001.jsonl").exists(),
        "the restarted coordinator's segment"
    );
}

#[test]
fn a_second_coordinator_on_the_same_checkpoint_uri_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    // Long enough that the first coordinator still runs (and renews its lease) while the
    // second one watches it.
    job.stage1_steps = 400;
    job.checkpoint_every = 100;
    let running = Running::start(job);
    wait_for_first_commit(&running);
    let log = dir.path().join("second-coordinator.log");
    let started = Instant::now();
    let mut second = std::process::Command::new(common::binaries().join("xfactor-coordinator"))
        .arg("run")
        .arg("--config")
        .arg(running.job.config_path())
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let status = wait_exit(&mut second, Duration::from_secs(30));
    let refused_after = started.elapsed().as_secs_f64();
    let said = std::fs::read_to_string(&log).unwrap();
    println!("fault=second_coordinator refused_after_s={refused_after:.1}");
    assert!(!status.success(), "the second coordinator ran\n{said}");
    assert!(said.contains("another coordinator"), "{said}");
    let report = running.finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(
        report["restarts"], 0,
        "the first job was not disturbed: {report:#}"
    );
}

#[test]
fn rank_0_killed_before_the_first_commit_and_the_survivor_starts_the_stage_again() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 20;
    job.checkpoint_every = 10;
    let mut running = Running::start(job);
    running.wait_for_log("group formed", 1, Duration::from_secs(120));
    let killed = Instant::now();
    running.workers[0].kill().unwrap();
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=rank0_sigkill_before_commit finished_after_s={:.1} restarts={}",
        killed.elapsed().as_secs_f64(),
        report["restarts"]
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let generations = report["generations"].as_array().unwrap();
    assert!(generations.len() >= 2, "{report:#}");
    assert_eq!(
        generations[1]["resume_from"], "",
        "nothing was committed to resume from"
    );
    assert_eq!(commits(&report, 1).last().unwrap().0, 20, "{report:#}");
}

#[test]
fn a_late_joiner_enters_at_the_next_commit() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 60;
    let mut running = Running::start(job);
    wait_for_first_commit(&running);
    running.workers[1].kill().unwrap();
    let _ = running.workers[1].wait();
    // The survivor trains alone first; only then does the replacement come.
    running.wait_for_log("group formed", 2, Duration::from_secs(60));
    let replacement = running.job.spawn_worker(&common::binaries(), 1).unwrap();
    running.workers[1] = replacement;
    let joined = Instant::now();
    running.wait_for_log(
        "the group re-forms at this commit",
        1,
        Duration::from_secs(120),
    );
    let entered = joined.elapsed().as_secs_f64();
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=late_joiner entered_after_s={entered:.1} restarts={}",
        report["restarts"]
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let generations = report["generations"].as_array().unwrap();
    let last_stage1 = generations.iter().rfind(|g| g["stage"] == 1).unwrap();
    assert_eq!(last_stage1["world_size"], 2, "{report:#}");
    assert_ne!(last_stage1["resume_from"], "", "{report:#}");
    assert_eq!(report["restarts"], 1, "only the kill counts: {report:#}");
}

#[test]
fn a_corrupt_job_json_stops_the_start_and_is_left_as_it_is() {
    let dir = tempfile::tempdir().unwrap();
    let job = small_job(dir.path(), 1);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(job.prepare()).unwrap();
    let state = job.checkpoint_dir().join("job.json");
    std::fs::create_dir_all(job.checkpoint_dir()).unwrap();
    std::fs::write(&state, b"{\"job\": \"small\", \"stage\": ").unwrap();
    let started = Instant::now();
    let mut coordinator = job.spawn_coordinator(&common::binaries()).unwrap();
    let status = wait_exit(&mut coordinator, Duration::from_secs(60));
    let said = std::fs::read_to_string(dir.path().join("coordinator.log")).unwrap();
    println!(
        "fault=job_json_corrupt refused_after_s={:.1}",
        started.elapsed().as_secs_f64()
    );
    assert!(!status.success(), "{said}");
    assert!(said.contains("job.json is not a job state"), "{said}");
    assert_eq!(
        std::fs::read(&state).unwrap(),
        b"{\"job\": \"small\", \"stage\": ",
        "the state was left as it was"
    );
}

#[test]
fn a_final_commit_the_store_refuses_is_retried_and_the_job_finishes_once_the_store_is_fixed() {
    let dir = tempfile::tempdir().unwrap();
    let (job, blocker) = job_whose_stage1_store_refuses_writes(dir.path());
    let running = Running::start(job);
    running.wait_for_log("generation failed", 1, Duration::from_secs(240));
    let failed = Instant::now();
    std::fs::remove_file(&blocker).unwrap();
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=final_commit_refused finished_after_fix_s={:.1} restarts={} exclusions={}",
        failed.elapsed().as_secs_f64(),
        report["restarts"],
        report["exclusions"].as_array().map_or(0, Vec::len)
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(report["restarts"].as_u64().unwrap() >= 1, "{report:#}");
    assert_eq!(commits(&report, 1).last().unwrap().0, 2, "{report:#}");
}

#[test]
fn a_worker_stuck_in_a_data_read_while_its_heartbeats_go_on_is_removed_and_the_job_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 400;
    job.checkpoint_every = 20;
    job.stall_timeout_s = 3.0;
    job.worker_metrics_ports = vec![free_port().unwrap(), free_port().unwrap()];
    let running = Running::start(job);
    wait_for_first_commit(&running);
    let fifos = block_one_sequence(&dir.path().join("data"));
    let blocked = Instant::now();
    let removal = "worker removed: no progress in its step";
    running.wait_for_log(removal, 1, Duration::from_secs(120));
    let removed_after = blocked.elapsed().as_secs_f64();
    let log = std::fs::read_to_string(dir.path().join("coordinator.log")).unwrap();
    let stuck = worker_named_after(&log, removal);
    // The stuck worker's /healthz turns 503 within a heartbeat or two of its removal, so a
    // liveness probe would restart it.
    let index: usize = stuck.trim_start_matches("local-").parse().unwrap();
    let (status, reason) = healthz_until_unhealthy(
        running.job.worker_metrics_ports[index],
        Duration::from_secs(10),
    );
    assert_eq!(status, 503, "{reason}");
    assert!(reason.contains("removed"), "{reason}");
    restore_frames(fifos);
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=worker_stuck_in_read removed_after_s={removed_after:.1} finished_after_s={:.1} restarts={} stuck={stuck}",
        blocked.elapsed().as_secs_f64(),
        report["restarts"]
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(report["restarts"].as_u64().unwrap() >= 1, "{report:#}");
    assert!(
        report["exclusions"].to_string().contains(&stuck),
        "{report:#}"
    );
    assert_eq!(commits(&report, 1).last().unwrap().0, 400, "{report:#}");
}

/// Turns the frames of one sequence under `data` into FIFOs: whoever opens one next blocks in
/// the read, while its heartbeat task keeps answering. Returns each frame with its bytes.
fn block_one_sequence(data: &std::path::Path) -> Vec<(std::path::PathBuf, Vec<u8>)> {
    let frames: Vec<_> = walk(data)
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "png" || e == "jpg"))
        .collect();
    let sequence = frames.iter().min().unwrap().parent().unwrap().to_path_buf();
    let mut fifos = Vec::new();
    for frame in frames
        .iter()
        .filter(|f| f.parent() == Some(sequence.as_path()))
    {
        let bytes = std::fs::read(frame).unwrap();
        std::fs::remove_file(frame).unwrap();
        let made = std::process::Command::new("mkfifo")
            .arg(frame)
            .status()
            .unwrap();
        assert!(made.success(), "mkfifo {}", frame.display());
        fifos.push((frame.clone(), bytes));
    }
    fifos
}

/// The `name=` of the worker the first `event` line of the coordinator's `log` names.
fn worker_named_after(log: &str, event: &str) -> String {
    log.split(event)
        .nth(1)
        .and_then(|rest| rest.split("name=").nth(1))
        .and_then(|rest| rest.split_whitespace().next())
        .unwrap()
        .to_string()
}

/// Polls `/healthz` on the loopback `port` until it answers 503 or `limit` passes; returns the
/// last answer's status and body.
fn healthz_until_unhealthy(port: u16, limit: Duration) -> (u16, String) {
    let health = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let deadline = Instant::now() + limit;
    loop {
        let answer = runtime
            .block_on(telemetry::http::get(health, "/healthz"))
            .unwrap();
        if answer.0 == 503 || Instant::now() > deadline {
            break answer;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The frames come back as plain files for the survivor; a reader still blocked in a FIFO
/// gets its bytes through the pipe.
fn restore_frames(fifos: Vec<(std::path::PathBuf, Vec<u8>)>) {
    for (frame, bytes) in fifos {
        let pipe = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&frame)
            .unwrap();
        let restored = frame.with_extension("restored");
        std::fs::write(&restored, &bytes).unwrap();
        std::fs::rename(&restored, &frame).unwrap();
        std::thread::spawn(move || {
            let mut pipe = pipe;
            let _ = std::io::Write::write_all(&mut pipe, &bytes);
        });
    }
}
