//! Every phase transition of the job, driven through the pure state machine with a hand-held
//! clock: forming groups, commits within and at the end of each phase, the evaluation, losses
//! and re-formation, refusals, and resuming from a saved state.

use std::time::{Duration, Instant};

use proto::v1::assignment::Work;
use proto::v1::{EvaluateAssignment, LossTerms, StepReport, TrainAssignment};

use super::*;
use crate::config::ClusterConfig;

const BASE: u64 = 1000;

fn plan(evaluate: bool) -> Plan {
    plan_with(if evaluate { "evaluate: {}\n" } else { "" })
}

/// The unit job's plan with `extra` top-level YAML.
fn plan_with(extra: &str) -> Plan {
    plan_of("{expected: 2, minimum: 1, regroup_grace_s: 1}", extra)
}

/// The unit job's plan with its `workers:` section and `extra` top-level YAML.
fn plan_of(workers: &str, extra: &str) -> Plan {
    let yaml = format!(
        "job: unit
auth: {{token: t}}
model: {{preset: tiny}}
data:
  generated: {{scenes: 1, trajectories: 1, frames: 6}}
stage1: {{steps: 4, global_batch: 6, micro_batch: 1, lpips_weight: 0}}
stage2: {{steps: 2, global_batch: 6, micro_batch: 1, lpips_weight: 0}}
checkpoint: {{uri: /tmp/unit-ckpt, every: 2}}
workers: {workers}
{extra}"
    );
    let config = ClusterConfig::from_yaml(&yaml, "unit.yaml").unwrap();
    tokio::runtime::Builder::new_current_thread()
        .build()
        .unwrap()
        .block_on(Plan::build(config))
        .unwrap()
}

fn timing() -> Timing {
    Timing {
        heartbeat_timeout: Duration::from_secs(5),
        quorum_timeout: Duration::from_secs(60),
        regroup_grace: Duration::from_secs(1),
        stall_timeout: Duration::from_secs(10),
        exclusion: Duration::from_secs(30),
    }
}

struct Run {
    state: JobState,
    now: Instant,
    workers: Vec<u64>,
}

impl Run {
    fn new(evaluate: bool, durable: Option<Durable>) -> Self {
        Self::of(plan(evaluate), durable)
    }

    fn of(plan: Plan, durable: Option<Durable>) -> Self {
        let now = Instant::now();
        let mut state = JobState::starting_at(plan, timing(), durable, BASE);
        let workers = (0..2)
            .map(|i| state.register(format!("w{i}"), format!("127.0.0.1:{}", 7000 + i), now))
            .collect();
        Self {
            state,
            now,
            workers,
        }
    }

    /// Every live worker asks for work after `after`; the state ticks; returns what each got.
    fn assign(&mut self, after: u64) -> Vec<Option<Assignment>> {
        let mut got = Vec::new();
        for &worker in &self.workers {
            if let Ok(first) = self.state.request_assignment(worker, after, self.now) {
                got.push(first);
            }
        }
        self.state.tick(self.now);
        for (slot, &worker) in got.iter_mut().zip(&self.workers) {
            if slot.is_none() {
                *slot = self
                    .state
                    .request_assignment(worker, after, self.now)
                    .unwrap();
            }
        }
        got
    }

    fn commit(&mut self, worker: u64, phase: Phase, step: u64, generation: u64) -> bool {
        let commit = Commit {
            phase,
            step,
            location: format!("mem://{phase}/{step}"),
        };
        self.state.commit(worker, commit, generation).unwrap()
    }

    fn step(&mut self, worker: u64, phase: Phase, step: u64, generation: u64) -> bool {
        let report = StepReport {
            worker_id: worker,
            generation,
            step,
            loss: Some(LossTerms {
                total: 0.5,
                ..LossTerms::default()
            }),
            ..StepReport::default()
        };
        self.state.report_step(worker, phase, &report)
    }
}

fn train(assignment: &Option<Assignment>) -> &TrainAssignment {
    match assignment.as_ref().and_then(|a| a.work.as_ref()) {
        Some(Work::Train(train)) => train,
        other => panic!("expected a training assignment, got {other:?}"),
    }
}

fn evaluation(assignment: &Option<Assignment>) -> &EvaluateAssignment {
    match assignment.as_ref().and_then(|a| a.work.as_ref()) {
        Some(Work::Evaluate(evaluate)) => evaluate,
        other => panic!("expected an evaluation, got {other:?}"),
    }
}

