//! Assignments and failure reports: every field survives the wire, and every missing or
//! malformed one is refused with its name.

use settings::data::{DataSource, DataSpec, SamplerConfig};
use settings::evaluation::EvaluationSpec;
use settings::objective::Stage2Config;
use settings::optim::{AdamWConfig, Schedule};
use settings::train::{StageObjective, TrainConfig};
use settings::work::{
    Assignment, CheckpointToEvaluate, ChecksumEvery, EvaluateWork, FailureCause, GenerationFailure,
    RingSecrets, TrainStart, TrainWork, WireFormat, Work,
};
use settings::{DeviceChoice, DeviceSet, Phase, XFactorConfig};

use super::ConvertError;
use crate::v1;

fn train_work(start: TrainStart, ring: Option<RingSecrets>) -> TrainWork {
    TrainWork {
        stage: Phase::Stage2,
        rank: 1,
        peers: vec!["10.0.0.1:7000".into(), "10.0.0.2:7000".into()],
        total_steps: 40,
        start,
        checkpoint_prefix: "s3://bucket/job/stage2".into(),
        checkpoint_every: 5,
        checksum_every: ChecksumEvery::Steps(3),
        lpips_weights: Some("lpips.safetensors".into()),
        device: DeviceChoice::Wgpu,
        model: XFactorConfig::tiny(16),
        train: TrainConfig {
            seed: 9,
            objective: StageObjective::Stage2(Stage2Config::default()),
            global_batch: 4,
            micro_batch: 2,
            shards: 1,
            schedule: Schedule::default(),
            optimizer: AdamWConfig::default(),
        },
        data: DataSpec {
            source: DataSource::Generated {
                scenes: 2,
                trajectories: 3,
                frames: 6,
            },
            sampler: SamplerConfig::stage2(),
            image_size: 16,
            seed: 9,
            global_batch: 4,
        },
        ring,
        devices: DeviceSet::Ids(vec![0, 2]),
        wire: WireFormat::Bf16,
        lanes: 3,
    }
}

