//! A job's phases in order: forming the first group, commits within and at the end of each
//! stage, the evaluation, refused commits, and resuming from a saved state or released weights.

use super::*;

#[test]
fn a_job_goes_through_stage1_stage2_evaluation_and_finishes() {
    let mut run = Run::new(true, None);
    assert_eq!(run.state.phase(), Phase::Stage1);
    let first = run.assign(0);
    let generation = first[0].as_ref().unwrap().generation;
    assert_eq!(generation, BASE + 1);
    let (rank0, rank1) = (train(&first[0]), train(&first[1]));
    assert_eq!((rank0.rank, rank1.rank, rank0.world_size()), (0, 1, 2));
    assert_eq!(rank0.stage, Phase::Stage1);
    assert_eq!(rank0.start, TrainStart::Fresh);
    assert_eq!(rank0.checkpoint_prefix, "/tmp/unit-ckpt/stage1");
    assert_eq!(rank0.total_steps, 4);
    assert_eq!(rank0.model, run.state.plan().model);

    let w0 = run.workers[0];
    assert!(run.step(w0, Phase::Stage1, 0, generation));
    assert!(!run.commit(w0, Phase::Stage1, 2, generation), "mid-stage");
    assert_eq!(run.state.phase(), Phase::Stage1);
    assert!(run.commit(w0, Phase::Stage1, 4, generation), "stage 1 ends");
    assert_eq!(run.state.phase(), Phase::Stage2);
    assert_eq!(
        run.state.durable().stage1_final.as_deref(),
        Some("mem://stage1/4")
    );
    assert_eq!(run.state.durable().last_commit, None);

    let second = run.assign(generation);
    let stage2 = train(&second[0]);
    assert_eq!(stage2.stage, Phase::Stage2);
    assert_eq!(
        stage2.start,
        TrainStart::InitWeights("mem://stage1/4".into())
    );
    let generation = second[0].as_ref().unwrap().generation;
    assert!(run.commit(w0, Phase::Stage2, 2, generation), "stage 2 ends");
    assert_eq!(run.state.phase(), Phase::Evaluate);

    let third = run.assign(generation);
    let evaluated: Vec<_> = third.iter().filter(|a| a.is_some()).collect();
    assert_eq!(evaluated.len(), 1, "one worker evaluates");
    let evaluate = evaluation(evaluated[0]);
    let scored: Vec<(&str, usize)> = evaluate
        .checkpoints
        .iter()
        .map(|c| (c.weights.as_str(), c.context_views))
        .collect();
    assert_eq!(scored, [("mem://stage1/4", 1), ("mem://stage2/2", 5)]);
    assert_eq!(evaluate.report_prefix, "/tmp/unit-ckpt/evaluation");
    let generation = evaluated[0].as_ref().unwrap().generation;
    let evaluator = run.workers[third.iter().position(|a| a.is_some()).unwrap()];
    assert!(run.commit(evaluator, Phase::Evaluate, 1, generation));
    assert!(run.state.finished());
    assert_eq!(run.state.report().outcome, "finished");
    assert_eq!(
        run.state.report().evaluation.as_deref(),
        Some("mem://evaluate/1")
    );

    let last = run.assign(generation);
    assert!(matches!(
        last[0].as_ref().map(|a| &a.work),
        Some(Work::Finish)
    ));
}

#[test]
fn without_an_evaluation_stage_2_ends_the_job() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let w0 = run.workers[0];
    run.commit(w0, Phase::Stage1, 4, generation);
    let generation = run.assign(generation)[0].as_ref().unwrap().generation;
    assert!(run.commit(w0, Phase::Stage2, 2, generation));
    assert_eq!(run.state.phase(), Phase::Finished);
}

