//! `xfactor`: the user-facing tool of the evaluation crate.
//!
//! `xfactor transfer` renders a scene along the camera motion of another video;
//! `xfactor evaluate` runs the paper's evaluation of a checkpoint on generated scenes;
//! `xfactor import-checkpoint` turns the authors' released clu checkpoint into ours;
//! `xfactor compare` lays several runs' evaluation reports side by side;
//! `xfactor curve` evaluates every checkpoint a run committed: transferability against steps.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Parser, Subcommand, ValueEnum};
use evaluation::evaluate::{CheckpointUnderTest, read_spec};
use evaluation::{Sampling, TransferRequest, run_evaluation, run_transfer_sampled};
use settings::evaluation::OracleSpec;
use telemetry::logging::LogArgs;
use trainer_core::backend::{BackendArgs, BackendDevices};

/// Trajectory transfer and the paper's evaluation of an XFactor checkpoint.
#[derive(Debug, Parser)]
#[command(
    name = "xfactor",
    version = telemetry::VERSION,
    after_help = "Example: render a scene along the camera path of a video (videos are decoded through ffmpeg):
  xfactor transfer --checkpoint ckpt/model.safetensors --trajectory walk.mp4 \\
      --scene room.mp4 --frames 30 --out transfer-out
writes frames/, strip.png, transfer.gif and transfer.mp4 under --out"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Renders a scene along the camera motion of another video
    Transfer(TransferArgs),
    /// Runs the paper's evaluation of a checkpoint on generated scenes
    Evaluate(EvaluateArgs),
    /// Imports the authors' released clu checkpoint (the `.flax` its `checkpoint` file names)
    /// as a checkpoint of ours: weights, optimiser state and LPIPS weights
    ImportCheckpoint(ImportArgs),
    /// Lays the evaluation reports of several runs side by side (the paper's Table 3 layout):
    /// compare.md and compare.png
    Compare(CompareArgs),
    /// Evaluates every checkpoint a run committed in one stage with the run's own evaluation
    /// settings: TPS AUC@30 against steps beside the unrelated-path calibration, as CSV, PNG
    /// and SVG
    Curve(CurveArgs),
}

#[derive(Debug, clap::Args)]
struct CurveArgs {
    /// The run's folder (`xfactor-local --dir`): its report.json lists the commits
    #[arg(long, value_name = "DIR")]
    run: PathBuf,
    /// The stage whose commits are evaluated
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=2))]
    stage: u64,
    /// Evaluation settings (JSON) instead of those of the run's own evaluation
    #[arg(long, value_name = "SPEC.json")]
    spec: Option<PathBuf>,
    /// Context views each checkpoint renders from (default: as the run's own evaluation
    /// gave the stage)
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    context_views: Option<u64>,
    /// Folder of the curve and its evaluation (default: DIR/checkpoints/curves)
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    #[command(flatten)]
    backend: BackendArgs,
    #[command(flatten)]
    log: LogArgs,
}

