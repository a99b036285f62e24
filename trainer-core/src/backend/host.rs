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

/// Why burn's CUDA backend cannot run here. cubecl-cuda loads libcuda and NVRTC at run time
/// and panics on a thread of its own when either is missing, so this is asked first.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CudaUnavailable {
    /// The binary was built without the `cuda` cargo feature.
    #[error("this build has no `cuda` cargo feature")]
    NotInThisBuild,
    /// The NVIDIA driver's library does not load.
    #[error(
        "the NVIDIA driver's libcuda.so does not load: is the driver installed (`nvidia-smi`) \
         and libcuda.so.1 on the library path?"
    )]
    NoDriverLibrary,
    /// NVRTC, which compiles every kernel of this build at run time, does not load.
    #[error(
        "NVRTC (libnvrtc.so of the CUDA toolkit, which compiles this build's kernels at run \
         time) does not load: add the toolkit's lib64 (e.g. /usr/local/cuda/lib64) to \
         LD_LIBRARY_PATH"
    )]
    NoNvrtc,
    /// The driver loaded but refused to start or to count devices.
    #[error("the CUDA driver failed: {0}")]
    Driver(String),
    /// The driver runs and reports no device.
    #[error("the CUDA driver reports no device")]
    NoDevice,
}

/// How many CUDA devices burn's CUDA backend can use, or why it cannot run here.
#[cfg(feature = "cuda")]
pub fn cuda_device_count() -> Result<usize, CudaUnavailable> {
    use cudarc::driver::result;
    // SAFETY: both only try to dlopen the library's candidate names; no symbol is called.
    if !unsafe { cudarc::driver::sys::is_culib_present() } {
        return Err(CudaUnavailable::NoDriverLibrary);
    }
    if !unsafe { cudarc::nvrtc::sys::is_culib_present() } {
        return Err(CudaUnavailable::NoNvrtc);
    }
    let driver_failed = |error: result::DriverError| CudaUnavailable::Driver(error.to_string());
    result::init().map_err(driver_failed)?;
    let count = result::device::get_count().map_err(driver_failed)?;
    match usize::try_from(count) {
        Ok(0) | Err(_) => Err(CudaUnavailable::NoDevice),
        Ok(count) => Ok(count),
    }
}

/// How many CUDA devices burn's CUDA backend can use: none in a build without `cuda`.
#[cfg(not(feature = "cuda"))]
pub fn cuda_device_count() -> Result<usize, CudaUnavailable> {
    Err(CudaUnavailable::NotInThisBuild)
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
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HostDevices {
    /// The wgpu adapters (Vulkan, Metal, DX12), in the drivers' order.
    pub adapters: Vec<Adapter>,
    /// CUDA devices of burn's CUDA backend, or why it cannot run here.
    pub cuda: Result<usize, CudaUnavailable>,
    /// CUDA devices of the installed libtorch (0 without CUDA or the `libtorch` feature).
    pub libtorch_cuda: usize,
}

/// A host with no device at all (burn's CPU backend only).
impl Default for HostDevices {
    fn default() -> Self {
        Self {
            adapters: Vec::new(),
            cuda: Err(CudaUnavailable::NotInThisBuild),
            libtorch_cuda: 0,
        }
    }
}

impl HostDevices {
    /// Asks the drivers. Slow the first time (each API's driver loads), so call it once per
    /// decision.
    pub fn probe() -> Self {
        Self {
            adapters: wgpu_adapters(),
            cuda: cuda_device_count(),
            libtorch_cuda: libtorch_cuda_devices(),
        }
    }
}
