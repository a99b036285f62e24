//! Every setting survives the wire; missing parts and unknown values are named.

use super::*;
use settings::model::PoseConditioning;
use settings::{Backend, DeviceChoice, DeviceInUse, XFactorConfig};

#[test]
fn model_settings_survive_the_wire() {
    let model = XFactorConfig::benchmark();
    assert_eq!(XFactorConfig::from(&v1::ModelConfig::from(&model)), model);
    let plucker = XFactorConfig {
        pose_conditioning: PoseConditioning::PluckerRays,
        precision: settings::model::Precision::Bf16,
        compute: settings::model::Precision::F16,
        pose_dim: settings::model::CAMERA_VECTOR_VALUES,
        ..XFactorConfig::tiny(16)
    };
    assert_eq!(
        XFactorConfig::from(&v1::ModelConfig::from(&plucker)),
        plucker
    );
}

#[test]
fn every_objective_survives_the_wire() {
    for objective in [
        StageObjective::Stage1(Stage1Config {
            lpips_weight: 0.25,
            ..Stage1Config::default()
        }),
        StageObjective::Stage2(Stage2Config {
            views: 4,
            render_from_stage1: true,
            ..Stage2Config::default()
        }),
        StageObjective::Stage1(Stage1Config {
            variant: ObjectiveVariant::Autoencode,
            ..Stage1Config::default()
        }),
        StageObjective::Stage2(Stage2Config {
            variant: ObjectiveVariant::Autoencode,
            ..Stage2Config::default()
        }),
        StageObjective::Stage2(Stage2Config {
            variant: ObjectiveVariant::Se3Plucker,
            ..Stage2Config::default()
        }),
        StageObjective::Stage1(Stage1Config {
            variant: ObjectiveVariant::ExtraViewDecoder,
            ..Stage1Config::default()
        }),
        StageObjective::Stage1(Stage1Config {
            variant: ObjectiveVariant::ExtraViewEncoderDecoder,
            ..Stage1Config::default()
        }),
    ] {
        let train = TrainConfig {
            seed: 7,
            objective,
            global_batch: 8,
            micro_batch: 2,
            shards: 3,
            schedule: Schedule::default(),
            optimizer: AdamWConfig {
                skip_norm_above: Some(5.0),
                ..AdamWConfig::default()
            },
        };
        let back = TrainConfig::try_from(&v1::TrainSettings::from(&train)).unwrap();
        assert_eq!(back, train);
    }
}

#[test]
fn data_settings_survive_the_wire() {
    for source in [
        DataSource::Generated {
            scenes: 3,
            trajectories: 4,
            frames: 5,
        },
        DataSource::Stored(vec![StoredDataset {
            kind: DatasetKind::Co3dv2,
            uri: "s3://bucket/co3d".into(),
            fingerprint: ListingFingerprint {
                objects: 10,
                bytes: 20,
                newest: -3,
                paths_crc: 99,
            },
            split_file: Some("splits/co3d_train.json".into()),
        }]),
    ] {
        let spec = DataSpec {
            source,
            sampler: SamplerConfig::stage2(),
            image_size: 64,
            seed: 1,
            global_batch: 16,
        };
        assert_eq!(
            DataSpec::try_from(&v1::DataSettings::from(&spec)).unwrap(),
            spec
        );
    }
}

