//! The evaluation phase on the one worker of its group: download stage 2's final weights,
//! evaluate them, upload the report and commit it.

use anyhow::Context;
use proto::convert::{ConvertError, device_from_wire};
use proto::v1::EvaluateAssignment;
use settings::Phase;
use settings::evaluation::EvaluationSpec;
use tokio::runtime::Runtime;

use crate::checkpoints::{self, CommitRequest};
use crate::daemon::{Ending, Group};
use crate::device;
use crate::session::Client;

/// Evaluates the assigned weights (stage 2's final checkpoint) with the job's evaluation spec,
/// uploads the report under the assignment's prefix with its manifest last, and commits it.
pub fn evaluate(
    runtime: &Runtime,
    client: &mut Client,
    group: &Group<'_>,
    generation: u64,
    assignment: &EvaluateAssignment,
) -> anyhow::Result<Ending> {
    let Group {
        options,
        progress,
        shutdown,
        ..
    } = *group;
    let spec = EvaluationSpec::try_from(
        assignment
            .spec
            .as_ref()
            .ok_or(ConvertError::Missing("evaluate.spec"))?,
    )?;
    let backend = device::backend(match options.device {
        Some(device) => device,
        None => device_from_wire(assignment.device, "evaluate.device")?,
    });
    let scratch = options
        .scratch
        .join(format!("worker-{}", progress.worker_id()));
    let weights_dir = scratch.join("evaluate-weights");
    let report_dir = scratch.join("evaluation");
    for dir in [&weights_dir, &report_dir] {
        let _ = std::fs::remove_dir_all(dir);
    }
    runtime.block_on(checkpoints::download(&assignment.weights, &weights_dir))?;
    if shutdown.is_cancelled() {
        return Ok(Ending::Stopping);
    }
    tracing::info!(weights = %assignment.weights, "evaluating");
    let report = evaluation::run_evaluation(
        &spec,
        &weights_dir.join("model.safetensors"),
        &report_dir,
        &backend.device(),
    )
    .with_context(|| format!("evaluating {}", assignment.weights))?;
    tracing::info!(
        seconds = report.seconds,
        "evaluation done; report.json, report.md and figures written"
    );
    let request = CommitRequest {
        dir: &report_dir,
        location: format!("{}/g{generation}", assignment.report_prefix),
        phase: Phase::Evaluate,
        step: 1,
        generation,
    };
    checkpoints::commit(runtime, client, progress, request)?;
    Ok(Ending::Done)
}
