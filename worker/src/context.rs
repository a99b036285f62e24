//! What every generation of a worker shares and how a generation ends: the types the
//! generation layers (`training`, `evaluate`) take and return, owned here so that those layers
//! and the daemon that drives them import this leaf rather than each other.

use crate::collective::{Link, Mailbox};
use crate::options::WorkerOptions;
use crate::progress::Progress;
use crate::shutdown::Shutdown;

/// How a generation ended for this worker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    /// The stage (or this generation's part of it) is done.
    Done,
    /// SIGTERM arrived; the last step finished cleanly and nothing is half-committed.
    Stopping,
    /// The coordinator suspends the job: this worker's part is committed (rank 0) or needs
    /// nothing more (the others); it exits without leaving, so the generation stays whole
    /// until the commit is in.
    Suspended,
}

/// The coordinator ended a generation this worker was still in (it re-forms the group after
/// another member's failure, a loss or a store outage): nobody's fault of this worker's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the coordinator ended generation {generation}")]
pub struct GenerationEnded {
    /// The generation.
    pub generation: u64,
}

/// What every generation of this worker shares.
#[derive(Clone, Copy)]
pub struct WorkerContext<'a> {
    /// How the worker was started.
    pub options: &'a WorkerOptions,
    /// How to reach peers.
    pub link: &'a Link,
    /// Chunks from the left neighbour.
    pub mailbox: &'a Mailbox,
    /// Shared with the heartbeat task.
    pub progress: &'a Progress,
    /// Cancelled on SIGTERM.
    pub shutdown: &'a Shutdown,
}

impl WorkerContext<'_> {
    /// This worker's scratch directory (per registration, so two workers on one host never
    /// share one).
    pub fn scratch(&self) -> std::path::PathBuf {
        self.options
            .scratch
            .join(format!("worker-{}", self.progress.worker_id()))
    }
}
