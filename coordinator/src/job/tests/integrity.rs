//! What the job does when the training itself goes wrong: replicas whose parameters disagree,
//! frames the data cannot serve, and a checkpoint that does not read back.

use super::*;

#[test]
fn checksum_disagreements_are_recorded_once_per_step() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    for (worker, checksum) in [(run.workers[0], 1), (run.workers[1], 2)] {
        let report = StepReport {
            generation,
            step: 0,
            checksum: Some(checksum),
            ..StepReport::default()
        };
        run.state.report_step(worker, Phase::Stage1, &report);
    }
    assert_eq!(run.state.mismatches(), 1);
    assert_eq!(run.state.report().steps.len(), 1);
}

#[test]
fn skipped_frames_past_the_job_limit_stop_the_job_naming_examples() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let limit = run.state.plan().config.max_skipped_frames;
    for (worker, count, path) in [
        (run.workers[0], limit / 2, "a.jpg"),
        (run.workers[1], limit / 2 + 1, "b.jpg"),
    ] {
        let report = StepReport {
            generation,
            step: 0,
            skipped_frames: count,
            skipped_examples: vec![format!("re10k {path}: does not exist")],
            ..StepReport::default()
        };
        run.state.report_step(worker, Phase::Stage1, &report);
    }
    assert!(run.state.finished());
    let outcome = run.state.report().outcome;
    assert!(outcome.starts_with("failed: 1001 frames"), "{outcome}");
    assert!(outcome.contains("re10k a.jpg: does not exist"), "{outcome}");
    assert!(outcome.contains("re10k b.jpg"), "{outcome}");
    let next = run.assign(generation);
    assert!(matches!(
        next[0].as_ref().map(|a| &a.work),
        Some(Work::Finish)
    ));
}

/// Every member of the running group reports `step` with the checksum `checksum_of` gives it.
fn report_checksums(run: &mut Run, generation: u64, checksum_of: impl Fn(u64) -> u32) {
    for worker in run.workers.clone() {
        let report = StepReport {
            generation,
            step: 0,
            checksum: Some(checksum_of(worker)),
            ..StepReport::default()
        };
        run.state.report_step(worker, Phase::Stage1, &report);
    }
}

#[test]
fn diverged_replicas_roll_back_and_a_repeat_odd_one_sits_out() {
    let mut run = Run::of(
        plan_of("{expected: 3, minimum: 1, regroup_grace_s: 1}", ""),
        None,
    );
    let odd = run
        .state
        .register("w2".into(), "127.0.0.1:7002".into(), run.now);
    run.workers.push(odd);
    let mut generation = 0;
    for round in 1..=2u64 {
        let group = run.assign(generation);
        assert!(
            group.iter().all(Option::is_some),
            "round {round}: a group of three"
        );
        generation = group[0].as_ref().unwrap().generation;
        report_checksums(&mut run, generation, |w| if w == odd { 2 } else { 1 });
        assert!(
            run.state.tick(run.now),
            "round {round}: the divergence ends the generation"
        );
        let report = run.state.report();
        assert_eq!(report.restarts, round);
        let blamed: Vec<&str> = report
            .exclusions
            .iter()
            .map(|e| e.worker.as_str())
            .collect();
        assert_eq!(
            blamed,
            if round == 1 { vec![] } else { vec!["w2"] },
            "round {round}"
        );
        run.now += Duration::from_secs(2);
    }
}

#[test]
fn two_replicas_that_disagree_roll_back_without_blame() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let first = run.workers[0];
    report_checksums(&mut run, generation, |w| if w == first { 1 } else { 2 });
    assert!(run.state.tick(run.now));
    let report = run.state.report();
    assert_eq!((report.restarts, report.exclusions.len()), (1, 0));
}

#[test]
fn a_corrupt_newest_commit_falls_back_to_the_one_before_without_blame() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let w0 = run.workers[0];
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    assert!(!run.commit(w0, Phase::Stage1, 3, generation));
    assert!(
        run.state
            .checkpoint_corrupt(w0, generation, "mem://stage1/3", run.now)
    );
    assert_eq!(run.state.durable().last_commit.as_ref().unwrap().step, 2);
    let report = run.state.report();
    assert_eq!(report.fallbacks, ["mem://stage1/3"]);
    assert!(
        report.exclusions.is_empty(),
        "no one is blamed for the store"
    );
    assert!(
        !run.state
            .checkpoint_corrupt(w0, generation, "mem://stage1/2", run.now),
        "a report about an ended generation changes nothing"
    );
    run.now += Duration::from_secs(2);
    let again = run.assign(generation);
    assert_eq!(
        train(&again[0]).start,
        TrainStart::Resume("mem://stage1/2".into())
    );
}

