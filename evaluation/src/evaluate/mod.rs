//! The `evaluate` stage: each checkpoint of a job (stage 1's and stage 2's final weights, each
//! with the context views its stage trained with) scored on held-out generated scenes by
//! reconstruction (autoencoding), TPS and the pose probe, beside baselines that know no pose
//! (copy the context view, its mean colour, no camera motion) and an untrained model, computed
//! on the same frames and pairs; every figure with its bootstrap spread. Real test sequences are
//! reconstructed under E-RayZer's protocol when asked for. Written as `report.json`,
//! `report.md` and PNG figures.

use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::tensor::Device;
use data::Split;
use data::scenes::SceneConfig;
use data::synthetic::SyntheticDataset;
use serde::{Deserialize, Serialize};
use trainer_core::lpips::Lpips;
use trainer_core::{XFactor, XFactorConfig, checkpoint};

use crate::error::{EvalError, io_error};
use crate::metrics::{CameraMetrics, ReconstructionReport};
use crate::oracle::{
    ClassicalOracle, ClassicalSettings, ExternalOracle, GroundTruthOracle, PoseOracle,
};
use crate::probe::ProbeReport;
use crate::sequences::{ProtocolSet, SequenceReport, load_protocol};
use crate::tps::TpsReport;
use measurements::{
    Figures, baselines, evaluate_probe, evaluate_tps, generated_reconstruction,
    sequence_reconstructions,
};
use settings::evaluation::{EvaluationSpec, OracleSpec};

mod markdown;
mod measurements;
mod reconstruction;

pub use markdown::markdown;

/// Pairs drawn in the render-grid figure.
const GRID_PAIRS: usize = 3;

/// One checkpoint to score, as its stage trained it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointUnderTest {
    /// What it is (`stage1`, `stage2`, `checkpoint`): names its rows and figures.
    pub label: String,
    /// Its weights (the `.json` configuration beside them).
    pub weights: PathBuf,
    /// The step it was committed at, when known.
    pub step: Option<u64>,
    /// Context views it renders from (stage 1: 1; stage 2: its views less the target).
    pub context_views: usize,
}

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

/// What scores without reading any pose, on the same frames and pairs as the models.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Baselines {
    /// Every target rendered as the context view nearest to it.
    pub copy: ReconstructionReport,
    /// Every target one flat image of the context views' mean colour.
    pub mean_colour: ReconstructionReport,
    /// Every transfer's renders all B's context view: a camera that never moves.
    pub tps_no_motion: CameraMetrics,
    /// The probe predicting the reference pose for every frame.
    pub probe_no_motion: CameraMetrics,
}

impl Baselines {
    /// The better reconstruction baseline by PSNR, with its name.
    pub fn best_reconstruction(&self) -> (&'static str, &ReconstructionReport) {
        if self.mean_colour.psnr > self.copy.psnr {
            ("mean_colour", &self.mean_colour)
        } else {
            ("copy", &self.copy)
        }
    }
}

/// One checkpoint's scores beside its baselines.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageReport {
    /// The checkpoint.
    pub checkpoint: CheckpointUnderTest,
    /// Its numbers.
    pub trained: ModelReport,
    /// An untrained model's numbers with the same context views, when asked for.
    pub untrained: Option<ModelReport>,
    /// The pose-free baselines.
    pub baselines: Baselines,
}

/// The scenes every figure is measured on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluationScenes {
    /// `test`: generated from the held-out draws no training job generates.
    pub split: String,
    /// Scenes.
    pub scenes: u64,
    /// Camera paths, each rendered in every scene.
    pub trajectories: u64,
    /// Frames per path.
    pub frames: usize,
    /// Seed of the draws.
    pub seed: u64,
}

/// The whole evaluation, as written to `report.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluationReport {
    /// The spec it ran with.
    pub spec: EvaluationSpec,
    /// The scenes it ran on.
    pub scenes: EvaluationScenes,
    /// The model's configuration.
    pub model: XFactorConfig,
    /// One entry per checkpoint, in the order given (stage 1, then stage 2).
    pub stages: Vec<StageReport>,
    /// Every evaluation setting that departs from the release's or the paper's.
    pub departures: Vec<String>,
    /// Figures written beside the report, relative to it.
    pub figures: Vec<String>,
    /// Wall time of the evaluation.
    pub seconds: f64,
}

