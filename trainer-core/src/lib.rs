//! `trainer-core`: the XFactor model, its weights, LPIPS, both objectives, the optimiser and the
//! single-process trainer, in burn. Settings come from `settings`, samples from `data`.
//!
//! This crate knows nothing about networking: workers and the evaluation drive it through
//! plain function calls.

pub mod allocator;
pub mod augment;
pub mod backend;
pub mod checkpoint;
pub mod flat;
pub mod flax;
pub mod import;
pub mod lpips;
pub mod model;
pub mod objective;
pub mod optim;
pub mod parity;
pub mod sharded;
pub mod standin;
pub mod trainer;

pub use burn::tensor::Device;
pub use model::XFactor;
pub use settings::XFactorConfig;
