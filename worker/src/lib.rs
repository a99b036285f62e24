//! The worker daemon: registers with the coordinator, trains its rank of each assigned group
//! with `trainer-core`, all-reduces gradients with its peers over gRPC, and writes the
//! checkpoints it is asked to.
//!
//! It knows ranks, flat gradient vectors and files, never attention heads: the model is built
//! and stepped through `trainer-core`'s public API.

pub mod bench;
pub mod checkpoints;
pub mod collective;
pub mod daemon;
pub mod device;
pub mod evaluate;
pub mod health;
pub mod metrics;
pub mod session;
pub mod shutdown;
pub mod slurm;
pub mod training;
