//! The object store failing under a running job, for a minute and for longer than any retry
//! budget: the failures are the store's, so no worker is blamed, benched or gives up; the
//! coordinator retries against the store with a back-off of its own, and the job goes on
//! within seconds of the store's return. Prints `fault=store_down ...` and
//! `fault=store_outage ...` figures.

mod common;

use std::time::{Duration, Instant};

use common::{Running, commits, job_whose_stage1_store_refuses_writes};

/// Lets the store write again (removes `blocker`), waits for stage 1 to finish and the job
/// to end; returns its report, the seconds stage 1 took to commit after the store's return,
/// and the workers excluded.
fn store_returns(running: Running, blocker: &std::path::Path) -> (serde_json::Value, f64, usize) {
    std::fs::remove_file(blocker).unwrap();
    let back = Instant::now();
    running.wait_for_log("stage 1 finished", 1, Duration::from_secs(120));
    let stage1_after_return_s = back.elapsed().as_secs_f64();
    let report = running.finish(Duration::from_secs(300));
    let exclusions = report["exclusions"].as_array().map_or(0, Vec::len);
    (report, stage1_after_return_s, exclusions)
}

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
    let (report, stage1_after_return_s, exclusions) = store_returns(running, &blocker);
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

/// Failed generations the store causes before it returns: more than the 8 in a row after
/// which a worker used to give up whatever the cause.
const FAILURES_BEFORE_RETURN: usize = 10;

/// The stage's only commit refused until every worker has seen 10 generations fail on the
/// store (a few minutes: the workers wait 1 s doubling to 8 s between tries): no worker
/// process exits, none is blamed, and the job finishes once the store is back. Prints the
/// timeline as `fault=store_outage ...`.
#[test]
fn a_store_outage_longer_than_any_retry_budget_ends_no_worker_and_the_job_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let (job, blocker) = job_whose_stage1_store_refuses_writes(dir.path());
    let mut running = Running::start(job);
    let started = Instant::now();
    running.wait_for_log(
        "generation failed on the object store",
        FAILURES_BEFORE_RETURN,
        Duration::from_secs(600),
    );
    let down_s = started.elapsed().as_secs_f64();
    for (index, worker) in running.workers.iter_mut().enumerate() {
        let status = worker.try_wait().unwrap();
        assert!(
            status.is_none(),
            "worker {index} exited during the outage: {status:?}"
        );
    }
    let (report, stage1_after_return_s, exclusions) = store_returns(running, &blocker);
    println!(
        "fault=store_outage failures={FAILURES_BEFORE_RETURN} down_s={down_s:.0} stage1_committed_after_return_s={stage1_after_return_s:.1} restarts={} exclusions={exclusions}",
        report["restarts"],
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(exclusions, 0, "a store fault benched a worker: {report:#}");
    assert_eq!(commits(&report, 1).last().unwrap().0, 2, "{report:#}");
}