/// Breaks one field of a wire message, and the field the refusal must name.
type Breakage<M> = (fn(&mut M), &'static str);

fn wire(work: &TrainWork) -> v1::TrainAssignment {
    v1::TrainAssignment::from(work)
}

/// One work of every kind and start the wire carries.
pub(super) fn every_kind_of_work() -> Vec<Work> {
    let secrets = RingSecrets {
        own: "own".into(),
        left: "left".into(),
    };
    vec![
        Work::Train(Box::new(train_work(
            TrainStart::Resume("s3://bucket/job/stage2/step-00000010-g3".into()),
            Some(secrets.clone()),
        ))),
        Work::Train(Box::new(train_work(
            TrainStart::InitWeights("s3://bucket/job/stage1/final".into()),
            Some(secrets),
        ))),
        Work::Train(Box::new(TrainWork {
            lpips_weights: None,
            devices: DeviceSet::All,
            ..train_work(TrainStart::Fresh, None)
        })),
        Work::Train(Box::new(TrainWork {
            devices: DeviceSet::Count(4),
            ..train_work(TrainStart::Fresh, None)
        })),
        Work::Evaluate(Box::new(EvaluateWork {
            checkpoints: vec![
                checkpoint(Phase::Stage1, "s3://bucket/job/stage1/final", 1),
                checkpoint(Phase::Stage2, "s3://bucket/job/stage2/final", 2),
            ],
            report_prefix: "s3://bucket/job/evaluation".into(),
            device: DeviceChoice::Cpu,
            model: XFactorConfig::tiny(16),
            spec: EvaluationSpec::default(),
        })),
        Work::Finish,
    ]
}

#[test]
fn every_kind_of_assignment_survives_the_wire() {
    for work in every_kind_of_work() {
        let assignment = Assignment {
            generation: 12,
            work,
        };
        let back = Assignment::try_from(&v1::Assignment::from(&assignment));
        assert_eq!(back, Ok(assignment));
    }
}

#[test]
fn an_assignment_without_work_is_refused() {
    let empty = v1::Assignment {
        generation: 3,
        work: None,
    };
    assert_eq!(
        Assignment::try_from(&empty),
        Err(ConvertError::Missing("work"))
    );
}

#[test]
fn missing_parts_of_a_train_assignment_are_named() {
    let whole = wire(&train_work(TrainStart::Fresh, None));
    let cases: [Breakage<v1::TrainAssignment>; 5] = [
        (|w| w.model = None, "train.model"),
        (|w| w.train = None, "train.train"),
        (|w| w.data = None, "train.data"),
        (|w| w.checkpoint_prefix.clear(), "train.checkpoint_prefix"),
        (|w| w.phase = 0, "train.phase"),
    ];
    for (break_it, field) in cases {
        let mut broken = whole.clone();
        break_it(&mut broken);
        let refused = TrainWork::try_from(&broken).unwrap_err();
        assert!(refused.to_string().contains(field), "{field}: {refused}");
    }
}

#[test]
fn malformed_train_assignments_are_refused_with_the_field() {
    let whole = wire(&train_work(TrainStart::Fresh, None));
    let cases: [Breakage<v1::TrainAssignment>; 9] = [
        (|w| w.rank = 2, "train.rank"),
        (|w| w.world_size = 3, "train.peers"),
        (|w| w.checkpoint_every = 0, "train.checkpoint_every"),
        (|w| w.phase = v1::Phase::Evaluate as i32, "train.phase"),
        (
            |w| {
                w.resume_from = "a".into();
                w.init_weights_from = "b".into();
            },
            "train.resume_from",
        ),
        (|w| w.ring_secret = "own".into(), "train.left_ring_secret"),
        (|w| w.left_ring_secret = "left".into(), "train.ring_secret"),
        (
            |w| {
                w.devices = Some(v1::DeviceSet {
                    count: 2,
                    ids: vec![0],
                })
            },
            "train.devices",
        ),
        (|w| w.ring_lanes = 65, "train.ring_lanes"),
    ];
    for (break_it, field) in cases {
        let mut broken = whole.clone();
        break_it(&mut broken);
        match TrainWork::try_from(&broken) {
            Err(ConvertError::Malformed { field: named, .. }) => assert_eq!(named, field),
            other => panic!("{field}: {other:?}"),
        }
    }
    let unknown: [Breakage<v1::TrainAssignment>; 2] = [
        (|w| w.device = 99, "train.device"),
        (|w| w.wire = 99, "train.wire"),
    ];
    for (break_it, field) in unknown {
        let mut broken = whole.clone();
        break_it(&mut broken);
        assert_eq!(
            TrainWork::try_from(&broken),
            Err(ConvertError::Unknown { field, value: 99 })
        );
    }
}

fn checkpoint(stage: Phase, weights: &str, context_views: usize) -> CheckpointToEvaluate {
    CheckpointToEvaluate {
        stage,
        weights: weights.into(),
        step: 40,
        context_views,
    }
}

#[test]
fn missing_parts_of_an_evaluate_assignment_are_named() {
    let whole = v1::EvaluateAssignment::from(&EvaluateWork {
        checkpoints: vec![checkpoint(Phase::Stage2, "w", 2)],
        report_prefix: "r".into(),
        device: DeviceChoice::Auto,
        model: XFactorConfig::tiny(16),
        spec: EvaluationSpec::default(),
    });
    let cases: [Breakage<v1::EvaluateAssignment>; 5] = [
        (|w| w.checkpoints.clear(), "evaluate.checkpoints"),
        (
            |w| w.checkpoints[0].weights.clear(),
            "evaluate.checkpoints.weights",
        ),
        (|w| w.report_prefix.clear(), "evaluate.report_prefix"),
        (|w| w.model = None, "evaluate.model"),
        (|w| w.spec = None, "evaluate.spec"),
    ];
    for (break_it, field) in cases {
        let mut broken = whole.clone();
        break_it(&mut broken);
        assert_eq!(
            EvaluateWork::try_from(&broken),
            Err(ConvertError::Missing(field))
        );
    }
    let mut no_views = whole.clone();
    no_views.checkpoints[0].context_views = 0;
    assert!(matches!(
        EvaluateWork::try_from(&no_views),
        Err(ConvertError::Malformed {
            field: "evaluate.checkpoints.context_views",
            ..
        })
    ));
}

#[test]
fn every_failure_cause_survives_the_wire() {
    for cause in [
        FailureCause::Worker,
        FailureCause::Peer { rank: 3 },
        FailureCause::Store,
        FailureCause::CorruptCheckpoint {
            location: "s3://bucket/job/stage1/step-00000004-g2".into(),
        },
    ] {
        let failure = GenerationFailure {
            reason: "it broke".into(),
            cause,
        };
        let back = GenerationFailure::try_from(&v1::GenerationFailure::from(&failure));
        assert_eq!(back, Ok(failure));
    }
}

#[test]
fn incomplete_failure_reports_are_refused() {
    let report = |kind: v1::FailureKind| v1::GenerationFailure {
        reason: "x".into(),
        suspect_rank: None,
        corrupt_checkpoint: String::new(),
        kind: kind as i32,
    };
    assert_eq!(
        GenerationFailure::try_from(&report(v1::FailureKind::Peer)),
        Err(ConvertError::Missing("failure.suspect_rank"))
    );
    assert_eq!(
        GenerationFailure::try_from(&report(v1::FailureKind::CorruptCheckpoint)),
        Err(ConvertError::Missing("failure.corrupt_checkpoint"))
    );
    assert_eq!(
        GenerationFailure::try_from(&report(v1::FailureKind::Unspecified)),
        Err(ConvertError::Unknown {
            field: "failure.kind",
            value: 0
        })
    );
}
