//! The object store failing under a running job, for a minute and for five (longer than any
//! retry budget): the failures are the store's, so no worker is blamed, benched or gives up;
//! the coordinator retries against the store with a back-off of its own, says since when it
//! waits for it, and the job goes on within seconds of the store's return. Prints
//! `fault=store_down ...` and `fault=store_outage ...` figures.

mod common;

use std::time::{Duration, Instant};

use common::{Moto, Running, commits, job_whose_stage1_store_refuses_writes, small_job};

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

/// Generations the coordinator's log says failed on the object store so far.
fn store_failures(running: &Running) -> usize {
    let log = running.job.dir.join("coordinator.log");
    std::fs::read_to_string(&log)
        .unwrap()
        .matches("generation failed on the object store")
        .count()
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
    let failures = store_failures(&running);
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

/// How long the store refuses the stage's final commit: longer than any retry budget a
/// worker or the coordinator had before (8 failed generations in a row ended a worker).
const OUTAGE: Duration = Duration::from_secs(300);

/// The stage's final (and only) commit refused for five minutes: no worker process exits,
/// none is blamed, the coordinator's status says since when it waits for the store, and the
/// job finishes once the store is back with every commit kept. Prints the timeline as
/// `fault=store_outage ...`.
#[test]
fn a_final_commit_refused_for_five_minutes_ends_no_worker_and_the_job_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let (job, blocker) = job_whose_stage1_store_refuses_writes(dir.path());
    let mut running = Running::start(job);
    running.wait_for_log(
        "generation failed on the object store",
        1,
        Duration::from_secs(240),
    );
    let first_failure = Instant::now();
    while first_failure.elapsed() < OUTAGE {
        std::thread::sleep(Duration::from_secs(5));
        assert_all_alive(&mut running, first_failure.elapsed().as_secs_f64());
    }
    let waiting = running.status_line();
    let failures = store_failures(&running);
    let (report, stage1_after_return_s, exclusions) = store_returns(running, &blocker);
    println!(
        "fault=store_outage down_s={:.0} store_failures={failures} stage1_committed_after_return_s={stage1_after_return_s:.1} restarts={} exclusions={exclusions}",
        OUTAGE.as_secs_f64(),
        report["restarts"],
    );
    assert!(waiting.contains("waiting for the store since"), "{waiting}");
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(exclusions, 0, "a store fault benched a worker: {report:#}");
    assert!(
        failures >= 10,
        "the store was retried while down: {failures}"
    );
    assert_eq!(commits(&report, 1).last().unwrap().0, 2, "{report:#}");
}

/// Fails the test when a worker or the coordinator exited `seconds` into an outage.
fn assert_all_alive(running: &mut Running, seconds: f64) {
    for (index, worker) in running.workers.iter_mut().enumerate() {
        let status = worker.try_wait().unwrap();
        assert!(
            status.is_none(),
            "worker {index} exited {seconds:.0} s into the outage: {status:?}"
        );
    }
    let status = running.coordinator.try_wait().unwrap();
    assert!(
        status.is_none(),
        "the coordinator exited {seconds:.0} s into the outage: {status:?}"
    );
}

/// The checkpoint store (S3, moto's server) frozen for five minutes right after stage 1's
/// first commit: every request to it hangs unanswered. No process exits, no worker is blamed,
/// and once the store answers again the job finishes with every commit it had kept. Prints
/// the timeline as `fault=store_unreachable ...`.
#[test]
fn a_checkpoint_store_unreachable_for_five_minutes_mid_stage_loses_no_commit_and_ends_no_process() {
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(dir.path());
    moto.create_bucket("xfactor");
    let mut job = small_job(dir.path(), 2);
    (job.stage1_steps, job.checkpoint_every) = (12, 4);
    job.checkpoint_uri = Some("s3://xfactor/run/checkpoints".into());
    job.store_env = moto.env();
    let mut running = Running::start(job);
    running.wait_for_log("checkpoint committed", 1, Duration::from_secs(240));
    moto.signal("STOP");
    let frozen = Instant::now();
    while frozen.elapsed() < OUTAGE {
        std::thread::sleep(Duration::from_secs(5));
        assert_all_alive(&mut running, frozen.elapsed().as_secs_f64());
    }
    let waiting = running.status_line();
    moto.signal("CONT");
    let back = Instant::now();
    let report = running.finish(Duration::from_secs(600));
    let finished_after_return_s = back.elapsed().as_secs_f64();
    let exclusions = report["exclusions"].as_array().map_or(0, Vec::len);
    let stage1 = commits(&report, 1);
    println!(
        "fault=store_unreachable down_s={:.0} finished_after_return_s={finished_after_return_s:.1} restarts={} exclusions={exclusions} stage1_commits={:?}",
        OUTAGE.as_secs_f64(),
        report["restarts"],
        stage1.iter().map(|c| c.0).collect::<Vec<_>>(),
    );
    println!("status while frozen: {waiting}");
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(exclusions, 0, "a store fault benched a worker: {report:#}");
    let steps: Vec<u64> = stage1.iter().map(|c| c.0).collect();
    assert!(
        steps.windows(2).all(|w| w[0] < w[1]) && steps.first() == Some(&4),
        "the commit made before the outage is kept and none is lost after: {steps:?}"
    );
    assert_eq!(steps.last(), Some(&12), "{report:#}");
    assert_eq!(
        commits(&report, 2).last().map(|c| c.0),
        Some(3),
        "{report:#}"
    );
}
