//! The coordinator: reads the cluster YAML, indexes and shards the data, admits workers, and
//! runs stage 1 then stage 2 across them, re-forming the group when a worker is lost.
//!
//! It knows jobs, workers, steps and checkpoints, never tensors: model and data settings pass
//! through to the workers as the configuration types of `trainer-core`.

pub mod config;
pub mod health;
pub mod job;
pub mod local;
pub mod metrics;
pub mod plan;
pub mod progress;
pub mod service;
pub mod status;
