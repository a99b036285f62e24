//! What a process really holds of device memory, beside what burn's pools report.
//!
//! cubecl's pool figures count the pages its allocators reserved; they left out 80 GB of the
//! 92.5 GB an H200 showed in use during one step. So every figure printed or exported names
//! its source: the pools, the process's resident host memory (on the CPU backend and on
//! lavapipe, device memory is host memory, so resident memory beside the pools shows what
//! lies outside them), and the NVIDIA driver's own count of the device's and this process's
//! memory (NVML, loaded at run time; absent on hosts without the driver).

use std::sync::OnceLock;

use burn::tensor::Device;
use nvml_wrapper::Nvml;
use nvml_wrapper::enums::device::UsedGpuMemory;

/// Device memory figures, each `None` where its source does not answer here.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MemoryFigures {
    /// Bytes cubecl's pools reserved on the device (their pages, in use or kept for reuse).
    pub pool_reserved: Option<u64>,
    /// Bytes of live allocations in those pools.
    pub pool_in_use: Option<u64>,
    /// This process's resident host memory now (`VmRSS`).
    pub host_resident: Option<u64>,
    /// This process's peak resident host memory (`VmHWM`).
    pub host_peak_resident: Option<u64>,
    /// Bytes in use on NVIDIA GPU 0 by every process, as the driver counts them.
    pub driver_device_used: Option<u64>,
    /// Bytes this process holds on NVIDIA GPU 0, as the driver counts them.
    pub driver_process_used: Option<u64>,
}

impl MemoryFigures {
    /// Reads every source now; `device` is the one whose pools are asked.
    pub fn read(device: &Device) -> Self {
        let pools = device.memory_pool_usage();
        let (driver_device_used, driver_process_used) = nvidia_driver_memory();
        let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
        let status_bytes = |key| parse_status_kib(&status, key).map(|kib| kib * 1024);
        Self {
            pool_reserved: pools.map(|usage| usage.bytes_reserved),
            pool_in_use: pools.map(|usage| usage.bytes_in_use),
            host_resident: status_bytes("VmRSS:"),
            host_peak_resident: status_bytes("VmHWM:"),
            driver_device_used,
            driver_process_used,
        }
    }

    /// The figures present, by the name each is printed and exported under.
    pub fn named(&self) -> Vec<(&'static str, u64)> {
        [
            ("pool_reserved", self.pool_reserved),
            ("pool_in_use", self.pool_in_use),
            ("host_resident", self.host_resident),
            ("host_peak_resident", self.host_peak_resident),
            ("driver_device_used", self.driver_device_used),
            ("driver_process_used", self.driver_process_used),
        ]
        .into_iter()
        .filter_map(|(name, value)| Some((name, value?)))
        .collect()
    }

    /// ` memory_NAME_bytes=VALUE` for each figure present, for a benchmark's `key=value` line.
    pub fn key_values(&self) -> String {
        self.named()
            .into_iter()
            .map(|(name, value)| format!(" memory_{name}_bytes={value}"))
            .collect()
    }
}

/// The KiB count of `/proc/self/status`'s line `key` (`VmRSS:`, `VmHWM:`).
fn parse_status_kib(status: &str, key: &str) -> Option<u64> {
    let line = status.lines().find(|line| line.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// NVML, loaded once; `None` where the driver's library is absent or refuses.
fn nvml() -> Option<&'static Nvml> {
    static NVML: OnceLock<Option<Nvml>> = OnceLock::new();
    NVML.get_or_init(|| Nvml::init().ok()).as_ref()
}

/// GPU 0's used bytes and this process's share of them (compute and graphics contexts: CUDA
/// kernels are the first, Vulkan's the second), as the NVIDIA driver counts them.
fn nvidia_driver_memory() -> (Option<u64>, Option<u64>) {
    let Some(gpu) = nvml().and_then(|nvml| nvml.device_by_index(0).ok()) else {
        return (None, None);
    };
    let device_used = gpu.memory_info().ok().map(|info| info.used);
    let pid = std::process::id();
    let processes = [
        gpu.running_compute_processes(),
        gpu.running_graphics_processes(),
    ];
    let process_used = processes
        .into_iter()
        .flatten()
        .flatten()
        .filter(|process| process.pid == pid)
        .filter_map(|process| match process.used_gpu_memory {
            UsedGpuMemory::Used(bytes) => Some(bytes),
            UsedGpuMemory::Unavailable => None,
        })
        .max();
    (device_used, process_used)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_lines_are_read_in_kib() {
        let status = "Name:\tbench\nVmHWM:\t  2048 kB\nVmRSS:\t  1024 kB\n";
        assert_eq!(parse_status_kib(status, "VmRSS:"), Some(1024));
        assert_eq!(parse_status_kib(status, "VmHWM:"), Some(2048));
        assert_eq!(parse_status_kib(status, "VmSwap:"), None);
    }

    #[test]
    fn only_the_figures_present_are_printed_each_with_its_source() {
        let figures = MemoryFigures {
            pool_reserved: Some(10),
            host_resident: Some(30),
            ..MemoryFigures::default()
        };
        assert_eq!(
            figures.key_values(),
            " memory_pool_reserved_bytes=10 memory_host_resident_bytes=30"
        );
    }

    #[test]
    fn the_cpu_backend_reports_this_process_resident_memory() {
        let figures = MemoryFigures::read(&Device::flex());
        let resident = figures.host_resident.expect("Linux reports VmRSS");
        assert!(resident > 0 && figures.host_peak_resident >= Some(resident));
    }
}
