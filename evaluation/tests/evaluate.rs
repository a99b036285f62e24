//! After a short CPU training run on generated scenes that share camera motions across scenes,
//! the report scores the checkpoint on held-out scenes beside an untrained model and the
//! pose-free baselines, each figure with its spread, in JSON, Markdown and figures. Prints the
//! numbers.
//!
//! Why 16x16 frames, 1300 steps and a 2e-3 peak learning rate: the ground-truth oracle reads a
//! render's pose from the generated frame with the nearest 8x8 thumbnail, and a step at 16x16
//! is about four times cheaper than at 32x32 (about 70 s of training on 2 cores).
//!
//! What this run can and cannot show, measured on held-out scenes (2026-11-26): its
//! reconstruction clearly beats an untrained model (PSNR 15.1 vs 10.9 dB), but its transfers
//! and probe do not beat the untrained model's (TPS AUC@30 0.010 vs 0.006, probe 0.042 vs
//! 0.048, spreads about 0.004 and 0.02): 6 training scenes are too few to generalise, and with
//! 48 training scenes the same 1300 steps never learn to move the camera (TPS 0.000). Whether
//! training teaches transfer that holds on unseen scenes is the first run's guard
//! (`coordinator/tests/first_run.rs`, 4000 steps at 32x32 on 16 scenes); this test checks
//! that the evaluation measures and reports it.

use std::path::Path;
use std::time::Instant;

use burn::tensor::Device;
use data::scenes::SceneConfig;
use data::synthetic::SyntheticDataset;
use evaluation::evaluate::CheckpointUnderTest;
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
/// Held-out scenes the evaluation draws (16 give the probe 14 to train on and 2 to test).
const EVALUATION_SCENES: u64 = 16;
const TRAJECTORIES: u64 = 8;
const FRAMES: usize = 8;

fn summary(name: &str, report: &evaluation::evaluate::ModelReport) {
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
}

/// Stage 1 without LPIPS, `batch` samples a step in one micro-batch of `shards` shards,
/// with the default schedule.
fn stage1_without_lpips(batch: usize, shards: usize) -> TrainConfig {
    TrainConfig {
        seed: 0,
        objective: StageObjective::Stage1(Stage1Config {
            lpips_weight: 0.0,
            ..Stage1Config::default()
        }),
        global_batch: batch,
        micro_batch: batch,
        shards,
        schedule: Schedule::default(),
        optimizer: AdamWConfig::default(),
    }
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
    let mut config = stage1_without_lpips(16, 2);
    config.schedule = Schedule {
        initial_lr: 1e-5,
        peak_lr: 2e-3,
        final_lr: 1e-4,
        warmup_steps: 20,
        total_steps: STEPS,
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
            width: 64,
            ..ProbeSpec::default()
        },
        oracle: OracleSpec::default(),
        ..EvaluationSpec::default()
    }
}

/// The files written to `out` match `report`: `report.json` reads back to it, `report.md` has
/// both models' rows, and every figure opens (the probe paths and TPS renders among them).
fn assert_report_files(report: &EvaluationReport, out: &Path) {
    let json: EvaluationReport =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(
        (json.spec.clone(), json.figures.clone()),
        (report.spec.clone(), report.figures.clone())
    );
    let error = |r: &EvaluationReport| r.stages[0].trained.tps.model.mean_translation_error;
    assert!((error(&json) - error(report)).abs() < 1e-9);
    let markdown = std::fs::read_to_string(out.join("report.md")).unwrap();
    for row in [
        "| trained | TPS |",
        "| untrained | probe |",
        "| no camera motion | TPS |",
        "| copy nearest context |",
        "| mean colour |",
        "**lead over",
    ] {
        assert!(markdown.contains(row), "{row} missing from\n{markdown}");
    }
    for figure in &report.figures {
        let image = image::open(out.join(figure)).unwrap();
        assert!(image.width() > 0, "{figure}");
    }
    assert!(
        report
            .figures
            .iter()
            .any(|f| f == "stage1_trained_probe_paths.png")
    );
    assert!(
        report
            .figures
            .iter()
            .any(|f| f == "stage1_untrained_tps_renders.png")
    );
}

