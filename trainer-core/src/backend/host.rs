//! What devices this host offers each backend, asked of the drivers themselves (no guessing
//! from `/dev` nodes).

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

/// CUDA devices burn's CUDA backend sees; 0 in a build without the `cuda` feature.
pub(super) fn cuda_devices() -> usize {
    #[cfg(feature = "cuda")]
    {
        burn::tensor::Device::enumerate(burn::tensor::DeviceType::Cuda).len()
    }
    #[cfg(not(feature = "cuda"))]
    {
        0
    }
}

/// CUDA devices the installed PyTorch's libtorch sees; 0 without CUDA or without the
/// `libtorch` feature.
pub(super) fn libtorch_cuda_devices() -> usize {
    #[cfg(feature = "libtorch")]
    {
        burn::tensor::Device::enumerate(burn::tensor::DeviceType::LibTorch).len()
    }
    #[cfg(not(feature = "libtorch"))]
    {
        0
    }
}

/// A snapshot of what this host offers the backends of this build, for `auto` to choose
/// from and for errors to describe.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct HostDevices {
    /// The wgpu adapters (Vulkan, Metal, DX12), in the drivers' order.
    pub adapters: Vec<Adapter>,
    /// CUDA devices of burn's CUDA backend (0 without the `cuda` feature).
    pub cuda: usize,
    /// CUDA devices of the installed libtorch (0 without CUDA or the `libtorch` feature).
    pub libtorch_cuda: usize,
}

impl HostDevices {
    /// Asks the drivers. Slow the first time (each API's driver loads), so call it once per
    /// decision.
    pub fn probe() -> Self {
        Self {
            adapters: wgpu_adapters(),
            cuda: cuda_devices(),
            libtorch_cuda: libtorch_cuda_devices(),
        }
    }
}
