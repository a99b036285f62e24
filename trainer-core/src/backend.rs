//! Choosing the compute device: burn's pure-Rust CPU backend or burn-wgpu.

use std::str::FromStr;

use burn::tensor::{Device, DeviceKind};

/// The compute backends this crate runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BackendChoice {
    /// burn's pure-Rust CPU backend (`flex`), multi-threaded with rayon.
    Cpu,
    /// burn-wgpu on the best adapter present (a GPU, or lavapipe's software Vulkan device).
    Wgpu,
}

impl BackendChoice {
    /// The inference device of this backend; add `.autodiff()` to train on it.
    pub fn device(self) -> Device {
        match self {
            Self::Cpu => Device::flex(),
            Self::Wgpu => Device::wgpu(DeviceKind::DefaultDevice),
        }
    }

    /// Short lowercase name, as accepted by [`FromStr`].
    pub fn name(self) -> &'static str {
        match self {
            Self::Cpu => "cpu",
            Self::Wgpu => "wgpu",
        }
    }
}

/// A backend name that is neither `cpu` nor `wgpu`.
#[derive(Debug, thiserror::Error)]
#[error("unknown backend `{0}`: expected `cpu` or `wgpu`")]
pub struct UnknownBackend(String);

impl FromStr for BackendChoice {
    type Err = UnknownBackend;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        match name.to_ascii_lowercase().as_str() {
            "cpu" | "flex" => Ok(Self::Cpu),
            "wgpu" | "gpu" => Ok(Self::Wgpu),
            _ => Err(UnknownBackend(name.to_string())),
        }
    }
}
