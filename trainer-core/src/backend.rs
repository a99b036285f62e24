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

    /// The devices of `set` on this backend, one model replica each. The CPU is one device:
    /// `all` is one replica, a count `N` is `N` replicas on it, and only index 0 exists. On
    /// wgpu, `all` and a count take the default adapter and then the discrete GPUs by index;
    /// an index past the host's adapters fails when the device first runs.
    pub fn devices(self, set: &settings::DeviceSet) -> Result<Vec<Device>, NoSuchDevice> {
        use settings::DeviceSet;
        match (self, set) {
            (_, DeviceSet::All) => Ok(vec![self.device()]),
            (Self::Cpu, DeviceSet::Count(count)) => Ok(vec![Device::flex(); *count]),
            (Self::Wgpu, DeviceSet::Count(count)) => Ok((0..*count)
                .map(|index| Device::wgpu(wgpu_kind(index)))
                .collect()),
            (Self::Cpu, DeviceSet::Ids(ids)) => match ids.iter().find(|&&id| id != 0) {
                Some(&id) => Err(NoSuchDevice { backend: self, id }),
                None => Ok(vec![Device::flex(); ids.len()]),
            },
            (Self::Wgpu, DeviceSet::Ids(ids)) => Ok(ids
                .iter()
                .map(|&index| Device::wgpu(wgpu_kind(index)))
                .collect()),
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

/// What kind of device an adapter is, as the driver reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterKind {
    /// A GPU card of its own.
    DiscreteGpu,
    /// A GPU sharing the CPU's memory.
    IntegratedGpu,
    /// A virtualised GPU.
    VirtualGpu,
    /// A software renderer on the CPU (lavapipe, SwiftShader).
    Software,
    /// The driver does not say.
    Other,
}

/// A GPU adapter present on this host, as burn-wgpu would see it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Adapter {
    /// The driver's name for it (`NVIDIA H100 80GB HBM3`, `llvmpipe (LLVM 15.0.6, 256 bits)`).
    pub name: String,
    /// What kind of device it is.
    pub kind: AdapterKind,
    /// The graphics API it was found through (`Vulkan`, `Metal`, `Dx12`).
    pub api: String,
}

impl Adapter {
    /// Whether it is real GPU hardware, not a software renderer.
    pub fn is_gpu(&self) -> bool {
        matches!(
            self.kind,
            AdapterKind::DiscreteGpu | AdapterKind::IntegratedGpu | AdapterKind::VirtualGpu
        )
    }
}

/// The adapters burn-wgpu can use on this host, found by asking each graphics API's driver
/// (no guessing from device nodes); empty when no driver answers.
pub fn wgpu_adapters() -> Vec<Adapter> {
    let backends = wgpu::Backends::PRIMARY;
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
        backends,
        ..wgpu::InstanceDescriptor::new_without_display_handle()
    });
    futures::executor::block_on(instance.enumerate_adapters(backends))
        .iter()
        .map(|adapter| {
            let info = adapter.get_info();
            Adapter {
                name: info.name,
                kind: match info.device_type {
                    wgpu::DeviceType::DiscreteGpu => AdapterKind::DiscreteGpu,
                    wgpu::DeviceType::IntegratedGpu => AdapterKind::IntegratedGpu,
                    wgpu::DeviceType::VirtualGpu => AdapterKind::VirtualGpu,
                    wgpu::DeviceType::Cpu => AdapterKind::Software,
                    wgpu::DeviceType::Other => AdapterKind::Other,
                },
                api: format!("{:?}", info.backend),
            }
        })
        .collect()
}

/// wgpu's device for replica `index`: the default adapter first, then discrete GPUs.
fn wgpu_kind(index: usize) -> DeviceKind {
    if index == 0 {
        DeviceKind::DefaultDevice
    } else {
        DeviceKind::DiscreteGpu(index)
    }
}

/// A device index this backend does not have.
#[derive(Debug, thiserror::Error)]
#[error("{} has no device {id}: the CPU is device 0", backend.name())]
pub struct NoSuchDevice {
    /// The backend asked.
    pub backend: BackendChoice,
    /// The index it lacks.
    pub id: usize,
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
