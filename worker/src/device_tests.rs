use trainer_core::backend::AdapterKind;

use super::*;

fn adapter(name: &str, kind: AdapterKind, api: &str) -> Adapter {
    Adapter {
        name: name.into(),
        kind,
        api: api.into(),
    }
}

fn lavapipe() -> Adapter {
    adapter("llvmpipe", AdapterKind::Software, "Vulkan")
}

fn h100() -> Adapter {
    adapter("NVIDIA H100", AdapterKind::DiscreteGpu, "Vulkan")
}

fn host(adapters: Vec<Adapter>, cuda: usize, libtorch_cuda: usize) -> HostDevices {
    HostDevices {
        adapters,
        cuda: match cuda {
            0 => Err(CudaUnavailable::NoDriverLibrary),
            count => Ok(count),
        },
        libtorch_cuda,
    }
}

fn every_backend(_: Backend) -> bool {
    true
}

fn default_build(backend: Backend) -> bool {
    backend.cargo_feature().is_none()
}

#[test]
fn auto_takes_a_gpu_adapter_and_never_a_software_one() {
    let on_gpu = host(vec![lavapipe(), h100()], 0, 0);
    let resolved = resolve_with(DeviceChoice::Auto, &on_gpu, default_build).unwrap();
    assert_eq!(resolved.backend, Backend::Wgpu);
    assert_eq!(resolved.name, "NVIDIA H100 (Vulkan)");
    let on_cpu = host(vec![lavapipe()], 0, 0);
    let resolved = resolve_with(DeviceChoice::Auto, &on_cpu, every_backend).unwrap();
    assert_eq!(resolved.backend, Backend::Cpu);
    let bare = resolve_with(DeviceChoice::Auto, &HostDevices::default(), every_backend);
    assert_eq!(bare.unwrap().name, "cpu");
}

#[test]
fn auto_prefers_cuda_then_libtorch_then_vulkan_then_wgpu_among_what_is_built() {
    let gpu_host = host(vec![h100()], 4, 4);
    let pick = |built: &dyn Fn(Backend) -> bool| {
        resolve_with(DeviceChoice::Auto, &gpu_host, built)
            .unwrap()
            .backend
    };
    assert_eq!(pick(&every_backend), Backend::Cuda);
    assert_eq!(pick(&|b| b != Backend::Cuda), Backend::Libtorch);
    assert_eq!(
        pick(&|b| !matches!(b, Backend::Cuda | Backend::Libtorch)),
        Backend::Vulkan
    );
    assert_eq!(pick(&default_build), Backend::Wgpu);
    let libtorch_without_cuda = host(vec![], 0, 0);
    let resolved = resolve_with(DeviceChoice::Auto, &libtorch_without_cuda, every_backend);
    assert_eq!(resolved.unwrap().backend, Backend::Cpu);
}

#[test]
fn a_backend_left_out_of_the_build_names_its_feature_and_how_to_rebuild() {
    for (choice, feature) in [
        (DeviceChoice::Vulkan, "vulkan"),
        (DeviceChoice::Cuda, "cuda"),
        (DeviceChoice::Libtorch, "libtorch"),
    ] {
        let missing = resolve_with(choice, &host(vec![h100()], 1, 1), default_build).unwrap_err();
        assert_eq!(
            missing,
            DeviceMissing::NotInThisBuild {
                backend: choice.backend().unwrap(),
                feature
            }
        );
        let message = missing.to_string();
        assert!(
            message.contains(&format!("--features {feature}")),
            "{message}"
        );
    }
}

#[test]
fn a_built_backend_without_its_device_says_what_is_missing() {
    let missing = resolve_with(DeviceChoice::Wgpu, &HostDevices::default(), every_backend);
    assert!(
        missing
            .unwrap_err()
            .to_string()
            .contains("mesa-vulkan-drivers"),
        "wgpu without adapters"
    );
    let metal_only = host(
        vec![adapter("Apple M3", AdapterKind::IntegratedGpu, "Metal")],
        0,
        0,
    );
    let missing = resolve_with(DeviceChoice::Vulkan, &metal_only, every_backend).unwrap_err();
    assert_eq!(
        missing,
        DeviceMissing::NoVulkanAdapter {
            found: "Apple M3 on Metal".into()
        }
    );
    let missing = resolve_with(DeviceChoice::Cuda, &metal_only, every_backend).unwrap_err();
    assert!(missing.to_string().contains("nvidia-smi"), "{missing}");
    let driver_without_nvrtc = HostDevices {
        cuda: Err(CudaUnavailable::NoNvrtc),
        ..HostDevices::default()
    };
    let missing = resolve_with(DeviceChoice::Cuda, &driver_without_nvrtc, every_backend);
    let message = missing.unwrap_err().to_string();
    assert!(
        message.starts_with("--device cuda: NVRTC (libnvrtc.so"),
        "{message}"
    );
    let auto = resolve_with(DeviceChoice::Auto, &driver_without_nvrtc, every_backend).unwrap();
    assert_eq!(
        auto.backend,
        Backend::Cpu,
        "auto passes over a CUDA that cannot run"
    );
}

#[test]
fn vulkan_runs_on_lavapipe_when_asked_and_libtorch_falls_back_to_its_cpu() {
    let on_lavapipe = host(vec![lavapipe()], 0, 0);
    let resolved = resolve_with(DeviceChoice::Vulkan, &on_lavapipe, every_backend).unwrap();
    assert_eq!(
        (resolved.backend, resolved.name.as_str()),
        (Backend::Vulkan, "llvmpipe (Vulkan)")
    );
    let resolved = resolve_with(DeviceChoice::Libtorch, &on_lavapipe, every_backend).unwrap();
    assert_eq!(resolved.name, "libtorch CPU");
    let resolved = resolve_with(DeviceChoice::Libtorch, &host(vec![], 0, 2), every_backend);
    assert_eq!(resolved.unwrap().name, "libtorch CUDA (2 devices)");
}

#[test]
fn the_cpu_needs_no_adapter() {
    let resolved = resolve_with(DeviceChoice::Cpu, &HostDevices::default(), default_build).unwrap();
    assert_eq!(
        (resolved.backend, resolved.name.as_str()),
        (Backend::Cpu, "cpu")
    );
}
