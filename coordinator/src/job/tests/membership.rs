//! Who stays in a group: lost, stuck and slow members, failed generations and whom they
//! blame, and a worker that joins a running job.

use super::*;

#[test]
fn a_lost_worker_ends_the_generation_and_the_survivor_resumes_from_the_last_commit() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    run.commit(w0, Phase::Stage1, 2, generation);
    run.now += Duration::from_secs(3);
    run.state.heartbeat(w0, generation, None, run.now);
    run.now += Duration::from_secs(3);
    run.state.heartbeat(w0, generation, None, run.now);
    assert!(run.state.tick(run.now), "w1 is silent past the timeout");
    assert_eq!(run.state.report().restarts, 1);
    assert!(
        !run.step(w0, Phase::Stage1, 2, generation),
        "the old generation is over"
    );
    assert_eq!(
        run.state.request_assignment(w1, generation, run.now),
        Err(Refusal::LostWorker(w1))
    );
    run.workers = vec![w0];
    assert!(run.assign(generation)[0].is_none(), "the grace period runs");
    assert_eq!(
        run.state.status(run.now).generation,
        generation,
        "no group formed, so no generation began"
    );
    run.now += Duration::from_secs(2);
    let again = run.assign(generation);
    let resumed = train(&again[0]);
    assert_eq!(resumed.world_size(), 1);
    assert_eq!(resumed.start, TrainStart::Resume("mem://stage1/2".into()));
    assert_eq!(again[0].as_ref().unwrap().generation, generation + 1);
}

#[test]
fn a_member_stuck_in_its_step_while_its_peer_waits_is_removed_and_sits_out() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    let beat = |run: &mut Run, worker, activity| {
        let now = run.now;
        run.state
            .heartbeat(worker, generation, Some((activity, 3)), now)
    };
    beat(&mut run, w0, Activity::Allreduce);
    beat(&mut run, w1, Activity::Computing);
    for _ in 0..4 {
        run.now += Duration::from_secs(3);
        beat(&mut run, w0, Activity::Allreduce);
        beat(&mut run, w1, Activity::Computing);
        run.state.tick(run.now);
    }
    assert_eq!(run.state.report().restarts, 1, "w1 stalled for 12 s > 10 s");
    let exclusions = run.state.report().exclusions;
    assert_eq!(exclusions.len(), 1);
    assert_eq!(exclusions[0].worker, "w1");
    assert_eq!(exclusions[0].seconds, 30.0);
    assert_eq!(
        run.state
            .request_assignment(w0, generation, run.now)
            .unwrap(),
        None,
        "w0 waits out the regroup grace"
    );
    let again = run
        .state
        .register("w1".into(), "127.0.0.1:7001".into(), run.now);
    run.workers = vec![w0, again];
    run.now += Duration::from_secs(2);
    let regrouped = run.assign(generation);
    assert_eq!(
        train(&regrouped[0]).world_size(),
        1,
        "the stuck worker's address sits out"
    );
    assert!(regrouped[1].is_none());
}

#[test]
fn a_slow_member_that_moves_on_is_not_removed() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    for step in 0..6 {
        run.now += Duration::from_secs(8);
        run.state
            .heartbeat(w0, generation, Some((Activity::Allreduce, step)), run.now);
        run.state
            .heartbeat(w1, generation, Some((Activity::Computing, step)), run.now);
        run.state.tick(run.now);
    }
    assert_eq!(run.state.report().restarts, 0);
    assert!(run.state.report().exclusions.is_empty());
}

#[test]
fn a_failed_final_commit_ends_the_generation_and_the_stage_resumes_from_the_last_commit() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    // Both ranks finish the stage's last step; rank 0's upload of the final commit fails.
    run.all_step(Phase::Stage1, 3..4, generation);
    assert!(
        run.state
            .request_assignment(w1, generation, run.now)
            .unwrap()
            .is_none()
    );
    assert!(
        !run.state.tick(run.now),
        "a finished member waiting is no trouble"
    );
    assert!(
        !run.state
            .generation_failed(w0, generation - 1, "old", None, run.now),
        "a report about an older generation changes nothing"
    );
    assert!(run.state.generation_failed(
        w0,
        generation,
        "uploading the checkpoint failed 3 times",
        None,
        run.now
    ));
    let report = run.state.report();
    assert_eq!(report.restarts, 1);
    let blamed = &report.exclusions;
    assert_eq!((blamed.len(), blamed[0].worker.as_str()), (1, "w0"));
    // The survivor re-forms from the last good commit once the grace period is over.
    run.workers = vec![w1];
    run.now += Duration::from_secs(2);
    let again = run.assign(generation);
    let resumed = train(&again[0]);
    assert_eq!(resumed.start, TrainStart::Resume("mem://stage1/2".into()));
    assert_eq!(resumed.world_size(), 1);
}

#[test]
fn a_timeout_blames_the_rank_the_evidence_names() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    // Rank 0 waited for rank 1's chunks past the collective timeout.
    assert!(run.state.generation_failed(
        w0,
        generation,
        "no chunk from rank 1 for 60 s",
        Some(1),
        run.now
    ));
    let report = run.state.report();
    let blamed = &report.exclusions;
    assert_eq!((blamed.len(), blamed[0].worker.as_str()), (1, "w1"));
    assert_eq!(
        run.state.request_assignment(w1, generation, run.now),
        Err(Refusal::LostWorker(w1)),
        "the suspect registers again and sits out its back-off"
    );
    assert!(
        run.state
            .request_assignment(w0, generation, run.now)
            .is_ok()
    );
}

#[test]
fn a_late_joiner_enters_at_the_next_commit_without_a_restart() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    assert!(run.state.leave(w1, "scaled down"));
    run.workers = vec![w0];
    assert!(run.assign(generation)[0].is_none(), "the grace period runs");
    run.now += Duration::from_secs(2);
    let alone = run.assign(generation);
    let generation = alone[0].as_ref().unwrap().generation;
    assert_eq!(train(&alone[0]).world_size(), 1);
    let joiner = run
        .state
        .register("w9".into(), "127.0.0.1:7009".into(), run.now);
    run.workers.push(joiner);
    assert!(
        run.state
            .request_assignment(joiner, 0, run.now)
            .unwrap()
            .is_none()
    );
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    let grown = run.assign(generation);
    let (first, second) = (train(&grown[0]), train(&grown[1]));
    assert_eq!((first.world_size(), second.world_size()), (2, 2));
    assert_eq!(
        first.start,
        TrainStart::Resume("mem://stage1/2".into()),
        "nothing is redone"
    );
    assert_eq!(
        run.state.report().restarts,
        1,
        "only the leave counted as a restart"
    );
}