#[test]
fn evaluation_settings_phases_and_devices_survive_the_wire() {
    let evaluation = EvaluationSpec {
        oracle: OracleSpec::External {
            program: "poses".into(),
            args: vec!["--fast".into()],
        },
        lpips_weights: Some("lpips.safetensors".into()),
        probe: ProbeSpec {
            loss: ProbeLoss::Trajectories,
            rotation_from_identity: true,
            ..ProbeSpec::default()
        },
        sequences: vec![SequenceProtocol {
            kind: DatasetKind::Wildrgbd,
            uri: "s3://bucket/wildrgbd".into(),
            length: 12,
            count: 20,
        }],
        notes: vec!["stage 2 keeps stage 1's Render".into()],
        ..EvaluationSpec::default()
    };
    let back = EvaluationSpec::try_from(&v1::EvaluationSettings::from(&evaluation)).unwrap();
    assert_eq!(back, evaluation);
    let finer = EvaluationSpec {
        oracle: OracleSpec::GroundTruth { subdivisions: 4 },
        ..evaluation
    };
    let back = EvaluationSpec::try_from(&v1::EvaluationSettings::from(&finer)).unwrap();
    assert_eq!(back, finer);
    // A sender that predates the field leaves it 0: the frames alone.
    let mut old = v1::EvaluationSettings::from(&finer);
    old.oracle = Some(v1::evaluation_settings::Oracle::GroundTruth(
        v1::GroundTruthOracle::default(),
    ));
    assert_eq!(
        EvaluationSpec::try_from(&old).unwrap().oracle,
        OracleSpec::default()
    );
    for phase in [
        Phase::Stage1,
        Phase::Stage2,
        Phase::Evaluate,
        Phase::Finished,
    ] {
        assert_eq!(
            phase_from_wire(phase_to_wire(phase) as i32, "phase"),
            Ok(phase)
        );
    }
    for device in DeviceChoice::ALL {
        assert_eq!(
            device_from_wire(device_to_wire(device) as i32, "device"),
            Ok(device)
        );
    }
    for backend in Backend::ALL {
        let in_use = DeviceInUse {
            backend,
            name: "NVIDIA H100 (Vulkan)".into(),
            replicas: 4,
        };
        let wire = device_in_use_to_wire(&in_use);
        assert_eq!(device_in_use_from_wire(&wire, "device"), Ok(in_use));
    }
    let auto = v1::DeviceInUse {
        backend: v1::Device::Auto as i32,
        name: "cpu".into(),
        replicas: 1,
    };
    assert!(matches!(
        device_in_use_from_wire(&auto, "device"),
        Err(ConvertError::Malformed {
            field: "device",
            ..
        })
    ));
}

#[test]
fn missing_parts_and_unknown_values_are_named() {
    let mut train = v1::TrainSettings::from(&TrainConfig {
        seed: 0,
        objective: StageObjective::Stage1(Stage1Config::default()),
        global_batch: 1,
        micro_batch: 1,
        shards: 0,
        schedule: Schedule::default(),
        optimizer: AdamWConfig::default(),
    });
    train.schedule = None;
    assert_eq!(
        TrainConfig::try_from(&train),
        Err(ConvertError::Missing("train.schedule"))
    );
    assert_eq!(
        phase_from_wire(0, "step.phase"),
        Err(ConvertError::Unknown {
            field: "step.phase",
            value: 0
        })
    );
    assert!(phase_from_wire(17, "x").is_err());
}

#[test]
fn seconds_from_the_wire_never_panic_and_name_their_field() {
    for bad in [
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NAN,
        -1.0,
        1e300,
        MAX_WIRE_SECONDS * 2.0,
    ] {
        let error = seconds_from_wire(bad, 0.0, "reply.interval_s").unwrap_err();
        assert!(
            error
                .to_string()
                .starts_with("`reply.interval_s` is malformed"),
            "{error}"
        );
    }
    assert!(seconds_from_wire(0.001, 0.01, "reply.interval_s").is_err());
    assert_eq!(
        seconds_from_wire(0.5, 0.0, "reply.interval_s").unwrap(),
        std::time::Duration::from_millis(500)
    );
    assert!(seconds_from_wire(MAX_WIRE_SECONDS, 0.0, "reply.interval_s").is_ok());
}

#[test]
fn the_status_label_says_how_long_the_job_waits_for_the_store() {
    let status = v1::JobStatus {
        phase: v1::Phase::Stage1 as i32,
        group_running: false,
        store_failing_s: Some(90.0),
        ..v1::JobStatus::default()
    };
    assert_eq!(
        super::status_label(&status),
        "stage1 (waiting for workers), waiting for the store since 90 s ago"
    );
    let working = v1::JobStatus {
        store_failing_s: None,
        group_running: true,
        ..status
    };
    assert_eq!(super::status_label(&working), "stage1");
}
