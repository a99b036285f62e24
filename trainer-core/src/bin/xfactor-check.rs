//! `xfactor-check FIXTURE.safetensors [--backend cpu|wgpu]`: checks the model against a fixture
//! of the authors' layout and exits non-zero when any output or gradient is out of tolerance.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Parser;
use trainer_core::backend::{BackendArgs, BackendDevices};
use trainer_core::parity::{GRADIENT_TOLERANCE, OUTPUT_TOLERANCE, check_fixture};

/// Checks the model against a fixture of the authors' layout; exits 1 when any output or
/// gradient is out of tolerance, 2 on an error.
#[derive(Debug, Parser)]
#[command(
    name = "xfactor-check",
    version,
    after_help = "Example: the tiny fixture the project ships, on burn-wgpu:
  xfactor-check ../shared/fixtures/xfactor-tiny.safetensors --backend wgpu"
)]
struct Cli {
    /// The fixture; FIXTURE.json beside it holds its configuration
    #[arg(value_name = "FIXTURE.safetensors")]
    fixture: PathBuf,
    #[command(flatten)]
    backend: BackendArgs,
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(1),
        Err(error) => {
            eprintln!("xfactor-check: {error:#}");
            ExitCode::from(2)
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<bool> {
    let Cli { fixture, backend } = cli;
    let backend = backend.backend;
    let report = check_fixture(&fixture, &backend.device()?)
        .with_context(|| format!("checking {}", fixture.display()))?;

    println!(
        "fixture={} backend={} image={} patch={} width={} heads={} layers={}+{} pose_dim={} global_tokens={}",
        fixture.display(),
        backend.name(),
        report.config.image_size,
        report.config.patch_size,
        report.config.width,
        report.config.num_heads,
        report.config.pose_layers,
        report.config.render_layers,
        report.config.pose_dim,
        report.config.global_tokens,
    );
    for (name, error) in &report.output_errors {
        let verdict = if *error <= OUTPUT_TOLERANCE {
            "ok"
        } else {
            "FAIL"
        };
        println!("output {name:<14} max_abs_err={error:.3e} {verdict}");
    }
    let failing: Vec<_> = report
        .gradient_errors
        .iter()
        .filter(|(_, e)| **e > GRADIENT_TOLERANCE)
        .collect();
    for (name, error) in &failing {
        println!("gradient {name} rel_err={error:.3e} FAIL");
    }
    let (worst_output, output_error) = report.worst_output();
    let (worst_gradient, gradient_error) = report.worst_gradient();
    println!(
        "summary outputs_max_abs_err={output_error:.3e} (worst {worst_output}) grads_max_rel_err={gradient_error:.3e} (worst {worst_gradient}) gradients_checked={} reference_pose_max_abs={:e} tolerance_output={OUTPUT_TOLERANCE:e} tolerance_grad={GRADIENT_TOLERANCE:e} result={}",
        report.gradient_errors.len(),
        report.reference_pose_max_abs,
        if report.passed() { "pass" } else { "FAIL" },
    );
    Ok(report.passed())
}
