//! `settings`: what xfactor-dist processes agree on, as plain serde types.
//!
//! The coordinator reads these from the cluster YAML, the proto carries them to workers, and
//! trainer-core, data and evaluation compute with them. Nothing here does I/O or links a tensor
//! library, so the control plane can depend on it alone.

pub mod cache;
pub mod commit;
pub mod data;
mod device;
pub mod evaluation;
pub mod model;
pub mod objective;
pub mod optim;
pub mod phase;
pub mod train;
pub mod work;

pub use device::{
    Backend, BadDeviceSet, DeviceChoice, DeviceInUse, DeviceSet, UnknownBackend, UnknownDevice,
};
pub use model::XFactorConfig;
pub use phase::Phase;
