//! What the training thread, the heartbeat task and the health endpoints share about this
//! worker: its registration, the generation and step it is in, what it is doing, whether the
//! coordinator still knows it, and its Prometheus series. A leaf: every other layer reads or
//! writes it, it reads none of them.

use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

use proto::v1::Activity;
use telemetry::Registry;
use tokio_util::sync::CancellationToken;

use crate::device::DeviceReport;

/// What the training thread and the heartbeat task share.
pub struct Progress {
    /// This worker's id (0 before registration).
    pub worker: AtomicU64,
    /// The secret its registration was given; every request naming the id carries it.
    pub session: RwLock<String>,
    /// The generation being worked in.
    pub generation: AtomicU64,
    /// Steps done in it.
    pub step: AtomicU64,
    /// What the worker is doing within its step (a `proto::v1::Activity` value), so the
    /// coordinator can tell stuck from slow.
    pub activity: AtomicI32,
    /// The current generation's token, a child of the shutdown token: cancelled when the
    /// coordinator abandons the generation or the worker shuts down; the step in flight stops.
    generation_token: RwLock<CancellationToken>,
    /// Whether the coordinator's last heartbeat reply still knew this worker: false once it
    /// was removed (silent, or stuck in its step while peers waited) until it registers again.
    pub known: AtomicBool,
    /// The worker's Prometheus series.
    pub metrics: Arc<Registry>,
    /// The device the current generation trains on, for the heartbeats.
    pub device: DeviceReport,
}

impl Progress {
    /// Nothing registered yet.
    pub fn new() -> Self {
        Self {
            worker: AtomicU64::new(0),
            session: RwLock::new(String::new()),
            generation: AtomicU64::new(0),
            step: AtomicU64::new(0),
            activity: AtomicI32::new(Activity::Idle as i32),
            generation_token: RwLock::new(CancellationToken::new()),
            known: AtomicBool::new(false),
            metrics: Arc::new(Registry::new()),
            device: DeviceReport::default(),
        }
    }

    /// `/healthz`: healthy while the coordinator knows this worker (or it has not registered
    /// yet); removed, it is not, so a liveness probe restarts a worker stuck in its step.
    pub fn health(progress: &Arc<Self>) -> telemetry::http::HealthCheck {
        let progress = Arc::clone(progress);
        Arc::new(move || {
            if progress.known.load(Ordering::SeqCst) || progress.worker_id() == 0 {
                Ok(())
            } else {
                Err(telemetry::http::Unhealthy(format!(
                    "the coordinator removed worker {} (no heartbeat, or no progress in step {} while its peers waited); it registers again once its step returns",
                    progress.worker_id(),
                    progress.step.load(Ordering::SeqCst)
                )))
            }
        })
    }

    /// Starts a generation with `token` (a child of the shutdown token).
    pub fn begin_generation(&self, token: CancellationToken) {
        if let Ok(mut current) = self.generation_token.write() {
            *current = token;
        }
    }

    /// The current generation's token: the ring and the step loop stop when it is cancelled.
    pub fn generation_token(&self) -> CancellationToken {
        self.generation_token.read().map_or_else(
            |poisoned| poisoned.into_inner().clone(),
            |token| token.clone(),
        )
    }

    /// This worker's id.
    pub fn worker_id(&self) -> u64 {
        self.worker.load(Ordering::SeqCst)
    }

    /// This registration's secret.
    pub fn session(&self) -> String {
        self.session
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// Records what the worker does next; the next heartbeat carries it.
    pub fn doing(&self, activity: Activity) {
        self.activity.store(activity as i32, Ordering::SeqCst);
    }
}

impl Default for Progress {
    fn default() -> Self {
        Self::new()
    }
}
