//! `xfactor`: the user-facing tool of the evaluation crate.
//!
//! `xfactor transfer` renders a scene along the camera motion of another video;
//! `xfactor evaluate` runs the paper's evaluation of a checkpoint on generated scenes;
//! `xfactor import-checkpoint` turns the authors' released clu checkpoint into ours.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use evaluation::evaluate::read_spec;
use evaluation::oracle::OracleSpec;
use evaluation::{TransferRequest, run_evaluation, run_transfer};
use trainer_core::backend::BackendChoice;
use trainer_core::cli::{Flags, init_logging};

const USAGE: &str = "usage:
  xfactor transfer --checkpoint MODEL.safetensors --trajectory DIR|URI --scene IMAGE|DIR|URI --out DIR
                   [--reference N] [--backend cpu|wgpu] [--log-format human|json]
  xfactor evaluate --checkpoint MODEL.safetensors --out DIR [--spec SPEC.json]
                   [--oracle ground_truth|classical] [--oracle-command PROGRAM] [--lpips WEIGHTS]
                   [--backend cpu|wgpu] [--log-format human|json]
  xfactor import-checkpoint CLU_DIR --out DIR [--image-size 256] [--log-format human|json]";

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some((command, rest)) = args.split_first() else {
        bail!("{USAGE}");
    };
    match command.as_str() {
        "transfer" => transfer(rest),
        "evaluate" => evaluate(rest),
        "import-checkpoint" => import_checkpoint(rest),
        "--help" | "-h" | "help" => {
            println!("{USAGE}");
            Ok(())
        }
        other => bail!("unknown command `{other}`\n{USAGE}"),
    }
}

/// Parses a subcommand's `--name value` flags and starts logging as `--log-format` asks.
fn parse_flags(args: &[String], values: &[&str]) -> anyhow::Result<Flags> {
    let flags = Flags::parse(args, &[], values).map_err(|e| anyhow::anyhow!("{e}\n{USAGE}"))?;
    init_logging(flags.get("log-format")).map_err(anyhow::Error::msg)?;
    Ok(flags)
}

/// A flag the subcommand cannot do without, with the usage in the error.
fn required<'a>(flags: &'a Flags, name: &str) -> anyhow::Result<&'a str> {
    flags
        .require(name)
        .map_err(|e| anyhow::anyhow!("{e}\n{USAGE}"))
}

fn backend(flags: &Flags) -> anyhow::Result<BackendChoice> {
    Ok(flags.get("backend").unwrap_or("cpu").parse()?)
}

fn transfer(args: &[String]) -> anyhow::Result<()> {
    let flags = parse_flags(
        args,
        &[
            "checkpoint",
            "trajectory",
            "scene",
            "out",
            "reference",
            "backend",
            "log-format",
        ],
    )?;
    let required = |name: &str| required(&flags, name);
    let request = TransferRequest {
        checkpoint: PathBuf::from(required("checkpoint")?),
        trajectory: required("trajectory")?.to_string(),
        scene: required("scene")?.to_string(),
        reference: flags
            .get("reference")
            .map_or(Ok(0), str::parse)
            .context("--reference must be a frame number")?,
        out_dir: PathBuf::from(required("out")?),
    };
    let device = backend(&flags)?.device();
    let output = run_transfer(&request, &device)
        .with_context(|| format!("transferring {} into {}", request.trajectory, request.scene))?;
    println!("{}", serde_json::to_string_pretty(&output)?);
    Ok(())
}

fn evaluate(args: &[String]) -> anyhow::Result<()> {
    let flags = parse_flags(
        args,
        &[
            "checkpoint",
            "out",
            "spec",
            "oracle",
            "oracle-command",
            "lpips",
            "backend",
            "log-format",
        ],
    )?;
    let required = |name: &str| required(&flags, name);
    let checkpoint = PathBuf::from(required("checkpoint")?);
    let out = PathBuf::from(required("out")?);
    let mut spec = read_spec(flags.get("spec").map(Path::new))?;
    match (flags.get("oracle"), flags.get("oracle-command")) {
        (Some(_), Some(_)) => bail!("give --oracle or --oracle-command, not both"),
        (Some("ground_truth"), None) => spec.oracle = OracleSpec::GroundTruth,
        (Some("classical"), None) => spec.oracle = OracleSpec::Classical,
        (Some(other), None) => bail!("--oracle `{other}`: expected ground_truth or classical"),
        (None, Some(program)) => {
            spec.oracle = OracleSpec::External {
                program: program.to_string(),
                args: Vec::new(),
            }
        }
        (None, None) => {}
    }
    if let Some(lpips) = flags.get("lpips") {
        spec.lpips_weights = Some(PathBuf::from(lpips));
    }
    let device = backend(&flags)?.device();
    let report = run_evaluation(&spec, &checkpoint, &out, &device)
        .with_context(|| format!("evaluating {}", checkpoint.display()))?;
    print!("{}", evaluation::evaluate::markdown(&report));
    Ok(())
}

fn import_checkpoint(args: &[String]) -> anyhow::Result<()> {
    let Some((dir, rest)) = args.split_first().filter(|(dir, _)| !dir.starts_with("--")) else {
        bail!("import-checkpoint needs the clu checkpoint directory first\n{USAGE}");
    };
    let flags = parse_flags(rest, &["out", "image-size", "log-format"])?;
    let out = PathBuf::from(required(&flags, "out")?);
    let image_size = flags
        .get("image-size")
        .map_or(Ok(256), str::parse)
        .context("--image-size must be a number of pixels")?;
    let imported = trainer_core::import::read_clu(Path::new(dir), image_size)
        .with_context(|| format!("importing {dir}"))?;
    imported
        .write(&out, &BackendChoice::Cpu.device())
        .with_context(|| format!("writing {}", out.display()))?;
    println!(
        "imported={} out={} width={} layers={}+{} step={} updates={} lpips={}",
        imported.source.display(),
        out.display(),
        imported.config.width,
        imported.config.pose_layers,
        imported.config.render_layers,
        imported.step,
        imported.updates,
        !imported.lpips.is_empty()
    );
    Ok(())
}