impl EvaluationReport {
    /// The last checkpoint's scores: the job's final model.
    pub fn last(&self) -> Option<&StageReport> {
        self.stages.last()
    }
}

fn oracle_for(
    spec: &OracleSpec,
    dataset: &SyntheticDataset,
    scene: &SceneConfig,
) -> Box<dyn PoseOracle> {
    match spec {
        OracleSpec::GroundTruth { subdivisions: 1 } => {
            Box::new(GroundTruthOracle::from_dataset(dataset))
        }
        OracleSpec::GroundTruth { subdivisions } => {
            let _span = tracing::info_span!("oracle_views", subdivisions).entered();
            Box::new(GroundTruthOracle::between_frames(
                dataset,
                *subdivisions as usize,
                scene,
            ))
        }
        OracleSpec::Classical => Box::new(ClassicalOracle::new(ClassicalSettings {
            fov_degrees: scene.fov_degrees,
            ..ClassicalSettings::default()
        })),
        OracleSpec::External { program, args } => Box::new(ExternalOracle::new(program, args)),
    }
}

/// Everything shared by the checkpoints and models of one evaluation.
struct Context<'a> {
    spec: &'a EvaluationSpec,
    dataset: SyntheticDataset,
    protocol_sets: Vec<ProtocolSet>,
    oracle: Box<dyn PoseOracle>,
    lpips: Option<Lpips>,
    device: Device,
    out_dir: &'a Path,
}

/// Scores one model with `context_views` context views, writing its figures with `prefix`.
fn evaluate_model(
    model: &XFactor,
    context_views: usize,
    context: &Context<'_>,
    prefix: &str,
    figures: &mut Vec<String>,
) -> Result<ModelReport, EvalError> {
    let mut figures = Figures {
        out_dir: context.out_dir,
        names: figures,
    };
    let reconstruction =
        generated_reconstruction(model, context_views, context, prefix, &mut figures)?;
    let sequences = sequence_reconstructions(model, context, prefix, &mut figures)?;
    let tps = evaluate_tps(model, context_views, context, prefix, &mut figures)?;
    let probe = evaluate_probe(model, context, prefix, &mut figures)?;
    Ok(ModelReport {
        reconstruction,
        tps,
        probe,
        sequences,
    })
}

/// Scores one checkpoint, its untrained twin when the spec asks, and the baselines.
fn evaluate_checkpoint(
    under_test: &CheckpointUnderTest,
    context: &Context<'_>,
    figures: &mut Vec<String>,
) -> Result<(StageReport, XFactorConfig), EvalError> {
    let _span = tracing::info_span!("checkpoint", label = %under_test.label).entered();
    // Before the weights are loaded: on a device without the half type, loading would panic.
    let stored = checkpoint::read_config(&under_test.weights)?;
    trainer_core::trainer::check_device_arithmetic(&stored, &context.device)
        .map_err(|e| EvalError::Invalid(format!("{}: {e}", under_test.weights.display())))?;
    let (model, config) = checkpoint::load(&under_test.weights, &context.device)?;
    let views = under_test.context_views.max(1);
    let label = &under_test.label;
    let trained = evaluate_model(&model, views, context, &format!("{label}_trained"), figures)?;
    let untrained = if context.spec.compare_untrained {
        let fresh = XFactor::new(&config, context.spec.seed, &context.device)
            .map_err(|e| EvalError::Invalid(e.to_string()))?;
        let prefix = format!("{label}_untrained");
        Some(evaluate_model(&fresh, views, context, &prefix, figures)?)
    } else {
        None
    };
    let report = StageReport {
        checkpoint: under_test.clone(),
        trained,
        untrained,
        baselines: baselines(views, context)?,
    };
    Ok((report, config))
}