#[test]
fn a_trained_checkpoint_is_scored_on_held_out_scenes_beside_its_baselines() {
    let started = Instant::now();
    let scratch = train_to_scratch();
    let trained_at = started.elapsed().as_secs_f64();

    let spec = evaluation_spec();
    let out = scratch.path().join("report");
    let checkpoint = CheckpointUnderTest {
        label: "stage1".into(),
        weights: scratch.path().join("model.safetensors"),
        step: None,
        context_views: 1,
    };
    let report = run_evaluation(&spec, &[checkpoint], &out, &Device::flex()).unwrap();
    assert_eq!(report.scenes.split, "test");
    let stage = &report.stages[0];
    println!(
        "training_seconds={trained_at:.1} evaluation_seconds={:.1}",
        report.seconds
    );
    summary("trained", &stage.trained);
    let untrained = stage.untrained.as_ref().unwrap();
    summary("untrained", untrained);
    let baselines = &stage.baselines;
    let tps = &stage.trained.tps;
    let auc30 = |m: &evaluation::metrics::CameraMetrics| m.at(30).unwrap().auc;
    println!(
        "copy_psnr={:.2} mean_colour_psnr={:.2} no_motion_tps_auc30={:.3} no_motion_probe_auc30={:.3} ideal_auc30={:.3} unrelated_auc30={:.3} copy_share={:.3}",
        baselines.copy.psnr,
        baselines.mean_colour.psnr,
        auc30(&baselines.tps_no_motion),
        auc30(&baselines.probe_no_motion),
        auc30(&tps.ideal_transfer),
        auc30(&tps.unrelated_trajectory),
        tps.copy_share,
    );
    assert!(auc30(&tps.ideal_transfer) > 0.99);
    // A camera that never moves has no translation direction: 90 degrees, no AUC.
    assert_eq!(auc30(&baselines.tps_no_motion), 0.0);
    assert_eq!(auc30(&baselines.probe_no_motion), 0.0);
    let (ours, fresh) = (&stage.trained.reconstruction, &untrained.reconstruction);
    assert!(
        ours.psnr - fresh.psnr > 4.0 * (ours.psnr_spread + fresh.psnr_spread),
        "PSNR {ours:?} vs untrained {fresh:?}"
    );
    for spread in [ours.psnr_spread, ours.ssim_spread] {
        assert!(spread > 0.0 && spread.is_finite(), "{ours:?}");
    }
    assert!(tps.model.spread.is_some_and(|s| s.auc30.is_finite()));
    // Measured 8.5% (8 of 96 transfers): blurry renders of this small model sometimes sit
    // nearer the source's frames; a model that copied the source would score 100%.
    assert!(tps.copy_share < 0.25, "{tps:?}");

    assert_report_files(&report, &out);
}

/// A checkpoint whose `model.compute` asks for bf16, evaluated on wgpu's WGSL (lavapipe here),
/// which has no bf16: refused naming the key, before any weight is loaded (the first bf16 op
/// would panic).
#[test]
fn a_checkpoint_whose_compute_the_device_lacks_is_refused_naming_the_key() {
    use trainer_core::backend::{Backend, BackendDevices};
    let wgpu = Backend::Wgpu.device().unwrap();
    assert!(
        !wgpu.supports_dtype(burn::tensor::FloatDType::BF16),
        "this test needs a device without bf16"
    );
    let cpu = Device::flex().autodiff();
    let mut model_config = XFactorConfig::tiny(SIDE);
    model_config.compute = settings::model::Precision::Bf16;
    let config = stage1_without_lpips(1, 1);
    let model = XFactor::new(&model_config, 0, &cpu).unwrap();
    let trainer = Trainer::new(config, model_config, model, None, &cpu).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    trainer.save_checkpoint(scratch.path()).unwrap();
    let checkpoint = CheckpointUnderTest {
        label: "stage1".into(),
        weights: scratch.path().join("model.safetensors"),
        step: None,
        context_views: 1,
    };
    let out = scratch.path().join("report");
    let error = run_evaluation(&evaluation_spec(), &[checkpoint], &out, &wgpu)
        .unwrap_err()
        .to_string();
    assert!(error.contains("compute bf16"), "{error}");
    assert!(error.contains("model.safetensors"), "{error}");
}
