//! After a short CPU training run on generated scenes that share camera motions across scenes,
//! the trained model's TPS and probe numbers beat those of the untrained model; the report
//! (JSON, Markdown, figures) shows both. Prints the numbers.
//!
//! Why 16x16 frames, 1300 steps and a 2e-3 peak learning rate: the ground-truth oracle reads a
//! render's pose from the generated frame with the nearest 8x8 thumbnail. After 200 steps at
//! 32x32 (peak 1e-3) the renders barely depend on the pose latent, so all five renders of a
//! transfer matched the same generated frame, their relative translations were zero and every
//! frame pair scored the conventional 90 degrees (TPS AUC@30 0.004 vs 0.000 untrained). At 16x16
//! a step is about four times cheaper, and 1300 steps at a higher peak rate teach the renderer
//! to move the camera in about 70 s on 2 cores (a 3e-3 peak moved the renders as far but left
//! the probe no better than the untrained model's). TPS uses all 8 frames of 96 transfers (2688
//! frame pairs) so the comparison is not decided by a handful of renders.
//!
//! Why the evaluation draws 16 scenes (10 more than training saw): the release's pose probe
//! reads PoseEnc's tokens before the pose head, which an untrained network's random features
//! also describe. Trained on the 4 non-held-out scenes of the training set, the probe
//! memorised them (training loss 0.11) and scored no better on held-out scenes than the
//! untrained model's (AUC@30 0.114 vs 0.130); on 14 it generalises, and the trained features
//! win (0.122 vs 0.085 after 800 probe steps; TPS 0.058 vs 0.000 on these scenes).

use std::path::Path;
use std::time::Instant;

use burn::tensor::Device;
use data::scenes::SceneConfig;
use data::synthetic::SyntheticDataset;
use evaluation::{EvaluationReport, run_evaluation};
use settings::evaluation::{EvaluationSpec, OracleSpec, ProbeSpec};
use settings::objective::Stage1Config;
use settings::optim::{AdamWConfig, Schedule};
use settings::train::{StageObjective, TrainConfig};
use trainer_core::trainer::Trainer;
use trainer_core::{XFactor, XFactorConfig};

const SIDE: usize = 16;
const STEPS: u64 = 1300;
const SCENES: u64 = 6;
/// Scenes the evaluation draws: the training scenes and 10 it never saw.
const EVALUATION_SCENES: u64 = 16;
const TRAJECTORIES: u64 = 8;
const FRAMES: usize = 8;

fn summary(name: &str, report: &evaluation::evaluate::ModelReport) -> (f64, f64) {
    let tps = report.tps.model.at(30).unwrap().auc;
    let probe = report.probe.metrics.at(30).unwrap().auc;
    println!(
        "{name}: psnr={:.2} ssim={:.3} tps_auc30={tps:.3} tps_rac5={:.3} tps_tac5={:.3} probe_auc30={probe:.3} probe_rac5={:.3} probe_tac5={:.3} probe_loss={:.4}",
        report.reconstruction.psnr,
        report.reconstruction.ssim,
        report.tps.model.at(5).unwrap().rotation_accuracy,
        report.tps.model.at(5).unwrap().translation_accuracy,
        report.probe.metrics.at(5).unwrap().rotation_accuracy,
        report.probe.metrics.at(5).unwrap().translation_accuracy,
        report.probe.final_loss,
    );
    (tps, probe)
}

