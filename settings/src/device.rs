//! Which compute device a worker trains on.

use serde::{Deserialize, Serialize};

/// The device a job (YAML `workers.device`) or a worker (`--device`) asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DeviceChoice {
    /// A GPU when the host has one, the CPU otherwise.
    #[default]
    Auto,
    /// burn's CPU backend.
    Cpu,
    /// burn-wgpu (a GPU, or lavapipe's software Vulkan device).
    Wgpu,
}

impl DeviceChoice {
    /// Every choice, in the order `--help` lists them.
    pub const ALL: [Self; 3] = [Self::Auto, Self::Cpu, Self::Wgpu];

    /// The YAML and command-line spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Cpu => "cpu",
            Self::Wgpu => "wgpu",
        }
    }
}

impl std::fmt::Display for DeviceChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A device name that is none of [`DeviceChoice::ALL`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown device `{0}`: expected auto, cpu or wgpu")]
pub struct UnknownDevice(pub String);

impl std::str::FromStr for DeviceChoice {
    type Err = UnknownDevice;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|choice| choice.name() == name)
            .ok_or_else(|| UnknownDevice(name.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for choice in DeviceChoice::ALL {
            assert_eq!(choice.name().parse::<DeviceChoice>(), Ok(choice));
        }
        assert_eq!(
            "tpu".parse::<DeviceChoice>(),
            Err(UnknownDevice("tpu".into()))
        );
    }
}
