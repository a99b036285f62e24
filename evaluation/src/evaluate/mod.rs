//! The `evaluate` stage: reconstruction (autoencoding), TPS and the pose probe of one checkpoint
//! on generated scenes, reconstruction of real test sequences under E-RayZer's protocol when
//! asked for, next to the same numbers for an untrained model of the same shape,
//! written as `report.json`, `report.md` and PNG figures.

use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::tensor::{Device, Tensor, TensorData};
use data::Image;
use data::scenes::SceneConfig;
use data::synthetic::SyntheticDataset;
use serde::{Deserialize, Serialize};
use trainer_core::lpips::Lpips;
use trainer_core::{XFactor, XFactorConfig, checkpoint};

use crate::error::{EvalError, io_error};
use crate::inference::{pose_latents, probe_features, render_targets};
use crate::metrics::{CameraMetrics, ReconstructionReport, psnr, ssim};
use crate::oracle::{
    ClassicalOracle, ClassicalSettings, ExternalOracle, GroundTruthOracle, PoseOracle,
};
use crate::probe::{ProbeReport, ProbeSequence};
use crate::sequences::{ProtocolSet, SequenceReport, load_protocol};
use crate::tps::TpsReport;
use measurements::{
    Figures, evaluate_probe, evaluate_tps, generated_reconstruction, sequence_reconstructions,
};
use settings::evaluation::{EvaluationSpec, OracleSpec};

mod measurements;

/// Pairs drawn in the render-grid figure.
const GRID_PAIRS: usize = 3;

/// Every number for one model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelReport {
    /// Autoencoding.
    pub reconstruction: ReconstructionReport,
    /// Transferability.
    pub tps: TpsReport,
    /// Pose probe.
    pub probe: ProbeReport,
    /// Reconstruction of real test sequences under E-RayZer's protocol, per dataset.
    #[serde(default)]
    pub sequences: Vec<SequenceReport>,
}

/// The whole evaluation, as written to `report.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluationReport {
    /// Checkpoint evaluated.
    pub checkpoint: PathBuf,
    /// The spec it ran with.
    pub spec: EvaluationSpec,
    /// The model's configuration.
    pub model: XFactorConfig,
    /// The checkpoint's numbers.
    pub trained: ModelReport,
    /// An untrained model's numbers, when asked for.
    pub untrained: Option<ModelReport>,
    /// Figures written beside the report, relative to it.
    pub figures: Vec<String>,
    /// Wall time of the evaluation.
    pub seconds: f64,
}

fn oracle_for(
    spec: &OracleSpec,
    dataset: &SyntheticDataset,
    scene: &SceneConfig,
) -> Box<dyn PoseOracle> {
    match spec {
        OracleSpec::GroundTruth => Box::new(GroundTruthOracle::from_dataset(dataset)),
        OracleSpec::Classical => Box::new(ClassicalOracle::new(ClassicalSettings {
            fov_degrees: scene.fov_degrees,
            ..ClassicalSettings::default()
        })),
        OracleSpec::External { program, args } => Box::new(ExternalOracle::new(program, args)),
    }
}

/// Everything shared by the trained and untrained runs.
struct Context<'a> {
    spec: &'a EvaluationSpec,
    dataset: SyntheticDataset,
    protocol_sets: Vec<ProtocolSet>,
    oracle: Box<dyn PoseOracle>,
    lpips: Option<Lpips>,
    device: Device,
    out_dir: &'a Path,
}