#[test]
fn a_job_goes_through_stage1_stage2_evaluation_and_finishes() {
    let mut run = Run::new(true, None);
    assert_eq!(run.state.phase(), Phase::Stage1);
    let first = run.assign(0);
    let generation = first[0].as_ref().unwrap().generation;
    assert_eq!(generation, BASE + 1);
    let (rank0, rank1) = (train(&first[0]), train(&first[1]));
    assert_eq!((rank0.rank, rank1.rank, rank0.world_size), (0, 1, 2));
    assert_eq!(rank0.phase, proto::v1::Phase::Stage1 as i32);
    assert!(rank0.resume_from.is_empty() && rank0.init_weights_from.is_empty());
    assert_eq!(rank0.checkpoint_prefix, "/tmp/unit-ckpt/stage1");
    assert_eq!(rank0.total_steps, 4);
    assert!(rank0.model.is_some() && rank0.train.is_some() && rank0.data.is_some());

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
    assert_eq!(stage2.phase, proto::v1::Phase::Stage2 as i32);
    assert_eq!(stage2.init_weights_from, "mem://stage1/4");
    let generation = second[0].as_ref().unwrap().generation;
    assert!(run.commit(w0, Phase::Stage2, 2, generation), "stage 2 ends");
    assert_eq!(run.state.phase(), Phase::Evaluate);

    let third = run.assign(generation);
    let evaluated: Vec<_> = third.iter().filter(|a| a.is_some()).collect();
    assert_eq!(evaluated.len(), 1, "one worker evaluates");
    let evaluate = evaluation(evaluated[0]);
    assert_eq!(evaluate.weights, "mem://stage2/2");
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
        last[0].as_ref().and_then(|a| a.work.as_ref()),
        Some(Work::Finish(_))
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
    run.now += Duration::from_secs(2);
    let again = run.assign(generation);
    let resumed = train(&again[0]);
    assert_eq!(resumed.world_size, 1);
    assert_eq!(resumed.resume_from, "mem://stage1/2");
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
    assert_eq!(stage2.resume_from, "mem://stage2/1");
    assert!(stage2.init_weights_from.is_empty());

    let old: Durable = serde_json::from_str(
        r#"{"job": "unit", "stage": 3, "last_commit": null, "stage1_final": "a"}"#,
    )
    .unwrap();
    assert_eq!(old.phase, Phase::Evaluate);
    let run = Run::new(true, Some(old));
    assert!(run.state.finished(), "no stage 2 result to evaluate");
}

#[test]
fn checksum_disagreements_are_recorded_once_per_step() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    for (worker, checksum) in [(run.workers[0], 1), (run.workers[1], 2)] {
        let report = StepReport {
            worker_id: worker,
            generation,
            step: 0,
            parameter_checksum: checksum,
            checksum_computed: true,
            ..StepReport::default()
        };
        run.state.report_step(worker, Phase::Stage1, &report);
    }
    assert_eq!(run.state.mismatches(), 1);
    assert_eq!(run.state.report().steps.len(), 1);
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
        train(&regrouped[0]).world_size,
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
fn skipped_frames_past_the_job_limit_stop_the_job_naming_examples() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let limit = run.state.plan().config.max_skipped_frames;
    for (worker, count, path) in [
        (run.workers[0], limit / 2, "a.jpg"),
        (run.workers[1], limit / 2 + 1, "b.jpg"),
    ] {
        let report = StepReport {
            worker_id: worker,
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
        next[0].as_ref().and_then(|a| a.work.as_ref()),
        Some(Work::Finish(_))
    ));
}

#[test]
fn init_weights_start_stage1_and_only_until_its_first_commit() {
    let mut run = Run::of(plan_with("init_weights: s3://released/xfactor-2v\n"), None);
    let first = run.assign(0);
    let generation = first[0].as_ref().unwrap().generation;
    for assignment in &first {
        let stage1 = train(assignment);
        assert_eq!(stage1.init_weights_from, "s3://released/xfactor-2v");
        assert!(stage1.resume_from.is_empty());
    }
    let w0 = run.workers[0];
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    assert!(run.state.leave(run.workers[1], "stopping"));
    run.workers = vec![w0];
    assert!(run.assign(generation)[0].is_none(), "the grace period runs");
    run.now += Duration::from_secs(2);
    let regrouped = run.assign(generation);
    let resumed = train(&regrouped[0]);
    assert_eq!(resumed.resume_from, "mem://stage1/2");
    assert!(resumed.init_weights_from.is_empty(), "a commit wins");
    let generation = regrouped[0].as_ref().unwrap().generation;
    assert!(run.commit(w0, Phase::Stage1, 4, generation));
    let next = run.assign(generation);
    let stage2 = train(&next[0]);
    assert_eq!(stage2.init_weights_from, "mem://stage1/4");
}

#[test]
fn a_failed_final_commit_ends_the_generation_and_the_stage_resumes_from_the_last_commit() {
    let mut run = Run::new(false, None);
    let generation = run.assign(0)[0].as_ref().unwrap().generation;
    let (w0, w1) = (run.workers[0], run.workers[1]);
    assert!(!run.commit(w0, Phase::Stage1, 2, generation));
    // Both ranks finish the stage's last step; rank 0's upload of the final commit fails.
    for worker in [w0, w1] {
        assert!(run.step(worker, Phase::Stage1, 3, generation));
    }
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
    assert_eq!(resumed.resume_from, "mem://stage1/2");
    assert_eq!(resumed.world_size, 1);
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

/// Every member of the running group reports `step` with the checksum `checksum_of` gives it.
fn report_checksums(run: &mut Run, generation: u64, checksum_of: impl Fn(u64) -> u32) {
    for worker in run.workers.clone() {
        let report = StepReport {
            worker_id: worker,
            generation,
            step: 0,
            parameter_checksum: checksum_of(worker),
            checksum_computed: true,
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
    assert_eq!(train(&alone[0]).world_size, 1);
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
    assert_eq!((first.world_size, second.world_size), (2, 2));
    assert_eq!(first.resume_from, "mem://stage1/2", "nothing is redone");
    assert_eq!(
        run.state.report().restarts,
        1,
        "only the leave counted as a restart"
    );
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
    assert_eq!(train(&again[0]).resume_from, "mem://stage1/2");
}