/// Scores every checkpoint of `checkpoints` (each with its `.json` configuration beside it; all
/// of one image size) on `device` and writes `report.json`, `report.md` and the figures into
/// `out_dir` (created if needed).
pub fn run_evaluation(
    spec: &EvaluationSpec,
    checkpoints: &[CheckpointUnderTest],
    out_dir: &Path,
    device: &Device,
) -> Result<EvaluationReport, EvalError> {
    let started = Instant::now();
    let _span = tracing::info_span!("evaluate", checkpoints = checkpoints.len()).entered();
    spec.validate()?;
    let first = checkpoints
        .first()
        .ok_or_else(|| EvalError::Invalid("no checkpoint to evaluate".to_string()))?;
    std::fs::create_dir_all(out_dir).map_err(|e| io_error(out_dir, e))?;
    let config = checkpoint::read_config(&first.weights)?;
    let context = build_context(spec, &config, device, out_dir)?;
    let mut figures = Vec::new();
    let mut stages = Vec::with_capacity(checkpoints.len());
    let mut model = config;
    for under_test in checkpoints {
        let (stage, config) = evaluate_checkpoint(under_test, &context, &mut figures)?;
        if config.image_size != model.image_size {
            return Err(EvalError::Invalid(format!(
                "{} is a {}-pixel model, {} a {}-pixel one: one evaluation scores one image size",
                under_test.weights.display(),
                config.image_size,
                first.weights.display(),
                model.image_size
            )));
        }
        stages.push(stage);
        model = config;
    }
    let report = EvaluationReport {
        spec: spec.clone(),
        scenes: EvaluationScenes {
            split: "test".to_string(),
            scenes: spec.scenes,
            trajectories: spec.trajectories,
            frames: spec.frames,
            seed: spec.seed,
        },
        model,
        stages,
        departures: departures(spec),
        figures,
        seconds: started.elapsed().as_secs_f64(),
    };
    write_report(&report, out_dir)?;
    tracing::info!(seconds = report.seconds, dir = %out_dir.display(), "evaluation written");
    Ok(report)
}

/// The spec's settings that differ from the release's evaluation or the paper's, in words, then
/// the job's own notes on its training.
fn departures(spec: &EvaluationSpec) -> Vec<String> {
    let mut notes = vec![
        "generated held-out scenes (test split), not a dataset's test split".to_string(),
        match spec.oracle {
            OracleSpec::GroundTruth { subdivisions: 1 } => "oracle GroundTruth".to_string(),
            OracleSpec::GroundTruth { subdivisions } => format!(
                "oracle GroundTruth, {subdivisions} views per gap between generated frames"
            ),
            ref other => format!("oracle {other:?}"),
        },
    ];
    if spec.probe.rotation_from_identity {
        notes.push(
            "probe.rotation_from_identity: the probe's matrix starts at the identity (the release's starts at zero)"
                .to_string(),
        );
    }
    if spec.probe.steps != 10_000 || spec.probe.batch != 64 {
        notes.push(format!(
            "probe: {} steps of {} (the paper: 10000 of 64)",
            spec.probe.steps, spec.probe.batch
        ));
    }
    if spec.tps_frames != 5 {
        notes.push(format!("tps_frames: {} (the paper: 5)", spec.tps_frames));
    }
    notes.extend(spec.notes.iter().cloned());
    notes
}

/// Generates the held-out scenes and loads the real sequences, pose oracle and LPIPS every
/// checkpoint shares.
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
        SyntheticDataset::generate_split(
            spec.seed,
            Split::Test,
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
        assert_eq!(spec.probe.width, 256, "the paper's probe width by default");
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
        let noted = EvaluationSpec {
            notes: vec!["stage 2 keeps stage 1's Render".into()],
            ..spec
        };
        let notes = departures(&noted);
        assert!(
            notes.iter().any(|n| n.contains("probe: 10 steps")),
            "{notes:?}"
        );
        assert_eq!(
            notes.last().map(String::as_str),
            Some("stage 2 keeps stage 1's Render"),
            "the job's notes come last"
        );
    }
}