/// Renders every frame of each sequence after the first from the first, with the poses PoseEnc
/// reads from the sequence itself.
fn reconstruct<'s>(
    model: &XFactor,
    sequences: impl Iterator<Item = &'s [Image]>,
    context: &Context<'_>,
) -> Result<(ReconstructionReport, Vec<Vec<Image>>), EvalError> {
    let (mut psnrs, mut ssims, mut lpipses) = (Vec::new(), Vec::new(), Vec::new());
    let mut grid = Vec::new();
    for frames in sequences {
        let first = &frames[0];
        let targets = &frames[1..];
        let latents = pose_latents(model, first, targets, &context.device)?;
        let zero = vec![0.0; latents.first().map_or(0, Vec::len)];
        let renders = render_targets(
            model,
            std::slice::from_ref(first),
            &[zero],
            &latents,
            &context.device,
        )?;
        for (render, target) in renders.iter().zip(targets) {
            psnrs.push(psnr(render, target)?);
            ssims.push(ssim(render, target)?);
        }
        if let Some(lpips) = &context.lpips {
            let upload = |images: &[Image]| {
                let values: Vec<f32> = images
                    .iter()
                    .flat_map(|i| i.pixels.iter().copied())
                    .collect();
                Tensor::<4>::from_data(
                    TensorData::new(values, [images.len(), first.height, first.width, 3]),
                    &context.device,
                )
            };
            let distances = lpips
                .distance(upload(&renders), upload(targets))
                .try_into_vec_as::<f32>()
                .map_err(|e| EvalError::Tensor(format!("{e:?}")))?;
            lpipses.extend(distances.iter().map(|&d| f64::from(d)));
        }
        if grid.len() < 2 * GRID_PAIRS {
            grid.push(frames.to_vec());
            grid.push([vec![first.clone()], renders].concat());
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    Ok((
        ReconstructionReport {
            frames: psnrs.len(),
            psnr: mean(&psnrs),
            ssim: mean(&ssims),
            lpips: (!lpipses.is_empty()).then(|| mean(&lpipses)),
        },
        grid,
    ))
}

fn probe_sequences(
    model: &XFactor,
    context: &Context<'_>,
) -> Result<(Vec<ProbeSequence>, Vec<ProbeSequence>), EvalError> {
    let first_test_scene = context
        .spec
        .scenes
        .saturating_sub(context.spec.probe.test_scenes);
    let (mut train, mut test) = (Vec::new(), Vec::new());
    for sequence in &context.dataset.sequences {
        let latents = probe_features(
            model,
            &sequence.frames[0],
            &sequence.frames,
            &context.device,
        )?;
        let item = ProbeSequence {
            latents,
            poses: sequence.poses.clone(),
        };
        if sequence.scene < first_test_scene {
            train.push(item);
        } else {
            test.push(item);
        }
    }
    Ok((train, test))
}

/// Evaluates one model, writing its figures with `prefix`.
fn evaluate_model(
    model: &XFactor,
    context: &Context<'_>,
    prefix: &str,
    figures: &mut Vec<String>,
) -> Result<ModelReport, EvalError> {
    let mut figures = Figures {
        out_dir: context.out_dir,
        names: figures,
    };
    let reconstruction = generated_reconstruction(model, context, prefix, &mut figures)?;
    let sequences = sequence_reconstructions(model, context, prefix, &mut figures)?;
    let tps = evaluate_tps(model, context, prefix, &mut figures)?;
    let probe = evaluate_probe(model, context, prefix, &mut figures)?;
    Ok(ModelReport {
        reconstruction,
        tps,
        probe,
        sequences,
    })
}

/// Evaluates the checkpoint `weights` (its `.json` configuration beside it) on `device` and
/// writes `report.json`, `report.md` and the figures into `out_dir` (created if needed).
pub fn run_evaluation(
    spec: &EvaluationSpec,
    weights: &Path,
    out_dir: &Path,
    device: &Device,
) -> Result<EvaluationReport, EvalError> {
    let started = Instant::now();
    let _span = tracing::info_span!("evaluate", checkpoint = %weights.display()).entered();
    spec.validate()?;
    std::fs::create_dir_all(out_dir).map_err(|e| io_error(out_dir, e))?;
    let (model, config) = checkpoint::load(weights, device)?;
    let context = build_context(spec, &config, device, out_dir)?;
    let mut figures = Vec::new();
    let trained = evaluate_model(&model, &context, "trained", &mut figures)?;
    let untrained = if spec.compare_untrained {
        let baseline = XFactor::new(&config, spec.seed, device)
            .map_err(|e| EvalError::Invalid(e.to_string()))?;
        Some(evaluate_model(
            &baseline,
            &context,
            "untrained",
            &mut figures,
        )?)
    } else {
        None
    };
    let report = EvaluationReport {
        checkpoint: weights.to_path_buf(),
        spec: spec.clone(),
        model: config,
        trained,
        untrained,
        figures,
        seconds: started.elapsed().as_secs_f64(),
    };
    write_report(&report, out_dir)?;
    tracing::info!(seconds = report.seconds, dir = %out_dir.display(), "evaluation written");
    Ok(report)
}

/// Generates the scenes and loads the real sequences, pose oracle and LPIPS both models share.
fn build_context<'a>(
    spec: &'a EvaluationSpec,
    config: &XFactorConfig,
    device: &Device,
    out_dir: &'a Path,
) -> Result<Context<'a>, EvalError> {
    let scene_config = SceneConfig {
        image_size: config.image_size,
        ..SceneConfig::default()
    };
    let dataset = {
        let _span = tracing::info_span!(
            "generate",
            scenes = spec.scenes,
            trajectories = spec.trajectories
        )
        .entered();
        SyntheticDataset::generate(
            spec.seed,
            spec.scenes,
            spec.trajectories,
            spec.frames,
            &scene_config,
        )
    };
    let protocol_sets = spec
        .sequences
        .iter()
        .map(|protocol| {
            let _span = tracing::info_span!("load_sequences", dataset = ?protocol.kind).entered();
            load_protocol(protocol, config.image_size)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let lpips =
        match &spec.lpips_weights {
            Some(path) => Some(Lpips::from_file(path, device).map_err(|e| {
                EvalError::Invalid(format!("LPIPS weights {}: {e}", path.display()))
            })?),
            None => None,
        };
    Ok(Context {
        spec,
        oracle: oracle_for(&spec.oracle, &dataset, &scene_config),
        dataset,
        protocol_sets,
        lpips,
        device: device.clone(),
        out_dir,
    })
}

/// Writes `report` into `out_dir` as `report.json` and `report.md`.
fn write_report(report: &EvaluationReport, out_dir: &Path) -> Result<(), EvalError> {
    let json_path = out_dir.join("report.json");
    let json = serde_json::to_string_pretty(report).map_err(|e| io_error(&json_path, e))?;
    std::fs::write(&json_path, json).map_err(|e| io_error(&json_path, e))?;
    let md_path = out_dir.join("report.md");
    std::fs::write(&md_path, markdown(report)).map_err(|e| io_error(&md_path, e))?;
    Ok(())
}

fn camera_cells(metrics: &CameraMetrics) -> String {
    let at =
        |t: u32, f: fn(&crate::metrics::ThresholdScores) -> f64| metrics.at(t).map_or(f64::NAN, f);
    let optional = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{v:.3}"));
    format!(
        "{:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {} | {}",
        at(5, |s| s.rotation_accuracy),
        at(5, |s| s.translation_accuracy),
        at(20, |s| s.rotation_auc),
        at(20, |s| s.translation_auc),
        at(20, |s| s.auc),
        at(30, |s| s.auc),
        optional(metrics.trajectory_error_scale_invariant),
        optional(metrics.trajectory_error_unscaled),
    )
}

/// The report as Markdown tables: the headline numbers of each model, then the oracle's
/// calibration.
pub fn markdown(report: &EvaluationReport) -> String {
    let mut rows = vec![("trained", &report.trained)];
    if let Some(untrained) = &report.untrained {
        rows.push(("untrained", untrained));
    }
    let mut text = format!(
        "# XFactor evaluation\n\nCheckpoint `{}`; {} scenes x {} trajectories x {} frames (seed {}); oracle `{}`; {:.1} s.\n\n",
        report.checkpoint.display(),
        report.spec.scenes,
        report.spec.trajectories,
        report.spec.frames,
        report.spec.seed,
        report.trained.tps.oracle,
        report.seconds
    );
    text.push_str("## Reconstruction (autoencoding)\n\n| model | frames | PSNR | SSIM | LPIPS |\n| --- | --- | --- | --- | --- |\n");
    for (name, r) in &rows {
        let c = &r.reconstruction;
        let lpips = c.lpips.map_or("-".to_string(), |v| format!("{v:.4}"));
        text.push_str(&format!(
            "| {name} | {} | {:.2} | {:.4} | {lpips} |\n",
            c.frames, c.psnr, c.ssim
        ));
    }
    text.push_str("\n## Transferability (TPS) and pose probe\n\n| model | measure | Rac@5 | Tac@5 | Rot_Auc@20 | Trans_Auc@20 | SE3_Auc@20 | SE3_Auc@30 | traj err (scale-inv.) | traj err (unscaled) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
    for (name, r) in &rows {
        text.push_str(&format!(
            "| {name} | TPS | {} |\n",
            camera_cells(&r.tps.model)
        ));
        text.push_str(&format!(
            "| {name} | probe | {} |\n",
            camera_cells(&r.probe.metrics)
        ));
    }
    if !report.trained.sequences.is_empty() {
        text.push_str("\n## Real test sequences (E-RayZer's protocol: fixed length, equally spaced frames, first and last included)\n\n| model | dataset | length | sequences | skipped (short) | frames | PSNR | SSIM | LPIPS |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
        for (name, r) in &rows {
            for set in &r.sequences {
                let c = &set.reconstruction;
                let lpips = c.lpips.map_or("-".to_string(), |v| format!("{v:.4}"));
                text.push_str(&format!(
                    "| {name} | {} | {} | {} | {} | {} | {:.2} | {:.4} | {lpips} |\n",
                    set.kind.name(),
                    set.length,
                    set.sequences,
                    set.skipped_short,
                    c.frames,
                    c.psnr,
                    c.ssim
                ));
            }
        }
    }
    let tps = &report.trained.tps;
    text.push_str(&format!(
        "\n## Oracle calibration\n\n{} pairs x {} frames ({} skipped, {} unreadable renders).\n\n| transfer | Rac@5 | Tac@5 | Rot_Auc@20 | Trans_Auc@20 | SE3_Auc@20 | SE3_Auc@30 | traj err (scale-inv.) | traj err (unscaled) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n| ideal (true rendering) | {} |\n| unrelated trajectory | {} |\n",
        tps.pairs,
        tps.frames_per_pair,
        tps.skipped,
        tps.failures,
        camera_cells(&tps.ideal_transfer),
        camera_cells(&tps.unrelated_trajectory)
    ));
    text.push_str("\n## Figures\n\n");
    for figure in &report.figures {
        text.push_str(&format!("![{figure}]({figure})\n"));
    }
    text
}

/// The spec in `path` (JSON), or the default when `path` is `None`.
pub fn read_spec(path: Option<&Path>) -> Result<EvaluationSpec, EvalError> {
    match path {
        None => Ok(EvaluationSpec::default()),
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(|e| io_error(path, e))?;
            serde_json::from_str(&text)
                .map_err(|e| EvalError::Invalid(format!("{}: {e}", path.display())))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_round_trips_and_fills_defaults() {
        let spec: EvaluationSpec = serde_json::from_str(r#"{"scenes": 4, "oracle": {"kind": "external", "program": "vggt-poses"}, "probe": {"steps": 10}}"#).unwrap();
        assert_eq!(spec.scenes, 4);
        assert_eq!(spec.probe.steps, 10);
        assert_eq!(spec.probe.width, 64);
        assert_eq!(
            spec.oracle,
            OracleSpec::External {
                program: "vggt-poses".into(),
                args: vec![]
            }
        );
        let back: EvaluationSpec =
            serde_json::from_str(&serde_json::to_string(&spec).unwrap()).unwrap();
        assert_eq!(back, spec);
        assert!(serde_json::from_str::<EvaluationSpec>(r#"{"scene": 4}"#).is_err());
    }
}
