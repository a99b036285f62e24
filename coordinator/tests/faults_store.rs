//! The object store failing for a minute under a running job: the failures are the store's,
//! so no worker is blamed or benched; the coordinator retries against the store with a
//! back-off of its own, and the job goes on within seconds of the store's return. Prints
//! `fault=store_down ...` figures.

mod common;

use std::time::{Duration, Instant};

use common::{Running, commits, job_whose_stage1_store_refuses_writes};

/// How long the store stays down.
const DOWN: Duration = Duration::from_secs(60);

#[test]
fn a_store_down_for_a_minute_benches_no_worker_and_the_job_goes_on_within_seconds_of_its_return() {
    let dir = tempfile::tempdir().unwrap();
    let (job, blocker) = job_whose_stage1_store_refuses_writes(dir.path());
    let running = Running::start(job);
    running.wait_for_log(
        "generation failed on the object store",
        1,
        Duration::from_secs(240),
    );
    let down = Instant::now();
    std::thread::sleep(DOWN.saturating_sub(down.elapsed()));
    let log = running.job.dir.join("coordinator.log");
    let failures = std::fs::read_to_string(&log)
        .unwrap()
        .matches("generation failed on the object store")
        .count();
    std::fs::remove_file(&blocker).unwrap();
    let back = Instant::now();
    running.wait_for_log("stage 1 finished", 1, Duration::from_secs(120));
    let stage1_after_return_s = back.elapsed().as_secs_f64();
    let report = running.finish(Duration::from_secs(300));
    let exclusions = report["exclusions"].as_array().map_or(0, Vec::len);
    println!(
        "fault=store_down down_s={:.0} store_failures={failures} stage1_committed_after_return_s={stage1_after_return_s:.1} restarts={} exclusions={exclusions}",
        DOWN.as_secs_f64(),
        report["restarts"],
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(exclusions, 0, "a store fault benched a worker: {report:#}");
    assert!(
        failures >= 3,
        "the store was retried while down: {failures}"
    );
    assert!(
        stage1_after_return_s < 20.0,
        "stage 1 committed {stage1_after_return_s:.1} s after the store returned"
    );
    assert_eq!(commits(&report, 1).last().unwrap().0, 2, "{report:#}");
}
