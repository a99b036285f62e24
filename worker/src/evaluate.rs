//! The evaluation phase on the one worker of its group: download stage 2's final weights,
//! evaluate them, upload the report and commit it.

use anyhow::Context;
use settings::Phase;
use settings::work::EvaluateWork;
use tokio::runtime::Runtime;
use trainer_core::backend::BackendDevices;

use crate::checkpoints;
use crate::commits::{self, CommitRequest};
use crate::context::{Ending, WorkerContext};
use crate::device;
use crate::session::Client;

/// Evaluates the assigned weights (stage 2's final checkpoint) with the job's evaluation spec,
/// uploads the report under the assignment's prefix with its manifest last, and commits it.
pub fn evaluate(
    runtime: &Runtime,
    client: &mut Client,
    context: &WorkerContext<'_>,
    generation: u64,
    work: &EvaluateWork,
) -> anyhow::Result<Ending> {
    let choice = context.options.device.unwrap_or(work.device);
    let resolved = device::resolve(choice, &context.progress.metrics)?;
    context.progress.device.set(&resolved, 1);
    let backend = resolved.backend;
    let scratch = context.scratch();
    let weights_dir = scratch.join("evaluate-weights");
    let report_dir = scratch.join("evaluation");
    for dir in [&weights_dir, &report_dir] {
        checkpoints::clear(dir)?;
    }
    runtime.block_on(checkpoints::download(&work.weights, &weights_dir))?;
    if context.shutdown.is_cancelled() {
        return Ok(Ending::Stopping);
    }
    tracing::info!(weights = %work.weights, "evaluating");
    let report = evaluation::run_evaluation(
        &work.spec,
        &weights_dir.join("model.safetensors"),
        &report_dir,
        &backend.device()?,
    )
    .with_context(|| format!("evaluating {}", work.weights))?;
    tracing::info!(
        seconds = report.seconds,
        "evaluation done; report.json, report.md and figures written"
    );
    let request = CommitRequest {
        dir: &report_dir,
        location: format!("{}/g{generation}", work.report_prefix),
        phase: Phase::Evaluate,
        step: 1,
        generation,
    };
    commits::commit(runtime, client, context.progress, request)?;
    Ok(Ending::Done)
}
