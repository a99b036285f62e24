//! `trainer-core`: the XFactor model, its weights and (later) its objectives and trainer.
//!
//! This crate knows nothing about networking: workers and the coordinator drive it through
//! plain function calls.

pub mod allocator;
pub mod augment;
pub mod backend;
pub mod checkpoint;
pub mod cli;
pub mod config;
pub mod data;
pub mod flat;
pub mod flax;
pub mod import;
pub mod lpips;
pub mod model;
pub mod objective;
pub mod optim;
pub mod parity;
pub mod rng;
pub mod scenes;
pub mod sharded;
pub mod synthetic;
pub mod trainer;

pub use config::XFactorConfig;
pub use model::XFactor;
