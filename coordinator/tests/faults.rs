//! Faults injected into real coordinator and worker processes on loopback, each with its
//! expected end state: frames deleted after indexing, a coordinator stopped while its workers
//! long-poll.

mod common;

use std::time::{Duration, Instant};

use common::{Running, signal, small_job, wait_exit, wait_for_first_commit};
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

fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let path = entry.path();
        if path.is_dir() {
            found.extend(walk(&path));
        } else {
            found.push(path);
        }
    }
    found
}
