//! Which burn backend a worker trains on, from the job's or its own device choice.

use std::path::Path;

use settings::DeviceChoice;
use trainer_core::backend::BackendChoice;

/// The backend for `choice`: `auto` takes wgpu where the host has an NVIDIA or AMD GPU
/// device node, the CPU otherwise.
pub fn backend(choice: DeviceChoice) -> BackendChoice {
    match choice {
        DeviceChoice::Cpu => BackendChoice::Cpu,
        DeviceChoice::Wgpu => BackendChoice::Wgpu,
        DeviceChoice::Auto => {
            if ["/dev/nvidiactl", "/dev/kfd"]
                .iter()
                .any(|p| Path::new(p).exists())
            {
                BackendChoice::Wgpu
            } else {
                BackendChoice::Cpu
            }
        }
    }
}
