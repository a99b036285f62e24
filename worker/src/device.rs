//! Which burn backend a worker trains on, from the job's or its own device choice, checked
//! against this build's backends and the devices the host's drivers report. `auto` takes the
//! best present (CUDA, libtorch on CUDA, Vulkan on a GPU, wgpu on a GPU, then the CPU); a
//! backend asked for and absent is an error naming what is missing (the cargo feature, the
//! driver, the adapter) before the worker joins.

use std::sync::RwLock;

use settings::{Backend, DeviceChoice, DeviceInUse};
use telemetry::Registry;
use trainer_core::backend::{Adapter, BackendDevices, CudaUnavailable, HostDevices};

use crate::metrics::DEVICE_INFO;

/// A device choice resolved on this host.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResolvedDevice {
    /// The backend to build the trainer on.
    pub backend: Backend,
    /// The adapter's or card's name (`cpu` for burn's CPU backend).
    pub name: String,
}

/// A device asked for that this build or host does not have.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DeviceMissing {
    /// The backend's cargo feature was off when this worker was built.
    #[error(
        "--device {backend}: this worker was built without the `{feature}` cargo feature; \
         rebuild it with `cargo build --release -p worker --features {feature}` (docs/gpus.md) \
         or choose --device auto, cpu or wgpu"
    )]
    NotInThisBuild {
        /// The backend asked.
        backend: Backend,
        /// The feature it needs.
        feature: &'static str,
    },
    /// No wgpu adapter at all.
    #[error(
        "--device wgpu: no Vulkan, Metal or DX12 adapter answered on this host; install a driver \
         (a GPU's, with its Vulkan ICD, or mesa-vulkan-drivers for lavapipe on the CPU) or use --device cpu"
    )]
    NoAdapter,
    /// No adapter on the Vulkan API.
    #[error(
        "--device vulkan: no Vulkan adapter answered on this host (found: {found}); install the \
         GPU's Vulkan ICD (NVIDIA: the driver's libnvidia-gl and /usr/share/vulkan/icd.d/nvidia_icd.json) \
         or use --device wgpu"
    )]
    NoVulkanAdapter {
        /// The adapters found on other APIs, or `none`.
        found: String,
    },
    /// burn's CUDA backend cannot run on this host (no driver, no NVRTC, no device).
    #[error("--device cuda: {0}")]
    NoCudaDevice(CudaUnavailable),
}

/// Resolves `choice` against `host` (the drivers' answers) for a build that has the backends
/// `built` says.
pub fn resolve_with(
    choice: DeviceChoice,
    host: &HostDevices,
    built: impl Fn(Backend) -> bool,
) -> Result<ResolvedDevice, DeviceMissing> {
    let Some(backend) = choice.backend() else {
        return Ok(best(host, built));
    };
    if !built(backend) {
        return Err(DeviceMissing::NotInThisBuild {
            backend,
            feature: backend.cargo_feature().unwrap_or("default"),
        });
    }
    let gpu = host.adapters.iter().find(|adapter| adapter.is_gpu());
    match backend {
        Backend::Cpu => Ok(cpu()),
        Backend::Wgpu => gpu
            .or(host.adapters.first())
            .map(|adapter| on_adapter(Backend::Wgpu, adapter))
            .ok_or(DeviceMissing::NoAdapter),
        Backend::Vulkan => vulkan_adapter(host)
            .map(|adapter| on_adapter(Backend::Vulkan, adapter))
            .ok_or_else(|| DeviceMissing::NoVulkanAdapter {
                found: adapter_list(&host.adapters),
            }),
        Backend::Cuda => match &host.cuda {
            Ok(count) => Ok(cuda(*count)),
            Err(why) => Err(DeviceMissing::NoCudaDevice(why.clone())),
        },
        Backend::Libtorch => Ok(libtorch(host.libtorch_cuda)),
    }
}

