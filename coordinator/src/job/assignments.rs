//! The typed assignments a group's members receive: what to train or evaluate, from where, and
//! with which settings.

use proto::convert::{device_to_wire, devices_to_wire, phase_to_wire};
use proto::v1::{
    Assignment, CheckpointToEvaluate, EvaluateAssignment, Finish, TrainAssignment, assignment::Work,
};
use settings::Phase;
use settings::train::StageObjective;

use super::records::Durable;
use crate::plan::Plan;

/// The checkpoint prefix of `phase` under the job's checkpoint URI.
fn prefix(plan: &Plan, leaf: &str) -> String {
    format!(
        "{}/{leaf}",
        plan.config.checkpoint.uri.0.trim_end_matches('/')
    )
}

/// Rank `rank` of a training group of `peers` in `phase` (stage 1 or 2).
pub fn train(
    plan: &Plan,
    durable: &Durable,
    generation: u64,
    phase: Phase,
    rank: usize,
    peers: &[String],
) -> Assignment {
    let stage = plan.stage(phase);
    let config = &plan.config;
    let resume_from = durable
        .last_commit
        .as_ref()
        .filter(|c| c.phase == phase)
        .map(|c| c.location.clone())
        .unwrap_or_default();
    let init_weights_from = match phase {
        _ if !resume_from.is_empty() => String::new(),
        Phase::Stage2 => durable.stage1_final.clone().unwrap_or_default(),
        _ => config
            .init_weights
            .as_ref()
            .map(|uri| uri.0.clone())
            .unwrap_or_default(),
    };
    Assignment {
        generation,
        work: Some(Work::Train(TrainAssignment {
            rank: rank as u32,
            world_size: peers.len() as u32,
            peers: peers.to_vec(),
            phase: phase_to_wire(phase) as i32,
            total_steps: stage.steps,
            resume_from,
            init_weights_from,
            checkpoint_prefix: prefix(plan, phase.name()),
            checkpoint_every: config.checkpoint.every.0,
            checksum_every: config.workers.checksum_every.0,
            lpips_weights: stage.lpips_weights.clone().unwrap_or_default(),
            device: device_to_wire(config.workers.device) as i32,
            model: Some((&plan.model).into()),
            train: Some((&stage.train).into()),
            data: Some((&stage.data).into()),
            // Drawn by the service, which holds the randomness this pure state does not.
            ring_secret: String::new(),
            left_ring_secret: String::new(),
            devices: Some(devices_to_wire(&config.workers.devices)),
        })),
    }
}

/// Context views a stage's model renders from: stage 1's one, stage 2's views less the target.
fn context_views(plan: &Plan, phase: Phase) -> u64 {
    match &plan.stage(phase).train.objective {
        StageObjective::Stage1(_) => 1,
        StageObjective::Stage2(stage2) => stage2.views.saturating_sub(1).max(1) as u64,
    }
}

/// The evaluation of both stages' final weights (each scored as its stage trained), for the
/// one worker of the group; `None` when the job has no evaluation section.
pub fn evaluate(plan: &Plan, durable: &Durable, generation: u64) -> Option<Assignment> {
    let spec = plan.config.evaluate.as_ref()?;
    let finals = [
        (Phase::Stage1, &durable.stage1_final),
        (Phase::Stage2, &durable.stage2_final),
    ];
    let checkpoints = finals
        .into_iter()
        .filter_map(|(phase, location)| {
            Some(CheckpointToEvaluate {
                stage: phase_to_wire(phase) as i32,
                weights: location.clone()?,
                step: plan.stage(phase).steps,
                context_views: context_views(plan, phase),
            })
        })
        .collect();
    Some(Assignment {
        generation,
        work: Some(Work::Evaluate(EvaluateAssignment {
            checkpoints,
            report_prefix: prefix(plan, "evaluation"),
            device: device_to_wire(plan.config.workers.device) as i32,
            model: Some((&plan.model).into()),
            spec: Some(spec.into()),
        })),
    })
}

/// The end of the job.
pub fn finish(generation: u64) -> Assignment {
    Assignment {
        generation,
        work: Some(Work::Finish(Finish {})),
    }
}
