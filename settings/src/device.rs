//! Which compute device a worker trains on.

use serde::{Deserialize, Serialize};

/// The device a job (YAML `workers.device`) or a worker (`--device`) asks for: a backend, or
/// `auto` for the best one this build and host have.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DeviceChoice {
    /// The best device present: CUDA, then libtorch on CUDA, then Vulkan, then a wgpu GPU
    /// adapter, then the CPU (only the backends this build has).
    #[default]
    Auto,
    /// burn's CPU backend.
    Cpu,
    /// burn-wgpu (a GPU, or lavapipe's software Vulkan device).
    Wgpu,
    /// burn-wgpu pinned to Vulkan with SPIR-V kernels (cargo feature `vulkan`).
    Vulkan,
    /// burn's CUDA backend (cargo feature `cuda`).
    Cuda,
    /// burn-tch on an installed PyTorch's libtorch, on CUDA where it has it (cargo feature
    /// `libtorch`).
    Libtorch,
}

impl DeviceChoice {
    /// Every choice, in the order `--help` lists them.
    pub const ALL: [Self; 6] = [
        Self::Auto,
        Self::Cpu,
        Self::Wgpu,
        Self::Vulkan,
        Self::Cuda,
        Self::Libtorch,
    ];

    /// The YAML and command-line spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Cpu => "cpu",
            Self::Wgpu => "wgpu",
            Self::Vulkan => "vulkan",
            Self::Cuda => "cuda",
            Self::Libtorch => "libtorch",
        }
    }

    /// The backend named, `None` for `auto`, which the host decides.
    pub fn backend(self) -> Option<Backend> {
        match self {
            Self::Auto => None,
            Self::Cpu => Some(Backend::Cpu),
            Self::Wgpu => Some(Backend::Wgpu),
            Self::Vulkan => Some(Backend::Vulkan),
            Self::Cuda => Some(Backend::Cuda),
            Self::Libtorch => Some(Backend::Libtorch),
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
#[error("unknown device `{0}`: expected auto, cpu, wgpu, vulkan, cuda or libtorch")]
pub struct UnknownDevice(pub String);

impl std::str::FromStr for DeviceChoice {
    type Err = UnknownDevice;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|choice| choice.name().eq_ignore_ascii_case(name.trim()))
            .ok_or_else(|| UnknownDevice(name.to_string()))
    }
}

/// A compute backend a model runs on: what `auto` resolves to, what a worker reports it
/// trains on, and the `--backend` of the one-process binaries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Backend {
    /// burn's pure-Rust CPU backend (flex), multi-threaded with rayon.
    Cpu,
    /// burn-wgpu on the best adapter present; WGSL kernels in the default build.
    Wgpu,
    /// burn-wgpu pinned to Vulkan, SPIR-V kernels.
    Vulkan,
    /// burn's CUDA backend.
    Cuda,
    /// burn-tch, the libtorch of an installed PyTorch.
    Libtorch,
}

impl Backend {
    /// Every backend, in the order `--help` lists them.
    pub const ALL: [Self; 5] = [
        Self::Cpu,
        Self::Wgpu,
        Self::Vulkan,
        Self::Cuda,
        Self::Libtorch,
    ];

    /// Short lowercase name, as [`DeviceChoice`] spells it.
    pub fn name(self) -> &'static str {
        self.choice().name()
    }

    /// The device choice that names this backend.
    pub fn choice(self) -> DeviceChoice {
        match self {
            Self::Cpu => DeviceChoice::Cpu,
            Self::Wgpu => DeviceChoice::Wgpu,
            Self::Vulkan => DeviceChoice::Vulkan,
            Self::Cuda => DeviceChoice::Cuda,
            Self::Libtorch => DeviceChoice::Libtorch,
        }
    }

    /// The cargo feature (of trainer-core, worker and evaluation) a build needs for this
    /// backend; `None` for the two every build has.
    pub fn cargo_feature(self) -> Option<&'static str> {
        match self {
            Self::Cpu | Self::Wgpu => None,
            Self::Vulkan => Some("vulkan"),
            Self::Cuda => Some("cuda"),
            Self::Libtorch => Some("libtorch"),
        }
    }
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A backend name that is none of [`Backend::ALL`] (nor an alias).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown backend `{0}`: expected cpu (flex), wgpu (gpu), vulkan, cuda or libtorch")]
pub struct UnknownBackend(pub String);

impl std::str::FromStr for Backend {
    type Err = UnknownBackend;

    /// The names, and the aliases `flex` (cpu) and `gpu` (wgpu), in any case.
    fn from_str(name: &str) -> Result<Self, Self::Err> {
        let unknown = || UnknownBackend(name.to_string());
        match name.trim().to_ascii_lowercase().as_str() {
            "flex" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Wgpu),
            other => other
                .parse::<DeviceChoice>()
                .ok()
                .and_then(DeviceChoice::backend)
                .ok_or_else(unknown),
        }
    }
}

/// The device a worker resolved its choice to and trains on, as it reports it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct DeviceInUse {
    /// The backend.
    pub backend: Backend,
    /// The adapter's or card's name (`NVIDIA H100 80GB HBM3 (Vulkan)`; `cpu`).
    pub name: String,
    /// Model replicas on it (several devices, or several replicas of the CPU).
    pub replicas: u32,
}

