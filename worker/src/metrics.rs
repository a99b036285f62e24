//! The worker's Prometheus series: its own view of each step (loss, learning rate,
//! throughput, all-reduce time and bandwidth, loader queue) and of its link to the coordinator
//! (heartbeats). Scraped from `/metrics` (see the `telemetry` crate).

use telemetry::Metric;
pub use telemetry::training::{GENERATION, GRAD_NORM, LEARNING_RATE, LOSS, STAGE, STEP};

/// Rank in the group.
pub const RANK: Metric = Metric::gauge("xfactor_rank", "This worker's rank in its group.");
/// Samples per second of this worker.
pub const SAMPLES_PER_SECOND: Metric = Metric::gauge(
    "xfactor_samples_per_second",
    "Samples per second this worker trained in its last step.",
);
/// Step wall time.
pub const STEP_SECONDS: Metric =
    Metric::gauge("xfactor_step_seconds", "Wall time of the last step.");
/// All-reduce time.
pub const ALLREDUCE_SECONDS: Metric = Metric::gauge(
    "xfactor_allreduce_seconds",
    "Seconds the last step spent in the gradient all-reduce.",
);
/// All-reduce algorithmic bandwidth.
pub const ALLREDUCE_BANDWIDTH: Metric = Metric::gauge(
    "xfactor_allreduce_bytes_per_second",
    "Algorithmic bandwidth of the last all-reduce (buffer bytes / seconds).",
);
/// Data-loader queue depth.
pub const LOADER_QUEUE: Metric = Metric::gauge(
    "xfactor_loader_queue_depth",
    "Micro-batches the data loader has ready.",
);
/// Skipped frames.
pub const SKIPPED_FRAMES: Metric = Metric::counter(
    "xfactor_skipped_frames_total",
    "Undecodable frames skipped by the data loader.",
);
/// Heartbeats sent.
pub const HEARTBEATS: Metric = Metric::counter(
    "xfactor_heartbeats_total",
    "Heartbeats sent to the coordinator.",
);
/// Heartbeats that failed.
pub const HEARTBEAT_FAILURES: Metric = Metric::counter(
    "xfactor_heartbeat_failures_total",
    "Heartbeats the coordinator did not answer.",
);
/// Generations this worker joined after its first.
pub const RESTARTS: Metric = Metric::counter(
    "xfactor_restarts_total",
    "Generations this worker left early (lost peer, cancelled, failed).",
);