#[test]
fn a_job_stopping_after_stage_1_evaluates_stage_1_alone_or_ends_there() {
    let mut run = Run::of(plan_with("evaluate: {}\nstop_after: stage1\n"), None);
    assert_eq!(
        run.state.status(run.now).job_steps_total,
        4,
        "no stage-2 steps"
    );
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let w0 = run.workers[0];
    assert!(run.commit(w0, Phase::Stage1, 4, generation), "stage 1 ends");
    assert_eq!(run.state.phase(), Phase::Evaluate);
    let after = run.assign(generation);
    let evaluator = after.iter().find(|a| a.is_some()).unwrap();
    let scored: Vec<&str> = evaluation(evaluator)
        .checkpoints
        .iter()
        .map(|c| c.weights.as_str())
        .collect();
    assert_eq!(scored, ["mem://stage1/4"]);

    let plan = run.state.plan().describe();
    assert!(
        plan.contains("stage2: not trained (stop_after: stage1)"),
        "{plan}"
    );
    assert!(
        plan.contains("evaluates the final weights of stage 1 "),
        "{plan}"
    );

    let mut run = Run::of(plan_with("stop_after: stage1\n"), None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    assert!(run.commit(run.workers[0], Phase::Stage1, 4, generation));
    assert!(run.state.finished());
    assert_eq!(run.state.durable().stage2_final, None);
}

#[test]
fn stale_foreign_and_wrong_phase_commits_are_refused() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let w0 = run.workers[0];
    let commit = |phase| Commit {
        phase,
        step: 2,
        location: "mem://x".into(),
    };
    assert_eq!(
        run.state.commit(w0, commit(Phase::Stage1), generation - 1),
        Err(Refusal::StaleGeneration(generation - 1))
    );
    assert_eq!(
        run.state.commit(999, commit(Phase::Stage1), generation),
        Err(Refusal::NotInGroup(999))
    );
    assert_eq!(
        run.state.commit(w0, commit(Phase::Stage2), generation),
        Err(Refusal::WrongPhase {
            commit: Phase::Stage2,
            job: Phase::Stage1
        })
    );
    assert_eq!(
        run.state.request_assignment(999, 0, run.now),
        Err(Refusal::UnknownWorker(999))
    );
    assert!(run.state.report().commits.is_empty());
}

#[test]
fn a_saved_state_resumes_where_it_was_and_an_old_evaluation_state_counts_as_finished() {
    let mut saved = Durable::new("unit".into());
    saved.phase = Phase::Stage2;
    saved.stage1_final = Some("mem://stage1/4".into());
    saved.last_commit = Some(Commit {
        phase: Phase::Stage2,
        step: 1,
        location: "mem://stage2/1".into(),
    });
    let mut run = Run::new(false, Some(saved));
    let resumed = run.assign(0);
    let stage2 = train(&resumed[0]);
    assert_eq!(stage2.start, TrainStart::Resume("mem://stage2/1".into()));

    let old: Durable = serde_json::from_str(
        r#"{"job": "unit", "stage": 3, "last_commit": null, "stage1_final": "a"}"#,
    )
    .unwrap();
    assert_eq!(old.phase, Phase::Evaluate);
    let run = Run::new(true, Some(old));
    assert!(run.state.finished(), "no stage 2 result to evaluate");
}

/// The checkpoints the evaluation `run` hands out scores.
fn scored(run: &mut Run) -> Vec<String> {
    let assigned = run.assign(0);
    let evaluator = assigned
        .iter()
        .find(|a| a.is_some())
        .expect("an evaluation");
    let checkpoints = &evaluation(evaluator).checkpoints;
    checkpoints.iter().map(|c| c.weights.clone()).collect()
}

#[test]
fn a_job_stopping_after_stage_1_resumes_its_evaluation_and_sets_stage_2_aside() {
    let stage1_only = || plan_with("evaluate: {}\nstop_after: stage1\n");
    let mut evaluating = Durable::new("unit".into());
    evaluating.phase = Phase::Evaluate;
    evaluating.stage1_final = Some("mem://stage1/4".into());
    let mut run = Run::of(stage1_only(), Some(evaluating.clone()));
    assert_eq!(
        run.state.phase(),
        Phase::Evaluate,
        "stage 1 is all it trains"
    );
    assert_eq!(scored(&mut run), ["mem://stage1/4"]);

    // A job saved in (or after) stage 2 whose YAML now stops after stage 1.
    let mut in_stage2 = evaluating.clone();
    in_stage2.phase = Phase::Stage2;
    in_stage2.last_commit = Some(Commit {
        phase: Phase::Stage2,
        step: 1,
        location: "mem://stage2/1".into(),
    });
    let mut run = Run::of(stage1_only(), Some(in_stage2.clone()));
    assert_eq!(run.state.phase(), Phase::Evaluate);
    assert_eq!(scored(&mut run), ["mem://stage1/4"]);
    let run = Run::of(plan_with("stop_after: stage1\n"), Some(in_stage2));
    assert!(run.state.finished(), "nothing to evaluate");
    evaluating.stage2_final = Some("mem://stage2/2".into());
    let mut run = Run::of(stage1_only(), Some(evaluating));
    assert_eq!(scored(&mut run), ["mem://stage1/4"]);
}