/// What `auto` takes: the fastest backend this build has with a real GPU under it, else the
/// CPU. Software adapters (lavapipe) never win over burn's CPU backend.
fn best(host: &HostDevices, built: impl Fn(Backend) -> bool) -> ResolvedDevice {
    let vulkan_gpu = vulkan_adapter(host).filter(|adapter| adapter.is_gpu());
    let gpu = host.adapters.iter().find(|adapter| adapter.is_gpu());
    if let (true, Ok(count)) = (built(Backend::Cuda), &host.cuda) {
        cuda(*count)
    } else if built(Backend::Libtorch) && host.libtorch_cuda > 0 {
        libtorch(host.libtorch_cuda)
    } else if let Some(adapter) = vulkan_gpu.filter(|_| built(Backend::Vulkan)) {
        on_adapter(Backend::Vulkan, adapter)
    } else if let Some(adapter) = gpu {
        on_adapter(Backend::Wgpu, adapter)
    } else {
        cpu()
    }
}

fn vulkan_adapter(host: &HostDevices) -> Option<&Adapter> {
    let on_vulkan = || {
        host.adapters
            .iter()
            .filter(|adapter| adapter.api == "Vulkan")
    };
    on_vulkan()
        .find(|adapter| adapter.is_gpu())
        .or_else(|| on_vulkan().next())
}

fn adapter_list(adapters: &[Adapter]) -> String {
    if adapters.is_empty() {
        return "none".into();
    }
    let names: Vec<String> = adapters
        .iter()
        .map(|adapter| format!("{} on {}", adapter.name, adapter.api))
        .collect();
    names.join(", ")
}

fn on_adapter(backend: Backend, adapter: &Adapter) -> ResolvedDevice {
    ResolvedDevice {
        backend,
        name: format!("{} ({})", adapter.name, adapter.api),
    }
}

fn cpu() -> ResolvedDevice {
    ResolvedDevice {
        backend: Backend::Cpu,
        name: "cpu".into(),
    }
}

fn cuda(devices: usize) -> ResolvedDevice {
    ResolvedDevice {
        backend: Backend::Cuda,
        name: format!("CUDA ({devices} devices)"),
    }
}

fn libtorch(cuda_devices: usize) -> ResolvedDevice {
    ResolvedDevice {
        backend: Backend::Libtorch,
        name: match cuda_devices {
            0 => "libtorch CPU".into(),
            count => format!("libtorch CUDA ({count} devices)"),
        },
    }
}

/// Resolves `choice` on this host, logs it and shows it on `/metrics`. The CPU needs no
/// driver, so only the other choices ask the drivers.
pub fn resolve(choice: DeviceChoice, registry: &Registry) -> Result<ResolvedDevice, DeviceMissing> {
    let host = match choice {
        DeviceChoice::Cpu => HostDevices::default(),
        _ => HostDevices::probe(),
    };
    let resolved = resolve_with(choice, &host, Backend::built)?;
    tracing::info!(
        asked = %choice,
        backend = resolved.backend.name(),
        device = %resolved.name,
        adapters = host.adapters.len(),
        cuda = ?host.cuda,
        libtorch_cuda = host.libtorch_cuda,
        "device"
    );
    registry.retain(&DEVICE_INFO, "name", |_| false);
    registry.set(
        &DEVICE_INFO,
        &[
            ("backend", resolved.backend.name()),
            ("name", &resolved.name),
        ],
        1.0,
    );
    Ok(resolved)
}

/// The device in use, kept for the heartbeats that tell the coordinator (its `status`).
#[derive(Debug, Default)]
pub struct DeviceReport(RwLock<Option<DeviceInUse>>);

impl DeviceReport {
    /// Records the device a generation trains on with `replicas` model replicas.
    pub fn set(&self, device: &ResolvedDevice, replicas: usize) {
        let in_use = DeviceInUse {
            backend: device.backend,
            name: device.name.clone(),
            replicas: u32::try_from(replicas).unwrap_or(u32::MAX),
        };
        *self
            .0
            .write()
            .unwrap_or_else(|poisoned| poisoned.into_inner()) = Some(in_use);
    }

    /// The device last recorded, if any.
    pub fn get(&self) -> Option<DeviceInUse> {
        self.0
            .read()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .clone()
    }
}

#[cfg(test)]
#[path = "device_tests.rs"]
mod tests;
