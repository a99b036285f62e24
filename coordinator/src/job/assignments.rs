//! The typed assignments a group's members receive, as `settings::work` domain values: what to
//! train or evaluate, from where, and with which settings. The service converts them to the
//! wire once, after drawing the ring secrets this pure state does not hold.

use settings::Phase;
use settings::train::StageObjective;
use settings::work::{Assignment, CheckpointToEvaluate, EvaluateWork, TrainStart, TrainWork, Work};

use super::records::Durable;
use crate::plan::Plan;

/// The checkpoint prefix of `phase` under the job's checkpoint URI.
fn prefix(plan: &Plan, leaf: &str) -> String {
    format!(
        "{}/{leaf}",
        plan.config.checkpoint.uri.0.trim_end_matches('/')
    )
}

/// Where rank's trainer starts in `phase`: the phase's newest commit, else (stage 2) stage 1's
/// final weights or (stage 1) the job's initial weights, else a fresh initialisation.
fn start(plan: &Plan, durable: &Durable, phase: Phase) -> TrainStart {
    let resume = durable.last_commit.as_ref().filter(|c| c.phase == phase);
    if let Some(commit) = resume {
        return TrainStart::Resume(commit.location.clone());
    }
    let weights = match phase {
        Phase::Stage2 => durable.stage1_final.clone(),
        _ => plan.config.init_weights.as_ref().map(|uri| uri.0.clone()),
    };
    weights.map_or(TrainStart::Fresh, TrainStart::InitWeights)
}

/// Rank `rank` of a training group of `peers` in `phase` (stage 1 or 2); its ring secrets are
/// left to the service.
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
    Assignment {
        generation,
        work: Work::Train(Box::new(TrainWork {
            stage: phase,
            rank,
            peers: peers.to_vec(),
            total_steps: stage.steps,
            start: start(plan, durable, phase),
            checkpoint_prefix: prefix(plan, phase.name()),
            checkpoint_every: config.checkpoint.every.0,
            checksum_every: config.workers.checksum_every,
            lpips_weights: stage.lpips_weights.clone(),
            device: config.workers.device,
            model: plan.model.clone(),
            train: stage.train.clone(),
            data: stage.data.clone(),
            ring: None,
            devices: config.workers.devices.clone(),
            wire: config.workers.allreduce_wire,
            lanes: config.workers.allreduce_lanes,
        })),
    }
}

/// Context views a stage's model renders from: stage 1's one, stage 2's views less the target.
fn context_views(plan: &Plan, phase: Phase) -> usize {
    match &plan.stage(phase).train.objective {
        StageObjective::Stage1(_) => 1,
        StageObjective::Stage2(stage2) => stage2.views.saturating_sub(1).max(1),
    }
}

/// The evaluation of the final weights of every stage the job trains (each scored as its
/// stage trained), for the one worker of the group; `None` when the job has no evaluation
/// section.
pub fn evaluate(plan: &Plan, durable: &Durable, generation: u64) -> Option<Assignment> {
    let spec = plan.config.evaluate.as_ref()?;
    let finals = [
        (Phase::Stage1, &durable.stage1_final),
        (Phase::Stage2, &durable.stage2_final),
    ];
    let checkpoints = finals
        .into_iter()
        .filter(|(phase, _)| plan.trains(*phase))
        .filter_map(|(phase, location)| {
            Some(CheckpointToEvaluate {
                stage: phase,
                weights: location.clone()?,
                step: plan.stage(phase).steps,
                context_views: context_views(plan, phase),
            })
        })
        .collect();
    Some(Assignment {
        generation,
        work: Work::Evaluate(Box::new(EvaluateWork {
            checkpoints,
            report_prefix: prefix(plan, "evaluation"),
            device: plan.config.workers.device,
            model: plan.model.clone(),
            spec: spec.clone(),
        })),
    })
}

/// The end of the job.
pub fn finish(generation: u64) -> Assignment {
    Assignment {
        generation,
        work: Work::Finish,
    }
}