/// Trains the small model for [`STEPS`] stage-1 steps on generated scenes and returns the
/// scratch directory holding its checkpoint (`model.safetensors`); the report goes beside it.
fn train_to_scratch() -> tempfile::TempDir {
    let device = Device::flex().autodiff();
    let dataset = SyntheticDataset::generate(
        0,
        SCENES,
        TRAJECTORIES,
        FRAMES,
        &SceneConfig {
            image_size: SIDE,
            ..SceneConfig::default()
        },
    );
    let model_config = XFactorConfig::small(SIDE);
    let config = TrainConfig {
        seed: 0,
        objective: StageObjective::Stage1(Stage1Config {
            lpips_weight: 0.0,
            ..Stage1Config::default()
        }),
        global_batch: 16,
        micro_batch: 16,
        shards: 2,
        schedule: Schedule {
            initial_lr: 1e-5,
            peak_lr: 2e-3,
            final_lr: 1e-4,
            warmup_steps: 20,
            total_steps: STEPS,
        },
        optimizer: AdamWConfig::default(),
    };
    let model = XFactor::new(&model_config, 0, &device).unwrap();
    let mut trainer = Trainer::new(config, model_config, model, None, &device).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    trainer
        .run(&dataset, STEPS, Some((scratch.path(), 0)), |_| {})
        .unwrap();
    scratch
}

/// What the evaluation draws: every scene, 96 TPS transfers of all frames, an 800-step probe
/// and the ground-truth oracle (see the module docs for why).
fn evaluation_spec() -> EvaluationSpec {
    EvaluationSpec {
        seed: 0,
        scenes: EVALUATION_SCENES,
        trajectories: TRAJECTORIES,
        frames: FRAMES,
        tps_pairs: 96,
        tps_frames: FRAMES,
        probe: ProbeSpec {
            steps: 800,
            batch: 64,
            ..ProbeSpec::default()
        },
        oracle: OracleSpec::GroundTruth,
        ..EvaluationSpec::default()
    }
}

/// The files written to `out` match `report`: `report.json` reads back to it, `report.md` has
/// both models' rows, and every figure opens (the probe paths and TPS renders among them).
fn assert_report_files(report: &EvaluationReport, out: &Path) {
    let json: EvaluationReport =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(
        (json.spec, json.figures.clone()),
        (report.spec.clone(), report.figures.clone())
    );
    assert!(
        (json.trained.tps.model.mean_translation_error
            - report.trained.tps.model.mean_translation_error)
            .abs()
            < 1e-9
    );
    let markdown = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(markdown.contains("| trained | TPS |") && markdown.contains("| untrained | probe |"));
    for figure in &report.figures {
        let image = image::open(out.join(figure)).unwrap();
        assert!(image.width() > 0, "{figure}");
    }
    assert!(
        report
            .figures
            .iter()
            .any(|f| f == "trained_probe_paths.png")
    );
    assert!(
        report
            .figures
            .iter()
            .any(|f| f == "untrained_tps_renders.png")
    );
}

#[test]
fn trained_model_beats_untrained_on_tps_and_probe() {
    let started = Instant::now();
    let scratch = train_to_scratch();
    let trained_at = started.elapsed().as_secs_f64();

    let spec = evaluation_spec();
    let out = scratch.path().join("report");
    let report = run_evaluation(
        &spec,
        &scratch.path().join("model.safetensors"),
        &out,
        &Device::flex(),
    )
    .unwrap();
    println!(
        "training_seconds={trained_at:.1} evaluation_seconds={:.1}",
        report.seconds
    );
    let (tps_trained, probe_trained) = summary("trained", &report.trained);
    let untrained = report.untrained.as_ref().unwrap();
    let (tps_untrained, probe_untrained) = summary("untrained", untrained);
    let ideal = report.trained.tps.ideal_transfer.at(30).unwrap().auc;
    let unrelated = report.trained.tps.unrelated_trajectory.at(30).unwrap().auc;
    println!("oracle calibration: ideal_auc30={ideal:.3} unrelated_auc30={unrelated:.3}");
    assert!(ideal > 0.99);
    assert!(
        tps_trained > tps_untrained,
        "TPS {tps_trained} vs untrained {tps_untrained}"
    );
    assert!(
        report.trained.tps.model.mean_translation_error
            < untrained.tps.model.mean_translation_error,
        "TPS translation errors: trained {:?} untrained {:?}",
        report.trained.tps.model,
        untrained.tps.model
    );
    assert!(
        probe_trained > probe_untrained,
        "probe {probe_trained} vs untrained {probe_untrained}"
    );

    assert_report_files(&report, &out);
}