#[derive(Debug, clap::Args)]
struct CompareArgs {
    /// Evaluation reports: `report.json` files or the folders holding them
    #[arg(value_name = "RUN", required = true)]
    runs: Vec<PathBuf>,
    /// Row label of each run, in order (by default the run folder's name)
    #[arg(long = "label", value_name = "NAME")]
    labels: Vec<String>,
    /// Threshold in degrees of the Rac, Tac and AUC columns (3, 5, 10, 15, 20 or 30)
    #[arg(long, value_name = "DEGREES", default_value_t = 20)]
    threshold: u32,
    /// The checkpoint compared, by its place in each report (1: the first scored, xfactor-local's
    /// stage 1; the paper's Table 3 compares stage 1); by default each report's last
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    stage: Option<u64>,
    /// Folder compare.md and compare.png are written to (created if needed)
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

#[derive(Debug, clap::Args)]
struct ImportArgs {
    /// The clu checkpoint directory (holding `checkpoint` and `ckpt-N.flax`)
    #[arg(value_name = "CLU_DIR")]
    dir: PathBuf,
    /// Folder our checkpoint is written to
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Training resolution of the imported model, in pixels
    #[arg(long, value_name = "PIXELS", default_value_t = 256)]
    image_size: usize,
    #[command(flatten)]
    log: LogArgs,
}

#[derive(Debug, clap::Args)]
struct TransferArgs {
    /// Model weights, with their .json configuration beside them
    #[arg(long, value_name = "MODEL.safetensors")]
    checkpoint: PathBuf,
    /// The video whose camera motion is taken: a video file (.mp4, .mov, .mkv, ...), a frame
    /// folder or an object-store URI
    #[arg(long, value_name = "VIDEO|DIR|URI")]
    trajectory: String,
    /// The scene to move through: one image, a video file, or a frame folder or URI
    #[arg(long, value_name = "VIDEO|IMAGE|DIR|URI")]
    scene: String,
    /// Folder the outputs are written to (created if needed)
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Frame of the trajectory the motion is measured from
    #[arg(long, value_name = "N", default_value_t = 0)]
    reference: usize,
    /// Evenly spaced trajectory frames (by default 30 of a video, every frame of a folder)
    #[arg(long, value_name = "N")]
    frames: Option<usize>,
    /// Evenly spaced scene frames (by default the first frame of a video, every frame of a
    /// folder)
    #[arg(long, value_name = "N")]
    scene_frames: Option<usize>,
    #[command(flatten)]
    backend: BackendArgs,
    #[command(flatten)]
    log: LogArgs,
}

/// The built-in pose oracles `--oracle` names.
#[derive(Debug, Clone, Copy, ValueEnum)]
enum Oracle {
    /// Render-and-compare against the generated frames of known pose
    #[value(name = "ground_truth")]
    GroundTruth,
    /// Feature matching and essential matrices at the generated scenes' field of view
    Classical,
}

#[derive(Debug, clap::Args)]
struct EvaluateArgs {
    /// Model weights, with their .json configuration beside them; repeat to score several
    /// checkpoints (stage 1's, then stage 2's) side by side
    #[arg(long, value_name = "MODEL.safetensors", required = true)]
    checkpoint: Vec<PathBuf>,
    /// Context views each checkpoint renders from (1: the stereo model; stage 2: its views less
    /// one); one value for all checkpoints or one per checkpoint
    #[arg(long, value_name = "N", default_value = "1", value_delimiter = ',')]
    context_views: Vec<usize>,
    /// Each checkpoint's name in the report (default: checkpoint1, checkpoint2, ...)
    #[arg(long, value_name = "NAME")]
    label: Vec<String>,
    /// Folder the report and figures are written to (created if needed)
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Evaluation settings (JSON; by default the paper's)
    #[arg(long, value_name = "SPEC.json")]
    spec: Option<PathBuf>,
    /// Pose oracle instead of the spec's
    #[arg(long, value_enum)]
    oracle: Option<Oracle>,
    /// External pose-oracle program instead of the spec's
    #[arg(long, value_name = "PROGRAM", conflicts_with = "oracle")]
    oracle_command: Option<String>,
    /// The ground-truth oracle's candidate views per gap between generated frames (1: the
    /// frames alone; 4: a render between two frames reads its pose to a quarter of a frame)
    #[arg(long, value_name = "N", conflicts_with = "oracle_command", value_parser = clap::value_parser!(u32).range(1..=16))]
    oracle_subdivisions: Option<u32>,
    /// LPIPS weights (safetensors) instead of the spec's
    #[arg(long, value_name = "WEIGHTS")]
    lpips: Option<PathBuf>,
    #[command(flatten)]
    backend: BackendArgs,
    #[command(flatten)]
    log: LogArgs,
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Transfer(args) => transfer(args),
        Command::Evaluate(args) => evaluate(args),
        Command::ImportCheckpoint(args) => import_checkpoint(args),
        Command::Compare(args) => compare(args),
        Command::Curve(args) => curve(args),
    }
}

fn curve(args: CurveArgs) -> anyhow::Result<()> {
    use evaluation::curve;
    args.log.init()?;
    let (mut spec, context_views) = match (&args.spec, args.context_views) {
        (Some(path), Some(views)) => (read_spec(Some(path))?, usize::try_from(views)?),
        (given, views) => {
            let (own, own_views) = curve::run_evaluation_settings(&args.run, args.stage)?;
            let spec = match given {
                Some(path) => read_spec(Some(path))?,
                None => own,
            };
            let views = views.map_or(Ok(own_views), usize::try_from)?;
            (spec, views)
        }
    };
    // The untrained model is the same at every point: measured once, by the run itself.
    spec.compare_untrained = false;
    let checkpoints = curve::committed_checkpoints(&args.run, args.stage, context_views)?;
    let out = args
        .out
        .unwrap_or_else(|| args.run.join("checkpoints").join("curves"));
    let name = format!("transfer-stage{}", args.stage);
    let device = args.backend.backend.device()?;
    let report = run_evaluation(&spec, &checkpoints, &out.join(&name), &device)
        .context("evaluating the run's checkpoints")?;
    let points = curve::points(&report);
    let title = format!(
        "{}: stage {} transfer against steps",
        args.run.display(),
        args.stage
    );
    curve::write_curve(&points, &title, &out, &name)?;
    for point in &points {
        println!(
            "step={} tps_auc30={:.4} tps_auc30_spread={:.4} unrelated_auc30={:.4} unrelated_auc30_spread={:.4} lead_in_spreads={:.2} probe_auc30={:.4} psnr={:.2}",
            point.step,
            point.tps_auc30.0,
            point.tps_auc30.1,
            point.unrelated_auc30.0,
            point.unrelated_auc30.1,
            point.lead_in_spreads(),
            point.probe_auc30.0,
            point.psnr.0
        );
    }
    println!("curve: {}", out.join(format!("{name}.png")).display());
    Ok(())
}

fn compare(args: CompareArgs) -> anyhow::Result<()> {
    evaluation::compare::check_threshold(args.threshold)?;
    let stage = args.stage.map(usize::try_from).transpose()?;
    let runs = evaluation::compare::read_runs(&args.runs, &args.labels, stage)?;
    let table = evaluation::compare::write_comparison(&runs, args.threshold, &args.out)?;
    print!("{table}");
    Ok(())
}

fn transfer(args: TransferArgs) -> anyhow::Result<()> {
    args.log.init()?;
    let request = TransferRequest {
        checkpoint: args.checkpoint,
        trajectory: args.trajectory,
        scene: args.scene,
        reference: args.reference,
        out_dir: args.out,
    };
    let sampling = Sampling {
        frames: args.frames,
        scene_frames: args.scene_frames,
    };
    let device = args.backend.backend.device()?;
    let output = run_transfer_sampled(&request, &sampling, &device)
        .with_context(|| format!("transferring {} into {}", request.trajectory, request.scene))?;
    println!("{}", serde_json::to_string_pretty(&output)?);
    Ok(())
}

fn evaluate(args: EvaluateArgs) -> anyhow::Result<()> {
    args.log.init()?;
    let mut spec = read_spec(args.spec.as_deref())?;
    match (args.oracle, args.oracle_command) {
        (Some(Oracle::GroundTruth), _) => spec.oracle = OracleSpec::default(),
        (Some(Oracle::Classical), _) => spec.oracle = OracleSpec::Classical,
        (None, Some(program)) => {
            spec.oracle = OracleSpec::External {
                program,
                args: Vec::new(),
            }
        }
        (None, None) => {}
    }
    if let Some(subdivisions) = args.oracle_subdivisions {
        match &mut spec.oracle {
            OracleSpec::GroundTruth { subdivisions: slot } => *slot = subdivisions,
            other => anyhow::bail!(
                "--oracle-subdivisions refines the ground-truth oracle; this evaluation's is {other:?}"
            ),
        }
    }
    if let Some(lpips) = args.lpips {
        spec.lpips_weights = Some(lpips);
    }
    let checkpoints = checkpoints_under_test(&args.checkpoint, &args.context_views, &args.label)?;
    let device = args.backend.backend.device()?;
    let report = run_evaluation(&spec, &checkpoints, &args.out, &device).context("evaluating")?;
    print!("{}", evaluation::evaluate::markdown(&report));
    Ok(())
}

/// Pairs each `--checkpoint` with its context views and label; a count that matches neither one
/// nor the checkpoints is refused naming both.
fn checkpoints_under_test(
    weights: &[PathBuf],
    context_views: &[usize],
    labels: &[String],
) -> anyhow::Result<Vec<CheckpointUnderTest>> {
    let fits = |n: usize| n == 1 || n == weights.len();
    if !fits(context_views.len()) {
        bail!(
            "--context-views gives {} values for {} checkpoints: give one for all, or one each",
            context_views.len(),
            weights.len()
        );
    }
    if !labels.is_empty() && labels.len() != weights.len() {
        bail!(
            "--label is given {} times for {} checkpoints: give one each, or none",
            labels.len(),
            weights.len()
        );
    }
    Ok(weights
        .iter()
        .enumerate()
        .map(|(i, path)| CheckpointUnderTest {
            label: labels
                .get(i)
                .cloned()
                .unwrap_or_else(|| format!("checkpoint{}", i + 1)),
            weights: path.clone(),
            step: None,
            context_views: context_views[i.min(context_views.len() - 1)],
        })
        .collect())
}

fn import_checkpoint(args: ImportArgs) -> anyhow::Result<()> {
    args.log.init()?;
    let imported = trainer_core::import::read_clu(&args.dir, args.image_size)
        .with_context(|| format!("importing {}", args.dir.display()))?;
    imported
        .write(&args.out, &trainer_core::backend::Backend::Cpu.device()?)
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "imported={} out={} width={} layers={}+{} step={} updates={} lpips={}",
        imported.source.display(),
        args.out.display(),
        imported.config.width,
        imported.config.pose_layers,
        imported.config.render_layers,
        imported.step,
        imported.updates,
        !imported.lpips.is_empty()
    );
    Ok(())
}
