//! Choosing the compute device: burn's pure-Rust CPU backend, burn-wgpu (WGSL), and, in builds
//! with their cargo features, Vulkan (SPIR-V), CUDA and libtorch. A backend this build lacks is
//! an error that names the feature, never a panic inside burn.

mod host;
mod kernel_cache;
mod kernel_time;
mod kernels;
mod memory;

use burn::tensor::{Device, DeviceKind};
pub use host::{
    Adapter, AdapterKind, CudaUnavailable, HostDevices, cuda_device_count, wgpu_adapters,
};
pub use kernel_cache::{KernelCache, KernelCacheError, default_kernel_cache, keep_kernels_in};
pub use kernel_time::{KernelTime, time_kernels};
pub use kernels::{KernelCounts, count_kernels};
pub use memory::MemoryFigures;
pub use settings::Backend;

/// The `--backend` flag of the binaries that run the model in one process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::Args)]
pub struct BackendArgs {
    /// Compute backend: cpu (alias flex), wgpu (alias gpu), vulkan, cuda, libtorch; the last
    /// three only in a build with that cargo feature
    #[arg(long, default_value_t = Backend::Cpu, value_name = "BACKEND")]
    pub backend: Backend,
}

/// Why a backend's device cannot be made.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DeviceError {
    /// The backend's cargo feature was off when this binary was built.
    #[error(
        "{backend} is not in this build: rebuild with `--features {feature}` (docs/gpus.md), \
         or choose cpu or wgpu"
    )]
    NotInThisBuild {
        /// The backend asked.
        backend: Backend,
        /// The cargo feature it needs.
        feature: &'static str,
    },
    /// A device index the backend does not have here.
    #[error("{backend} has no device {id} on this host (it has {count})")]
    NoSuchDevice {
        /// The backend asked.
        backend: Backend,
        /// The index it lacks.
        id: usize,
        /// How many devices it has.
        count: usize,
    },
    /// burn's CUDA backend cannot run on this host.
    #[error("cuda: {0}")]
    Cuda(#[from] CudaUnavailable),
}

/// Making burn devices of a [`Backend`], as far as this build's cargo features allow.
pub trait BackendDevices: Copy {
    /// Whether this binary was built with the backend.
    fn built(self) -> bool;

    /// The backend's first device (the default adapter on wgpu and Vulkan); add `.autodiff()`
    /// to train on it.
    fn device(self) -> Result<Device, DeviceError>;

    /// The devices of `set`, one model replica each. The CPU is one device: `all` is one
    /// replica and a count `N` is `N` replicas on it. Elsewhere `all` is every device of the
    /// backend on this host and a count the first `N`.
    fn devices(self, set: &settings::DeviceSet) -> Result<Vec<Device>, DeviceError>;
}

impl BackendDevices for Backend {
    fn built(self) -> bool {
        match self {
            Self::Cpu | Self::Wgpu => true,
            Self::Vulkan => cfg!(feature = "vulkan"),
            Self::Cuda => cfg!(feature = "cuda"),
            Self::Libtorch => cfg!(feature = "libtorch"),
        }
    }

    fn device(self) -> Result<Device, DeviceError> {
        device_at(self, 0, 1)
    }

    fn devices(self, set: &settings::DeviceSet) -> Result<Vec<Device>, DeviceError> {
        use settings::DeviceSet;
        if !self.built() {
            return Err(not_in_this_build(self));
        }
        let count = device_count(self);
        match set {
            // At least device 0 is asked for, so a backend with none says why.
            DeviceSet::All => (0..count.max(1))
                .map(|id| device_at(self, id, count))
                .collect(),
            DeviceSet::Count(replicas) if count == 1 && on_one_host_device(self) => {
                Ok(vec![self.device()?; *replicas])
            }
            DeviceSet::Count(wanted) => (0..*wanted).map(|id| device_at(self, id, count)).collect(),
            DeviceSet::Ids(ids) => ids.iter().map(|&id| device_at(self, id, count)).collect(),
        }
    }
}

/// How many threads split a micro-batch when neither the job nor the worker says: one per core
/// on burn's CPU backend, whose element-wise kernels run on one thread each, so shards on
/// threads use the other cores. One elsewhere: a GPU runs one shard's kernels as fast as
/// several, and on cubecl's runtimes every thread that launches work gets its own stream and
/// memory pools, so sixteen shards on a sixteen-core GPU host hold sixteen sets of buffers.
pub fn default_shards(backend: Backend, cores: usize) -> usize {
    match backend {
        Backend::Cpu => cores.max(1),
        Backend::Wgpu | Backend::Vulkan | Backend::Cuda | Backend::Libtorch => 1,
    }
}

/// Whether the backend's only device is the host's CPU, which takes any number of replicas.
fn on_one_host_device(backend: Backend) -> bool {
    match backend {
        Backend::Cpu => true,
        Backend::Libtorch => host::libtorch_cuda_devices() == 0,
        Backend::Wgpu | Backend::Vulkan | Backend::Cuda => false,
    }
}

/// How many devices `all` means: the CPU is one; wgpu and Vulkan count the GPU adapters (at
/// least the default one); CUDA and libtorch their CUDA devices (libtorch without CUDA: its CPU).
fn device_count(backend: Backend) -> usize {
    match backend {
        Backend::Cpu => 1,
        Backend::Wgpu | Backend::Vulkan => wgpu_adapters()
            .iter()
            .filter(|adapter| adapter.kind == AdapterKind::DiscreteGpu)
            .count()
            .max(1),
        Backend::Cuda => host::cuda_device_count().unwrap_or(0),
        Backend::Libtorch => host::libtorch_cuda_devices().max(1),
    }
}

