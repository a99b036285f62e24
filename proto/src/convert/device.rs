//! Device choices and the device a worker reports it trains on, both ways.

use settings::{DeviceChoice, DeviceInUse};

use super::ConvertError;
use crate::v1;

/// The wire form of a device choice.
pub fn device_to_wire(device: DeviceChoice) -> v1::Device {
    match device {
        DeviceChoice::Auto => v1::Device::Auto,
        DeviceChoice::Cpu => v1::Device::Cpu,
        DeviceChoice::Wgpu => v1::Device::Wgpu,
        DeviceChoice::Vulkan => v1::Device::Vulkan,
        DeviceChoice::Cuda => v1::Device::Cuda,
        DeviceChoice::Libtorch => v1::Device::Libtorch,
    }
}

/// A device choice from its wire value.
pub fn device_from_wire(value: i32, field: &'static str) -> Result<DeviceChoice, ConvertError> {
    match v1::Device::try_from(value) {
        Ok(v1::Device::Auto) => Ok(DeviceChoice::Auto),
        Ok(v1::Device::Cpu) => Ok(DeviceChoice::Cpu),
        Ok(v1::Device::Wgpu) => Ok(DeviceChoice::Wgpu),
        Ok(v1::Device::Vulkan) => Ok(DeviceChoice::Vulkan),
        Ok(v1::Device::Cuda) => Ok(DeviceChoice::Cuda),
        Ok(v1::Device::Libtorch) => Ok(DeviceChoice::Libtorch),
        Err(_) => Err(ConvertError::Unknown { field, value }),
    }
}

/// The device a message may carry (heartbeats, step reports, `status`), from its wire form.
pub fn reported_device(
    device: Option<&v1::DeviceInUse>,
    field: &'static str,
) -> Result<Option<DeviceInUse>, ConvertError> {
    device
        .map(|device| device_in_use_from_wire(device, field))
        .transpose()
}

/// One worker of `status`, as a `key=value` line: its id, name, device and throughput.
pub fn worker_line(worker: &v1::WorkerSummary) -> String {
    let device = match reported_device(worker.device.as_ref(), "worker_list.device") {
        Ok(Some(device)) => format!(
            "backend={} device={:?} replicas={}",
            device.backend, device.name, device.replicas
        ),
        Ok(None) => "backend=- device=-".into(),
        Err(error) => format!("device_error={:?}", error.to_string()),
    };
    format!(
        "worker={} name={:?} {device} pairs_per_s={:.2}",
        worker.worker_id, worker.name, worker.samples_per_s
    )
}

/// The wire form of the device a worker trains on.
pub fn device_in_use_to_wire(device: &DeviceInUse) -> v1::DeviceInUse {
    v1::DeviceInUse {
        backend: device_to_wire(device.backend.choice()) as i32,
        name: device.name.clone(),
        replicas: device.replicas,
    }
}

/// The device a worker trains on, from its wire form; `auto` is refused, a worker reports
/// what it resolved.
pub fn device_in_use_from_wire(
    device: &v1::DeviceInUse,
    field: &'static str,
) -> Result<DeviceInUse, ConvertError> {
    let backend = device_from_wire(device.backend, field)?
        .backend()
        .ok_or_else(|| ConvertError::Malformed {
            field,
            reason: "a worker reports the backend it resolved, never auto".into(),
        })?;
    Ok(DeviceInUse {
        backend,
        name: device.name.clone(),
        replicas: device.replicas,
    })
}
