//! `xfactor`: the user-facing tool of the evaluation crate.
//!
//! `xfactor transfer` renders a scene along the camera motion of another video;
//! `xfactor evaluate` runs the paper's evaluation of a checkpoint on generated scenes.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use evaluation::evaluate::read_spec;
use evaluation::{Sampling, TransferRequest, run_evaluation, run_transfer_sampled};
use settings::evaluation::OracleSpec;
use telemetry::cli::{Flags, init_logging};
use trainer_core::backend::BackendChoice;

const USAGE: &str = "usage:
  xfactor transfer --checkpoint MODEL.safetensors --trajectory VIDEO|DIR|URI --scene VIDEO|IMAGE|DIR|URI
                   --out DIR [--frames N] [--scene-frames N] [--reference N] [--backend cpu|wgpu]
                   [--log-format human|json]
      videos (.mp4, .mov, .mkv, ... through ffmpeg): --frames evenly spaced trajectory frames
      (default 30), --scene-frames scene frames (default 1); writes frames/, strip.png,
      transfer.gif and transfer.mp4 under --out. Example:
      xfactor transfer --checkpoint ckpt/model.safetensors --trajectory walk.mp4 \
          --scene room.mp4 --frames 30 --out transfer-out
  xfactor evaluate --checkpoint MODEL.safetensors --out DIR [--spec SPEC.json]
                   [--oracle ground_truth|classical] [--oracle-command PROGRAM] [--lpips WEIGHTS]
                   [--backend cpu|wgpu] [--log-format human|json]";

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some((command, rest)) = args.split_first() else {
        bail!("{USAGE}");
    };
    match command.as_str() {
        "transfer" => transfer(rest),
        "evaluate" => evaluate(rest),
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
            "frames",
            "scene-frames",
            "backend",
            "log-format",
        ],
    )?;
    let required = |name: &str| required(&flags, name);
    let count = |name: &str| {
        flags
            .get(name)
            .map(str::parse::<usize>)
            .transpose()
            .with_context(|| format!("--{name} must be a whole number"))
    };
    let sampling = Sampling {
        frames: count("frames")?,
        scene_frames: count("scene-frames")?,
    };
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
    let output = run_transfer_sampled(&request, &sampling, &device)
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
