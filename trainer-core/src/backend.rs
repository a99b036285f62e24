//! Choosing the compute device: burn's pure-Rust CPU backend or burn-wgpu.

use std::str::FromStr;

use burn::tensor::{Device, DeviceKind};

/// The compute backends this crate runs on; also the values of `--backend`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BackendChoice {
    /// burn's pure-Rust CPU backend (flex), multi-threaded with rayon
    #[value(alias = "flex")]
    Cpu,
    /// burn-wgpu on the best adapter present (a GPU, or lavapipe's software Vulkan device)
    #[value(alias = "gpu")]
    Wgpu,
}

/// The `--backend` flag of the binaries that run the model in one process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::Args)]
pub struct BackendArgs {
    /// Compute backend
    #[arg(long, value_enum, ignore_case = true, default_value_t = BackendChoice::Cpu)]
    pub backend: BackendChoice,
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

    /// The names and aliases `--backend` accepts, in any case.
    fn from_str(name: &str) -> Result<Self, Self::Err> {
        <Self as clap::ValueEnum>::from_str(name, true)
            .map_err(|_| UnknownBackend(name.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_aliases_parse_in_any_case_and_others_are_refused() {
        for (name, backend) in [
            ("cpu", BackendChoice::Cpu),
            ("Flex", BackendChoice::Cpu),
            ("wgpu", BackendChoice::Wgpu),
            ("GPU", BackendChoice::Wgpu),
        ] {
            assert_eq!(name.parse::<BackendChoice>().unwrap(), backend, "{name}");
            assert_eq!(backend.name().parse::<BackendChoice>().unwrap(), backend);
        }
        let refused = "tpu".parse::<BackendChoice>().unwrap_err();
        assert!(refused.to_string().contains("`tpu`"), "{refused}");
    }
}
