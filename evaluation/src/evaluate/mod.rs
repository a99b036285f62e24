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
use serde::{Deserialize, Serialize};
use settings::evaluation::{EvaluationSpec, OracleSpec};
use trainer_core::{XFactor, XFactorConfig, checkpoint};

use crate::error::{EvalError, io_error};
use crate::metrics::{CameraMetrics, ReconstructionReport};
use crate::probe::ProbeReport;
use crate::sequences::SequenceReport;
use crate::tps::TpsReport;
use gather::{Gathered, gather};
use write::FigureSet;

mod gather;
mod infer;
mod markdown;
mod score;
mod write;

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

/// A checkpoint's models: its weights, and an untrained twin of its configuration when the
/// spec asks for one.
struct Models {
    trained: XFactor,
    untrained: Option<XFactor>,
    config: XFactorConfig,
}

/// Loads `under_test` (and its untrained twin) onto `device`.
fn load_models(
    under_test: &CheckpointUnderTest,
    spec: &EvaluationSpec,
    device: &Device,
) -> Result<Models, EvalError> {
    // Before the weights are loaded: on a device without the half type, loading would panic.
    let stored = checkpoint::read_config(&under_test.weights)?;
    trainer_core::trainer::check_device_arithmetic(&stored, device)
        .map_err(|e| EvalError::Invalid(format!("{}: {e}", under_test.weights.display())))?;
    let (trained, config) = checkpoint::load(&under_test.weights, device)?;
    let untrained = match spec.compare_untrained {
        true => Some(
            XFactor::new(&config, spec.seed, device)
                .map_err(|e| EvalError::Invalid(e.to_string()))?,
        ),
        false => None,
    };
    Ok(Models {
        trained,
        untrained,
        config,
    })
}

/// Runs one model on everything gathered and scores it, keeping what its figures draw.
fn run_and_score(
    model: &XFactor,
    views: usize,
    gathered: &Gathered<'_>,
    prefix: String,
    figures: &mut Vec<FigureSet>,
) -> Result<ModelReport, EvalError> {
    let _span = tracing::info_span!("model", name = %prefix).entered();
    let outputs = infer::run_model(model, views, gathered)?;
    let scored = score::score_model(&outputs, views, gathered)?;
    let paths = (scored.transfer_paths, scored.probe_paths);
    figures.push(FigureSet::new(prefix, views, &outputs, paths, gathered)?);
    Ok(scored.report)
}

/// Scores every checkpoint of `checkpoints` (each with its `.json` configuration beside it; all
/// of one image size) on `device` and writes `report.json`, `report.md` and the figures into
/// `out_dir` (created if needed). One pass: gather the frames every model is shown and scored
/// on ([`gather`]); for each checkpoint, run its models and the pose-free baselines
/// ([`infer`]) and score them ([`score`]); then write the figures and the report ([`write`]).
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
    let views: Vec<usize> = checkpoints.iter().map(|c| c.context_views.max(1)).collect();
    let gathered = gather(spec, &config, &views, device)?;
    let mut figures = Vec::new();
    let mut stages = Vec::with_capacity(checkpoints.len());
    for (under_test, &views) in checkpoints.iter().zip(&views) {
        let _span = tracing::info_span!("checkpoint", label = %under_test.label).entered();
        let models = load_models(under_test, spec, device)?;
        if models.config.image_size != config.image_size {
            return Err(EvalError::Invalid(format!(
                "{} is a {}-pixel model, {} a {}-pixel one: one evaluation scores one image size",
                under_test.weights.display(),
                models.config.image_size,
                first.weights.display(),
                config.image_size
            )));
        }
        let label = &under_test.label;
        let trained = run_and_score(
            &models.trained,
            views,
            &gathered,
            format!("{label}_trained"),
            &mut figures,
        )?;
        let untrained = match &models.untrained {
            Some(model) => Some(run_and_score(
                model,
                views,
                &gathered,
                format!("{label}_untrained"),
                &mut figures,
            )?),
            None => None,
        };
        let baselines = infer::run_baselines(views, &gathered)?;
        stages.push(StageReport {
            checkpoint: under_test.clone(),
            trained,
            untrained,
            baselines: score::score_baselines(&baselines, views, &gathered)?,
        });
    }
    let mut report = EvaluationReport {
        spec: spec.clone(),
        scenes: EvaluationScenes {
            split: "test".to_string(),
            scenes: spec.scenes,
            trajectories: spec.trajectories,
            frames: spec.frames,
            seed: spec.seed,
        },
        model: config,
        stages,
        departures: departures(spec),
        figures: Vec::new(),
        seconds: started.elapsed().as_secs_f64(),
    };
    write::write(&mut report, &figures, out_dir)?;
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
            OracleSpec::GroundTruth { subdivisions } => {
                format!("oracle GroundTruth, {subdivisions} views per gap between generated frames")
            }
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