/// Which of a host's devices one worker drives, one model replica on each (`--devices`):
/// every device of its backend, the first `N`, or the devices with these indices. The CPU is
/// one device; asking it for `N` runs `N` replicas on it, which computes what `N` devices
/// would (the tests use it).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum DeviceSet {
    /// Every device the backend has on this host.
    #[default]
    All,
    /// The first this many.
    Count(usize),
    /// These, by index among the backend's devices.
    Ids(Vec<usize>),
}

/// YAML's forms of a device set: `all`, a count, or a list of indices.
#[derive(Deserialize)]
#[serde(untagged)]
enum DeviceSetForm {
    Name(String),
    Count(usize),
    Ids(Vec<usize>),
}

impl<'de> Deserialize<'de> for DeviceSet {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let set = match DeviceSetForm::deserialize(deserializer)? {
            DeviceSetForm::Name(name) => name.parse(),
            DeviceSetForm::Count(0) => Err(BadDeviceSet("0".into())),
            DeviceSetForm::Count(count) => Ok(Self::Count(count)),
            DeviceSetForm::Ids(ids) => Self::from_ids(ids),
        };
        set.map_err(serde::de::Error::custom)
    }
}

impl Serialize for DeviceSet {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            Self::All => serializer.serialize_str("all"),
            Self::Count(count) => serializer.serialize_u64(*count as u64),
            Self::Ids(ids) => ids.serialize(serializer),
        }
    }
}

/// A `--devices` value that is not `all`, a count or a list of indices.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("`{0}` is not a device set: expected `all`, a count above 0 (`2`) or indices (`0,2`)")]
pub struct BadDeviceSet(pub String);

impl std::str::FromStr for DeviceSet {
    type Err = BadDeviceSet;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = || BadDeviceSet(text.to_string());
        let text = text.trim();
        if text == "all" {
            return Ok(Self::All);
        }
        if !text.contains(',') {
            return match text.parse::<usize>() {
                Ok(0) | Err(_) => Err(bad()),
                Ok(count) => Ok(Self::Count(count)),
            };
        }
        let ids = text
            .split(',')
            .map(|id| id.trim().parse::<usize>().map_err(|_| bad()))
            .collect::<Result<Vec<_>, _>>()?;
        Self::from_ids(ids).map_err(|_| bad())
    }
}

impl DeviceSet {
    /// A set of indices, each named once.
    fn from_ids(ids: Vec<usize>) -> Result<Self, BadDeviceSet> {
        let mut unique = ids.clone();
        unique.sort_unstable();
        unique.dedup();
        if ids.is_empty() || unique.len() != ids.len() {
            let named: Vec<String> = ids.iter().map(ToString::to_string).collect();
            return Err(BadDeviceSet(format!("[{}]", named.join(", "))));
        }
        Ok(Self::Ids(ids))
    }
}

impl std::fmt::Display for DeviceSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::All => f.write_str("all"),
            Self::Count(count) => write!(f, "{count}"),
            Self::Ids(ids) => {
                let ids: Vec<String> = ids.iter().map(ToString::to_string).collect();
                f.write_str(&ids.join(","))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_sets_parse_and_print_back() {
        for (text, set) in [
            ("all", DeviceSet::All),
            ("2", DeviceSet::Count(2)),
            ("0,2", DeviceSet::Ids(vec![0, 2])),
            ("3,1", DeviceSet::Ids(vec![3, 1])),
        ] {
            assert_eq!(text.parse::<DeviceSet>(), Ok(set.clone()));
            assert_eq!(set.to_string(), text);
        }
        for (yaml, set) in [
            ("all", DeviceSet::All),
            ("2", DeviceSet::Count(2)),
            ("[2]", DeviceSet::Ids(vec![2])),
            ("[0, 2]", DeviceSet::Ids(vec![0, 2])),
        ] {
            let json = yaml.replace("all", "\"all\"");
            let parsed: DeviceSet = serde_json::from_str(&json).unwrap();
            assert_eq!(parsed, set);
            assert_eq!(
                serde_json::to_string(&set).unwrap().replace(' ', ""),
                json.replace(' ', "")
            );
        }
        for bad in ["0", "[]", "[1, 1]", "\"some\""] {
            assert!(serde_json::from_str::<DeviceSet>(bad).is_err(), "{bad}");
        }
        for bad in ["0", "-1", "two", "0,0", "1,,2", ""] {
            assert_eq!(
                bad.parse::<DeviceSet>(),
                Err(BadDeviceSet(bad.to_string())),
                "{bad}"
            );
        }
    }

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for choice in DeviceChoice::ALL {
            assert_eq!(choice.name().parse::<DeviceChoice>(), Ok(choice));
            assert_eq!(
                choice.name().to_uppercase().parse::<DeviceChoice>(),
                Ok(choice)
            );
        }
        for backend in Backend::ALL {
            assert_eq!(backend.name().parse::<Backend>(), Ok(backend));
            assert_eq!(backend.choice().backend(), Some(backend));
        }
        assert_eq!("Flex".parse::<Backend>(), Ok(Backend::Cpu));
        assert_eq!("GPU".parse::<Backend>(), Ok(Backend::Wgpu));
        assert_eq!(
            "auto".parse::<Backend>(),
            Err(UnknownBackend("auto".into()))
        );
        assert_eq!(
            "tpu".parse::<Backend>().unwrap_err().to_string(),
            "unknown backend `tpu`: expected cpu (flex), wgpu (gpu), vulkan, cuda or libtorch"
        );
        assert_eq!(
            "tpu".parse::<DeviceChoice>(),
            Err(UnknownDevice("tpu".into()))
        );
    }
}
