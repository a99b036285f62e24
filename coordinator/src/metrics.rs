//! The coordinator's Prometheus series: job progress, what the workers report each step, and
//! membership events. Scraped from `/metrics` (see the `telemetry` crate).

use proto::v1::StepReport;

use crate::job::JobStatus;
use settings::Phase;
pub use telemetry::training::{GENERATION, GRAD_NORM, LEARNING_RATE, LOSS, STAGE, STEP};
use telemetry::{Metric, Registry};

/// Steps of the current stage.
pub const STAGE_STEPS: Metric = Metric::gauge("xfactor_stage_steps", "Steps of the current stage.");
/// Samples per second summed over the group.
pub const SAMPLES_PER_SECOND: Metric = Metric::gauge(
    "xfactor_samples_per_second",
    "Training samples per second, summed over the workers' last steps.",
);
/// Per-worker throughput.
pub const WORKER_SAMPLES_PER_SECOND: Metric = Metric::gauge(
    "xfactor_worker_samples_per_second",
    "Samples per second of one worker's last step.",
);
/// Per-worker all-reduce time.
pub const WORKER_ALLREDUCE_SECONDS: Metric = Metric::gauge(
    "xfactor_worker_allreduce_seconds",
    "Seconds one worker's last step spent in the all-reduce.",
);
/// Per-worker skipped frames.
pub const WORKER_SKIPPED_FRAMES: Metric = Metric::counter(
    "xfactor_worker_skipped_frames_total",
    "Undecodable frames one worker skipped.",
);
/// Live workers.
pub const WORKERS: Metric = Metric::gauge(
    "xfactor_workers",
    "Registered workers whose heartbeats are on time.",
);
/// Generations abandoned.
pub const RESTARTS: Metric = Metric::counter(
    "xfactor_restarts_total",
    "Generations abandoned because a worker was lost, left or failed.",
);
/// Heartbeats received.
pub const HEARTBEATS: Metric = Metric::counter(
    "xfactor_heartbeats_total",
    "Heartbeats received from workers.",
);
/// Commits accepted.
pub const COMMITS: Metric = Metric::counter("xfactor_commits_total", "Checkpoints committed.");
/// Checksum disagreements.
pub const CHECKSUM_MISMATCHES: Metric = Metric::counter(
    "xfactor_checksum_mismatches_total",
    "Steps whose ranks reported different parameter checksums.",
);

/// Workers blamed and sent to sit out.
pub const EXCLUSIONS: Metric = Metric::counter(
    "xfactor_exclusions_total",
    "Workers blamed for a failed generation and sent to sit out a back-off.",
);
/// Store outage.
pub const STORE_FAILING_SECONDS: Metric = Metric::gauge(
    "xfactor_store_failing_seconds",
    "Seconds the object store has been failing generations (0 while it works).",
);
/// When the newest commit landed.
pub const LAST_COMMIT_TIMESTAMP: Metric = Metric::gauge(
    "xfactor_last_commit_timestamp_seconds",
    "Unix time of the newest commit this coordinator accepted.",
);

/// Publishes one step report. Job-wide loss and learning rate come from rank 0's reports,
/// which the caller marks with `from_rank0`.
pub fn record_step(registry: &Registry, report: &StepReport, from_rank0: bool) {
    let worker = report.worker_id.to_string();
    let labels = [("worker", worker.as_str())];
    registry.set(&WORKER_SAMPLES_PER_SECOND, &labels, report.samples_per_s);
    registry.set(&WORKER_ALLREDUCE_SECONDS, &labels, report.allreduce_s);
    registry.raise_to(
        &WORKER_SKIPPED_FRAMES,
        &labels,
        report.skipped_frames as f64,
    );
    if from_rank0 && let Some(loss) = &report.loss {
        registry.set(&LOSS, &[], f64::from(loss.total));
        registry.set(&LEARNING_RATE, &[], loss.learning_rate);
        registry.set(&GRAD_NORM, &[], loss.grad_norm);
    }
}

/// Publishes the job's state as the `status` command sees it, plus the group's throughput
/// (`samples_per_second` summed over its workers' last reports).
pub fn record_status(
    registry: &Registry,
    status: &JobStatus,
    phase: Phase,
    samples_per_second: f64,
    mismatches: usize,
    exclusions: usize,
) {
    registry.set(&STAGE, &[], f64::from(phase.number()));
    registry.set(&STEP, &[], status.step as f64);
    registry.set(&STAGE_STEPS, &[], status.total_steps as f64);
    registry.set(&WORKERS, &[], status.workers as f64);
    registry.set(&GENERATION, &[], status.generation as f64);
    registry.raise_to(&RESTARTS, &[], status.restarts as f64);
    registry.raise_to(&CHECKSUM_MISMATCHES, &[], mismatches as f64);
    registry.set(&SAMPLES_PER_SECOND, &[], samples_per_second);
    registry.raise_to(&EXCLUSIONS, &[], exclusions as f64);
    let failing = status.store_failing.map_or(0.0, |d| d.as_secs_f64());
    registry.set(&STORE_FAILING_SECONDS, &[], failing);
}

/// Drops the per-worker series of workers that are no longer members (lost, left, or from
/// before a re-registration), so `/metrics` shows the live group only.
pub fn forget_departed(registry: &Registry, live: &[String]) {
    for metric in [
        &WORKER_SAMPLES_PER_SECOND,
        &WORKER_ALLREDUCE_SECONDS,
        &WORKER_SKIPPED_FRAMES,
    ] {
        registry.retain(metric, "worker", |id| live.iter().any(|l| l == id));
    }
}
