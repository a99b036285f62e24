//! The aggregate dataset: manifests of sequences, the window sampler with its curriculum and
//! mixture, and sharding of sequences across ranks.

pub mod cache;
pub mod decode;
pub mod frame_order;
pub mod index;
pub mod manifest;
pub mod prefetch;
pub mod resize;
pub mod sampler;
pub mod shard;
pub mod source;
pub mod spec;
pub mod split;
pub mod store;

pub use manifest::{DatasetKind, Manifest, Sequence, Split};
pub use sampler::{DatasetSampling, SamplerConfig, WindowDraw};
pub use shard::shard_sequences;
