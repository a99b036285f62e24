//! Which burn backend a worker trains on, from the job's or its own device choice, checked
//! against the adapters the host's drivers report: `auto` takes a GPU adapter when there is
//! one and the CPU otherwise, and `wgpu` asked of a host with no adapter is an error that says
//! what is missing, before any work starts.

use settings::DeviceChoice;
use telemetry::Registry;
use trainer_core::backend::{Adapter, BackendChoice, wgpu_adapters};

use crate::metrics::DEVICE_INFO;

/// A device choice resolved on this host.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResolvedDevice {
    /// The backend to build the trainer on.
    pub backend: BackendChoice,
    /// The adapter's name (`cpu` for burn's CPU backend).
    pub name: String,
}

/// A device asked for that this host does not have.
#[derive(Debug, thiserror::Error)]
#[error(
    "--device wgpu: no Vulkan, Metal or DX12 adapter answered on this host; install a driver \
     (a GPU's, with its Vulkan ICD, or mesa-vulkan-drivers for lavapipe on the CPU) or use --device cpu"
)]
pub struct DeviceMissing;

/// Resolves `choice` against `adapters` (the host's, in the drivers' order).
pub fn resolve_with(
    choice: DeviceChoice,
    adapters: &[Adapter],
) -> Result<ResolvedDevice, DeviceMissing> {
    let gpu = adapters.iter().find(|adapter| adapter.is_gpu());
    let wgpu = |adapter: &Adapter| ResolvedDevice {
        backend: BackendChoice::Wgpu,
        name: format!("{} ({})", adapter.name, adapter.api),
    };
    let cpu = ResolvedDevice {
        backend: BackendChoice::Cpu,
        name: "cpu".into(),
    };
    match choice {
        DeviceChoice::Cpu => Ok(cpu),
        DeviceChoice::Auto => Ok(gpu.map_or(cpu, wgpu)),
        DeviceChoice::Wgpu => gpu.or(adapters.first()).map(wgpu).ok_or(DeviceMissing),
    }
}

/// Resolves `choice` on this host, logs it and shows it on `/metrics`. The CPU needs no
/// driver, so only `auto` and `wgpu` ask the drivers.
pub fn resolve(choice: DeviceChoice, registry: &Registry) -> Result<ResolvedDevice, DeviceMissing> {
    let adapters = match choice {
        DeviceChoice::Cpu => Vec::new(),
        DeviceChoice::Auto | DeviceChoice::Wgpu => wgpu_adapters(),
    };
    let resolved = resolve_with(choice, &adapters)?;
    tracing::info!(
        asked = %choice,
        backend = resolved.backend.name(),
        device = %resolved.name,
        adapters = adapters.len(),
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

#[cfg(test)]
mod tests {
    use trainer_core::backend::AdapterKind;

    use super::*;

    fn adapter(name: &str, kind: AdapterKind) -> Adapter {
        Adapter {
            name: name.into(),
            kind,
            api: "Vulkan".into(),
        }
    }

    #[test]
    fn auto_takes_a_gpu_adapter_and_never_a_software_one() {
        let lavapipe = adapter("llvmpipe", AdapterKind::Software);
        let h100 = adapter("NVIDIA H100", AdapterKind::DiscreteGpu);
        let on_gpu = resolve_with(DeviceChoice::Auto, &[lavapipe.clone(), h100]).unwrap();
        assert_eq!(on_gpu.backend, BackendChoice::Wgpu);
        assert_eq!(on_gpu.name, "NVIDIA H100 (Vulkan)");
        let on_cpu = resolve_with(DeviceChoice::Auto, &[lavapipe]).unwrap();
        assert_eq!(on_cpu.backend, BackendChoice::Cpu);
        assert_eq!(resolve_with(DeviceChoice::Auto, &[]).unwrap().name, "cpu");
    }

    #[test]
    fn wgpu_runs_on_a_software_adapter_but_not_on_none() {
        let lavapipe = adapter("llvmpipe", AdapterKind::Software);
        let resolved = resolve_with(DeviceChoice::Wgpu, &[lavapipe]).unwrap();
        assert_eq!(resolved.backend, BackendChoice::Wgpu);
        let missing = resolve_with(DeviceChoice::Wgpu, &[]).unwrap_err();
        assert!(
            missing.to_string().contains("mesa-vulkan-drivers"),
            "{missing}"
        );
    }

    #[test]
    fn the_cpu_needs_no_adapter() {
        let resolved = resolve_with(DeviceChoice::Cpu, &[]).unwrap();
        assert_eq!(
            (resolved.backend, resolved.name.as_str()),
            (BackendChoice::Cpu, "cpu")
        );
    }
}