#[test]
fn a_store_outage_shows_in_the_status_for_as_long_as_it_lasts_and_blames_no_one() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    assert_eq!(run.state.status(run.now).store_failing, None);
    let w0 = run.workers[0];
    assert!(
        run.state
            .store_failed(w0, generation, "upload refused", run.now)
    );
    run.now += Duration::from_secs(90);
    let waiting = run.state.status(run.now);
    assert_eq!(waiting.store_failing, Some(Duration::from_secs(90)));
    let generation = run.assign(generation)[0].as_ref().unwrap().generation;
    assert_eq!(
        run.state.status(run.now).store_failing,
        Some(Duration::from_secs(90)),
        "a group formed is not yet an answer from the store"
    );
    report_checksums(&mut run, generation, |_| 1);
    assert_eq!(
        run.state.status(run.now).store_failing,
        None,
        "a step trained ends the outage"
    );
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    assert_eq!(run.state.status(run.now).store_failing, None);
    assert!(run.state.report().exclusions.is_empty());
}

#[test]
fn a_refused_commit_shows_as_an_outage_while_the_retry_retrains_the_steps_before_it() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let w0 = run.workers[0];
    run.all_step(Phase::Stage1, 0..2, generation);
    assert!(
        run.state
            .store_failed(w0, generation, "upload of step 2 refused", run.now)
    );
    run.now += Duration::from_secs(30);
    let generation = run.assign(generation)[0].as_ref().unwrap().generation;
    run.all_step(Phase::Stage1, 0..2, generation);
    assert_eq!(
        run.state.status(run.now).store_failing,
        Some(Duration::from_secs(30)),
        "steps before the refused commit prove only that reads work"
    );
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    assert_eq!(run.state.status(run.now).store_failing, None);
    assert!(run.state.report().exclusions.is_empty());
}

#[test]
fn a_commit_waits_for_every_ranks_checksum_of_its_step() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    let commit = Commit {
        phase: Phase::Stage1,
        step: 2,
        location: "mem://stage1/2".into(),
    };
    let with_checksum = |checksum: Option<u32>| StepReport {
        generation,
        step: 1,
        checksum,
        ..StepReport::default()
    };
    run.state
        .report_step(w0, Phase::Stage1, &with_checksum(Some(5)));
    run.state
        .report_step(w1, Phase::Stage1, &with_checksum(None));
    assert_eq!(
        run.state.commit(w0, commit.clone(), generation),
        Err(Refusal::Unverified {
            phase: Phase::Stage1,
            step: 2,
            missing: vec![1]
        }),
        "rank 1 reported the step without its checksum"
    );
    assert!(run.state.durable().last_commit.is_none());
    run.state
        .report_step(w1, Phase::Stage1, &with_checksum(Some(5)));
    assert_eq!(run.state.commit(w0, commit, generation), Ok(false));
    assert_eq!(run.state.durable().last_commit.as_ref().unwrap().step, 2);
}

#[test]
fn a_commit_still_unverified_after_the_wait_ends_its_generation_without_blame() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let w0 = run.workers[0];
    let commit = Commit {
        phase: Phase::Stage1,
        step: 2,
        location: "mem://stage1/2".into(),
    };
    let refusal = run.state.commit(w0, commit, generation).unwrap_err();
    assert!(matches!(refusal, Refusal::Unverified { .. }), "{refusal}");
    assert!(run.state.roll_back_refused(&refusal, generation, run.now));
    assert!(
        !run.state.roll_back_refused(&refusal, generation, run.now),
        "the generation is over already"
    );
    let stale = Refusal::StaleGeneration(generation);
    assert!(!run.state.roll_back_refused(&stale, generation, run.now));
    let report = run.state.report();
    assert_eq!((report.restarts, report.exclusions.len()), (1, 0));
}

#[test]
fn a_commit_of_a_step_whose_replicas_disagree_is_refused_and_the_group_rolls_back() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let w0 = run.workers[0];
    assert!(!run.commit(w0, Phase::Stage1, 1, generation));
    for (worker, checksum) in [(run.workers[0], 5), (run.workers[1], 6)] {
        let report = StepReport {
            generation,
            step: 1,
            checksum: Some(checksum),
            ..StepReport::default()
        };
        run.state.report_step(worker, Phase::Stage1, &report);
    }
    let diverged = Commit {
        phase: Phase::Stage1,
        step: 2,
        location: "mem://stage1/2".into(),
    };
    assert!(matches!(
        run.state.commit(w0, diverged, generation),
        Err(Refusal::ChecksumsDiffer { step: 2, .. })
    ));
    assert!(
        run.state.tick(run.now),
        "the divergence ends the generation"
    );
    run.now += Duration::from_secs(2);
    let again = run.assign(generation);
    assert_eq!(
        train(&again[0]).start,
        TrainStart::Resume("mem://stage1/1".into()),
        "the group resumes from the last verified commit"
    );
}
