//! The evaluation phase on the one worker of its group: download every stage's final weights,
//! evaluate them, upload the report and commit it.

use anyhow::Context;
use evaluation::evaluate::CheckpointUnderTest;
use settings::Phase;
use settings::work::EvaluateWork;
use tokio::runtime::Runtime;
use trainer_core::backend::BackendDevices;

use crate::checkpoints;
use crate::commits::{self, CommitRequest};
use crate::context::{Ending, WorkerContext};
use crate::device;
use crate::session::Client;

/// Evaluates the assigned weights (each stage's final checkpoint, with the context views it
/// trained with) with the job's evaluation spec, uploads the report under the assignment's
/// prefix with its manifest last, and commits it.
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
    let mut under_test = Vec::with_capacity(work.checkpoints.len());
    for checkpoint in &work.checkpoints {
        let dir = weights_dir.join(checkpoint.stage.name());
        runtime.block_on(checkpoints::download(&checkpoint.weights, &dir))?;
        under_test.push(CheckpointUnderTest {
            label: checkpoint.stage.name().to_string(),
            weights: dir.join("model.safetensors"),
            step: Some(checkpoint.step),
            context_views: checkpoint.context_views,
        });
    }
    if context.shutdown.is_cancelled() {
        return Ok(Ending::Stopping);
    }
    let locations: Vec<&str> = work
        .checkpoints
        .iter()
        .map(|c| c.weights.as_str())
        .collect();
    tracing::info!(weights = ?locations, "evaluating");
    let report =
        evaluation::run_evaluation(&work.spec, &under_test, &report_dir, &backend.device()?)
            .with_context(|| format!("evaluating {}", locations.join(", ")))?;
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
