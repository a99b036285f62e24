//! `data`: everything about training data that needs no tensor library. The object-store root
//! (`store`), indexing of the four dataset layouts into manifests (`index`, `cache`), frame
//! decoding (`decode`), the window sampler (`sampler`), sharding across ranks (`shard`,
//! `spec`), the loader thread (`prefetch`), and the generated scenes used by tests, demos and
//! the evaluation (`scenes`, `synthetic`). Every random draw comes from `rng`, keyed by
//! `(seed, step, sample)`.
//!
//! The coordinator links this crate to index datasets and to read and write its checkpoint
//! store; workers link it (through trainer-core) to read their samples.

mod batch;
pub mod cache;
pub mod decode;
mod frame;
pub mod frame_order;
pub mod index;
mod manifest;
pub mod prefetch;
pub mod resize;
pub mod rng;
mod sampler;
pub mod scenes;
mod shard;
pub mod source;
pub mod spec;
pub mod split;
pub mod store;
pub mod synthetic;

pub use batch::{BatchSource, FrameError, SampleError, Samples};
pub use frame::Image;
pub use manifest::{Manifest, Sequence, Split};
pub use sampler::{WindowDraw, WindowSampler};
pub use settings::data::{DatasetKind, DatasetSampling, SamplerConfig};
pub use shard::shard_sequences;