fn not_in_this_build(backend: Backend) -> DeviceError {
    DeviceError::NotInThisBuild {
        backend,
        feature: backend.cargo_feature().unwrap_or("default"),
    }
}

/// Device `id` of `backend`, which has `count` here.
fn device_at(backend: Backend, id: usize, count: usize) -> Result<Device, DeviceError> {
    if !backend.built() {
        return Err(not_in_this_build(backend));
    }
    let missing = DeviceError::NoSuchDevice { backend, id, count };
    match backend {
        Backend::Cpu if id == 0 => Ok(Device::flex()),
        Backend::Cpu => Err(missing),
        Backend::Wgpu => Ok(Device::wgpu(wgpu_kind(id))),
        Backend::Vulkan => vulkan(id).ok_or(missing),
        Backend::Cuda => match host::cuda_device_count()? {
            count if id < count => cuda(id).ok_or(missing),
            _ => Err(missing),
        },
        Backend::Libtorch => libtorch(id).ok_or(missing),
    }
}

/// wgpu's device for replica `index`: the default adapter first, then discrete GPUs.
fn wgpu_kind(index: usize) -> DeviceKind {
    if index == 0 {
        DeviceKind::DefaultDevice
    } else {
        DeviceKind::DiscreteGpu(index)
    }
}

#[cfg(feature = "vulkan")]
fn vulkan(index: usize) -> Option<Device> {
    Some(Device::vulkan(wgpu_kind(index)))
}

#[cfg(not(feature = "vulkan"))]
fn vulkan(_index: usize) -> Option<Device> {
    None
}

#[cfg(feature = "cuda")]
fn cuda(index: usize) -> Option<Device> {
    Some(Device::cuda(index))
}

#[cfg(not(feature = "cuda"))]
fn cuda(_index: usize) -> Option<Device> {
    None
}

/// libtorch's CUDA device `index` where PyTorch has CUDA, else its CPU as device 0. burn marks
/// burn-tch deprecated in 0.22, but it is the only road to libtorch's CUDA kernels.
#[cfg(feature = "libtorch")]
#[allow(deprecated)]
fn libtorch(index: usize) -> Option<Device> {
    let cuda = host::libtorch_cuda_devices();
    match (cuda, index) {
        (0, 0) => Some(Device::libtorch()),
        (0, _) => None,
        (cuda, index) if index < cuda => Some(Device::libtorch_cuda(index)),
        _ => None,
    }
}

#[cfg(not(feature = "libtorch"))]
fn libtorch(_index: usize) -> Option<Device> {
    None
}

#[cfg(test)]
mod tests {
    use settings::DeviceSet;

    use super::*;

    #[test]
    fn the_cpu_is_one_device_that_takes_any_number_of_replicas() {
        assert_eq!(Backend::Cpu.devices(&DeviceSet::All).unwrap().len(), 1);
        assert_eq!(Backend::Cpu.devices(&DeviceSet::Count(3)).unwrap().len(), 3);
        assert_eq!(
            Backend::Cpu
                .devices(&DeviceSet::Ids(vec![0, 2]))
                .unwrap_err(),
            DeviceError::NoSuchDevice {
                backend: Backend::Cpu,
                id: 2,
                count: 1
            }
        );
    }

    /// On a host without the NVIDIA driver (CI's, this project's machines) a `cuda` build refuses
    /// every way of asking for a CUDA device with the missing library's name, where cubecl-cuda
    /// alone would panic on its own thread.
    #[cfg(feature = "cuda")]
    #[test]
    fn cuda_without_its_driver_is_refused_naming_the_library() {
        let Err(why) = cuda_device_count() else {
            return; // a host with a working CUDA driver: nothing to refuse
        };
        assert_ne!(why, CudaUnavailable::NotInThisBuild);
        let expected = DeviceError::Cuda(why.clone());
        assert_eq!(Backend::Cuda.device().unwrap_err(), expected);
        for set in [DeviceSet::All, DeviceSet::Count(2), DeviceSet::Ids(vec![1])] {
            assert_eq!(
                Backend::Cuda.devices(&set).unwrap_err(),
                expected,
                "{set:?}"
            );
        }
        let message = expected.to_string();
        assert!(
            message.contains("libcuda.so") || message.contains("libnvrtc.so"),
            "{message}"
        );
    }

    #[test]
    fn only_the_cpu_backend_splits_a_batch_over_the_cores_by_default() {
        assert_eq!(default_shards(Backend::Cpu, 16), 16);
        assert_eq!(default_shards(Backend::Cpu, 0), 1);
        for gpu in [
            Backend::Wgpu,
            Backend::Vulkan,
            Backend::Cuda,
            Backend::Libtorch,
        ] {
            assert_eq!(default_shards(gpu, 16), 1, "{gpu}");
        }
    }

    #[test]
    fn a_backend_left_out_of_the_build_names_its_feature() {
        for backend in [Backend::Vulkan, Backend::Cuda, Backend::Libtorch] {
            if backend.built() {
                continue;
            }
            let error = backend.device().unwrap_err();
            let feature = backend.cargo_feature().unwrap();
            assert_eq!(
                error,
                DeviceError::NotInThisBuild { backend, feature },
                "{backend}"
            );
            assert!(
                error.to_string().contains(&format!("--features {feature}")),
                "{error}"
            );
        }
    }
}