#[test]
fn init_weights_start_stage1_and_only_until_its_first_commit() {
    let mut run = Run::of(plan_with("init_weights: s3://released/xfactor-2v\n"), None);
    let first = run.assign(0);
    let generation = first[0].as_ref().unwrap().generation;
    for assignment in &first {
        let stage1 = train(assignment);
        assert_eq!(
            stage1.start,
            TrainStart::InitWeights("s3://released/xfactor-2v".into())
        );
    }
    let w0 = run.workers[0];
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    assert!(run.state.leave(run.workers[1], "stopping"));
    run.workers = vec![w0];
    assert!(run.assign(generation)[0].is_none(), "the grace period runs");
    run.now += Duration::from_secs(2);
    let regrouped = run.assign(generation);
    let resumed = train(&regrouped[0]);
    assert_eq!(resumed.start, TrainStart::Resume("mem://stage1/2".into()));
    let generation = regrouped[0].as_ref().unwrap().generation;
    assert!(run.commit(w0, Phase::Stage1, 4, generation));
    let next = run.assign(generation);
    let stage2 = train(&next[0]);
    assert_eq!(
        stage2.start,
        TrainStart::InitWeights("mem://stage1/4".into())
    );
}

#[test]
fn a_suspension_ignores_commits_before_its_step_and_completes_when_the_stage_ends() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    run.all_step(Phase::Stage1, 0..2, generation);
    assert!(!run.commit(w0, Phase::Stage1, 2, generation), "mid-stage");
    assert!(run.step(w0, Phase::Stage1, 2, generation));
    assert_eq!(
        run.state.suspends(w0, generation, 2),
        SuspendAnswer::Continue,
        "not requested yet"
    );
    run.state.request_suspension();
    assert!(run.step(w1, Phase::Stage1, 2, generation));
    assert_eq!(
        run.state.suspends(w1, generation, 2),
        SuspendAnswer::Continue,
        "rank 0 goes on to step 3, so rank 1 must too"
    );
    for worker in [w0, w1] {
        assert!(!run.state.suspension_complete(), "worker {worker} not told");
        assert!(run.step(worker, Phase::Stage1, 3, generation));
        assert_eq!(
            run.state.suspends(worker, generation, 3),
            SuspendAnswer::ChecksumNext,
            "the point (step 4) is past the stage's end; the notice comes all the same"
        );
    }
    assert!(
        !run.state.suspension_complete(),
        "the commit of step 2 came before the suspension's step"
    );
    run.commit(w0, Phase::Stage1, 4, generation);
    assert!(run.state.suspension_complete());
}

#[test]
fn a_suspension_mid_stage_completes_once_rank_0_commits_the_step_every_rank_heard() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    assert!(run.step(w0, Phase::Stage1, 0, generation));
    run.state.request_suspension();
    assert!(run.step(w1, Phase::Stage1, 0, generation));
    assert_eq!(
        run.state.suspends(w1, generation, 0),
        SuspendAnswer::Continue
    );
    run.all_step(Phase::Stage1, 1..3, generation);
    for worker in [w1, w0] {
        assert_eq!(
            run.state.suspends(worker, generation, 1),
            SuspendAnswer::ChecksumNext
        );
    }
    assert_eq!(
        run.state.suspends(w1, generation, 2),
        SuspendAnswer::Suspend
    );
    assert!(!run.state.suspension_complete(), "rank 0 not told");
    assert_eq!(
        run.state.suspends(w0, generation, 2),
        SuspendAnswer::Suspend
    );
    assert!(!run.state.suspension_complete(), "no commit yet");
    assert!(!run.commit(w0, Phase::Stage1, 3, generation), "mid-stage");
    assert!(run.state.suspension_complete());
}
