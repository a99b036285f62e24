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
        }
        assert_eq!(
            "tpu".parse::<DeviceChoice>(),
            Err(UnknownDevice("tpu".into()))
        );
    }
}
