//! The worker daemon: registers with the coordinator, trains its rank of each assigned group
//! with `trainer-core`, all-reduces gradients with its peers over gRPC, and writes the
//! checkpoints it is asked to.
//!
//! It knows ranks, flat gradient vectors and files, never attention heads: the model is built
//! and stepped through `trainer-core`'s public API. The layers, from the process down (each
//! imports only layers below it; `ARCHITECTURE.md` has the picture):
//!
//! - `daemon`: the loop over assignments; `failure`: whose fault a failed generation was;
//!   `streaks`: whether to go on after it (only own faults can end a worker).
//! - `training`, `evaluate`: one generation's work; `generation` prepares a training one.
//! - `datapath`: one optimizer step over the worker's replicas, from their backward passes
//!   through the ring to the update and the checksum; `accounting`: its books.
//! - `commits`: when rank 0 commits, and the commit in flight; `checkpoints`: the transfers.
//! - `session`: the coordinator's RPCs and heartbeats; `health`: the gRPC health service.
//! - leaves: `context`, `options`, `progress`, `metrics`, `device`, `shutdown`, `slurm`,
//!   [`collective`] (the ring).

pub mod bench;
pub mod collective;
pub mod slurm;

mod accounting;
mod checkpoints;
mod commits;
mod context;
mod daemon;
mod datapath;
mod device;
mod evaluate;
mod failure;
mod generation;
mod health;
mod metrics;
mod options;
mod progress;
mod session;
mod shutdown;
mod streaks;
mod training;

pub use daemon::run;
pub use options::{WorkerOptions, WorkerTls};
