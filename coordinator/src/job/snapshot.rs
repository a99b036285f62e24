//! The job at a glance, as one value: what the status page draws and `/api/status` serves as
//! JSON. Built from the job's state under its lock (`job/queries.rs`), then rendered without
//! it, so a slow browser never holds the job up.

use serde::{Deserialize, Serialize};

/// The newest commits the page lists.
pub const COMMITS_SHOWN: usize = 20;

/// Points of the loss curve the page draws, at most.
pub const LOSS_POINTS: usize = 600;

/// Everything the status page shows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusSnapshot {
    /// The job's name.
    pub job: String,
    /// Its phase (`stage1`, `stage2`, `evaluate`, `finished`).
    pub phase: String,
    /// "running", "waiting for workers", "finished", or "failed: ...".
    pub state: String,
    /// The newest generation.
    pub generation: u64,
    /// The step the phase is at, and the phase's steps.
    pub step: u64,
    /// Steps of the phase (0 outside training).
    pub stage_steps: u64,
    /// Steps done over both stages, and their total.
    pub job_steps_done: u64,
    /// Steps of both stages.
    pub job_steps_total: u64,
    /// Seconds left at the recent steps' pace, while training.
    pub eta_s: Option<f64>,
    /// Rank 0's newest loss.
    pub last_loss: f32,
    /// Samples per second of the running group.
    pub samples_per_s: f64,
    /// Seconds the object store has been failing generations, while it is.
    pub store_failing_s: Option<f64>,
    /// Every worker that registered, lost ones included.
    pub workers: Vec<WorkerView>,
    /// Generations as they started and ended, oldest first.
    pub timeline: Vec<TimelineEntry>,
    /// Faults that are not a generation's end: exclusions, checksum disagreements, commits
    /// found corrupt.
    pub faults: Vec<String>,
    /// The newest commits, newest first.
    pub commits: Vec<CommitView>,
    /// The loss by step over both stages (stage 2's steps after stage 1's), thinned.
    pub loss: Vec<(u64, f32)>,
    /// Where the evaluation report was committed, once it was.
    pub evaluation: Option<String>,
}

/// One worker on the page.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorkerView {
    /// Its id.
    pub id: u64,
    /// Its name.
    pub name: String,
    /// The device it trains on, once a generation resolved it.
    pub device: String,
    /// Samples per second of its last step.
    pub samples_per_s: f64,
    /// Seconds since its last heartbeat.
    pub heartbeat_age_s: f64,
    /// What it is doing: `computing step 120`, `waiting for work`, `lost`.
    pub state: String,
    /// Generations it was blamed for.
    pub faults: u32,
}

/// One generation's start or end.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TimelineEntry {
    /// The generation.
    pub generation: u64,
    /// What happened to it.
    pub event: String,
}

/// One commit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommitView {
    /// The phase that wrote it.
    pub phase: String,
    /// Steps done when written.
    pub step: u64,
    /// Where it is.
    pub location: String,
}

/// `points` thinned to at most `most`, evenly, keeping the last.
pub fn thinned<T: Copy>(points: &[T], most: usize) -> Vec<T> {
    if points.len() <= most || most < 2 {
        return points.to_vec();
    }
    let stride = points.len().div_ceil(most - 1);
    let mut kept: Vec<T> = points.iter().step_by(stride).copied().collect();
    if !(points.len() - 1).is_multiple_of(stride)
        && let Some(&last) = points.last()
    {
        kept.push(last);
    }
    kept
}

/// Seconds left for `steps_left` steps at the mean of `recent_step_s`.
pub fn eta_seconds(steps_left: u64, recent_step_s: &[f64]) -> Option<f64> {
    let times: Vec<f64> = recent_step_s
        .iter()
        .copied()
        .filter(|s| s.is_finite() && *s > 0.0)
        .collect();
    (!times.is_empty()).then(|| steps_left as f64 * times.iter().sum::<f64>() / times.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thinning_keeps_at_most_the_bound_and_both_ends() {
        let points: Vec<u64> = (0..1000).collect();
        let kept = thinned(&points, 100);
        assert!(kept.len() <= 100, "{}", kept.len());
        assert_eq!((kept[0], *kept.last().unwrap()), (0, 999));
        assert_eq!(thinned(&points[..10], 100), points[..10].to_vec());
    }

    #[test]
    fn the_eta_is_the_steps_left_at_the_recent_pace() {
        assert_eq!(eta_seconds(100, &[0.5, 1.5]), Some(100.0));
        assert_eq!(eta_seconds(100, &[]), None);
        assert_eq!(eta_seconds(100, &[f64::NAN, 0.0]), None);
    }
}
