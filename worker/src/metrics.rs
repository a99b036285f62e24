//! The worker's Prometheus series: its own view of each step (loss, learning rate,
//! throughput, all-reduce time and bandwidth, loader queue) and of its link to the coordinator
//! (heartbeats), and histograms of step, all-reduce, data-wait and checkpoint-upload times.
//! Scraped from `/metrics` (see the `telemetry` crate).

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use data::{BatchSource, SampleError, Samples};
use telemetry::histogram::SECONDS_BUCKETS;
pub use telemetry::training::{GENERATION, GRAD_NORM, LEARNING_RATE, LOSS, STAGE, STEP};
use telemetry::{Metric, Registry};
use trainer_core::backend::MemoryFigures;

/// The device this worker trains on (value 1; the labels say which).
pub const DEVICE_INFO: Metric = Metric::gauge(
    "xfactor_device_info",
    "The backend and adapter this worker trains on (labels backend, name).",
);
/// Device memory, by where the figure comes from.
pub const DEVICE_MEMORY: Metric = Metric::gauge(
    "xfactor_device_memory_bytes",
    "Device memory after the last step, by source: cubecl's pools (pool_reserved, pool_in_use), \
     this process's resident host memory (host_resident, host_peak_resident: the device's on the \
     CPU backend and lavapipe) and the NVIDIA driver's count (driver_device_used for GPU 0, \
     driver_process_used for this process).",
);

/// Exports every figure `figures` has, each under its source's label.
pub fn record_device_memory(registry: &Registry, figures: &MemoryFigures) {
    for (source, bytes) in figures.named() {
        registry.set(&DEVICE_MEMORY, &[("source", source)], bytes as f64);
    }
}

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
/// Whether the worker is waiting out a failure that was not its own, by cause.
pub const WAITING: Metric = Metric::gauge(
    "xfactor_worker_waiting",
    "1 while the worker waits after a generation failed by someone else's fault (label cause: \
     peer, store, corrupt_checkpoint), before asking for work again; it never gives up on those.",
);
/// Distribution of step wall times (the gauge above keeps only the last).
pub const STEP_DURATION: Metric = Metric::histogram(
    "xfactor_step_duration_seconds",
    "Wall time of each training step.",
    SECONDS_BUCKETS,
);
/// Distribution of all-reduce times.
pub const ALLREDUCE_DURATION: Metric = Metric::histogram(
    "xfactor_allreduce_duration_seconds",
    "Seconds each step spent in the gradient all-reduce.",
    SECONDS_BUCKETS,
);
/// Time the trainer waited on the data loader.
pub const DATA_WAIT: Metric = Metric::histogram(
    "xfactor_data_wait_seconds",
    "Seconds each step waited for micro-batches from the data loader.",
    SECONDS_BUCKETS,
);
/// Checkpoint upload time.
pub const CHECKPOINT_UPLOAD: Metric = Metric::histogram(
    "xfactor_checkpoint_upload_seconds",
    "Seconds each checkpoint took to upload to the object store, COMMIT.json included.",
    SECONDS_BUCKETS,
);

/// A [`BatchSource`] that adds the time its caller spends waiting in `samples` to a running
/// total: wrapped around the loader, it measures how long the trainer waits for data (zero
/// when the prefetch queue keeps ahead).
pub struct Timed<'a, S> {
    inner: &'a S,
    waited_ns: AtomicU64,
}

impl<'a, S: BatchSource> Timed<'a, S> {
    /// Wraps `inner` with the total at zero.
    pub fn new(inner: &'a S) -> Self {
        Self {
            inner,
            waited_ns: AtomicU64::new(0),
        }
    }

    /// Seconds spent waiting since the last call, and the total reset to zero.
    pub fn take_seconds(&self) -> f64 {
        self.waited_ns.swap(0, Ordering::Relaxed) as f64 * 1e-9
    }
}

impl<S: BatchSource> BatchSource for Timed<'_, S> {
    fn samples(&self, step: u64, first_sample: u64, count: usize) -> Result<Samples, SampleError> {
        let started = Instant::now();
        let samples = self.inner.samples(step, first_sample, count);
        let waited = u64::try_from(started.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.waited_ns.fetch_add(waited, Ordering::Relaxed);
        samples
    }
}
