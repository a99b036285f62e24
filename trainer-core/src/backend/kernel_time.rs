//! The device time of the kernels a piece of work launches on cubecl's runtimes, beside its
//! wall time: whether a step is bound by the device or by the host that feeds it.
//!
//! Each launch is bracketed by timing events that nothing waits for (cubecl's deferred
//! timing), so the kernels still run back to back; the events are read once the work is over.
//! The brackets cost the host a little per launch, so a step measured this way is a step of
//! its own, not one of the timed ones.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use burn::cubecl::logging::{
    Duration, LaunchObservation, LaunchObserver, ProfileDuration, TimingMethod, TimingRequest,
};

/// Where the device time of some work went.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct KernelTime {
    /// Kernels launched.
    pub launched: u64,
    /// Kernels whose time was read.
    pub timed: u64,
    /// The timed kernels' device time, summed, in seconds.
    pub device_s: f64,
    /// From the first timed kernel's start to the last one's end, in seconds: the device time
    /// and the gaps where the device waited for the host (0 where the backend gives lengths
    /// without a common clock).
    pub span_s: f64,
    /// Whether some kernel was timed on the host's clock around a blocking submit
    /// (`TimingMethod::System`: wgpu once its timestamp queries run out, or without them),
    /// which counts submission and compilation too.
    pub host_timed: bool,
}

impl KernelTime {
    /// The method as one word for a `key=value` figure.
    pub fn method(&self) -> &'static str {
        if self.timed == 0 {
            "none"
        } else if self.host_timed {
            "host"
        } else {
            "device"
        }
    }
}

/// What the observer collected while installed.
#[derive(Default)]
struct Timings {
    launched: AtomicU64,
    unread: Mutex<Vec<ProfileDuration>>,
    read: Mutex<Vec<(Duration, TimingMethod)>>,
}

impl LaunchObserver for Timings {
    fn launched(&self, _kernel: &'static str) {
        self.launched.fetch_add(1, Ordering::Relaxed);
    }

    fn timing(&self) -> TimingRequest {
        TimingRequest::Deferred
    }

    fn profiled(&self, _kernel: &'static str, profile: ProfileDuration) {
        self.unread
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(profile);
    }

    /// Where the profiling logger is on, it reads each measurement itself and hands over the
    /// length (the kernels then ran one at a time).
    fn timed(&self, _kernel: &'static str, duration: Duration, method: TimingMethod) {
        self.read
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push((duration, method));
    }
}

/// Runs `work` and returns the device time of the kernels it launched on cubecl's runtimes
/// (none on burn's CPU backend or libtorch). cubecl's observer is process-wide: launches of
/// other threads in that time are counted too.
pub fn time_kernels<T>(work: impl FnOnce() -> T) -> (T, KernelTime) {
    let timings = Arc::new(Timings::default());
    let observation = LaunchObservation::new(timings.clone());
    let epoch = Instant::now();
    let result = work();
    drop(observation);
    let mut time = KernelTime {
        launched: timings.launched.load(Ordering::Relaxed),
        ..KernelTime::default()
    };
    let (mut first_start, mut last_end) = (f64::INFINITY, 0.0f64);
    let unread = std::mem::take(
        &mut *timings
            .unread
            .lock()
            .unwrap_or_else(PoisonError::into_inner),
    );
    for profile in unread {
        let method = profile.timing_method();
        let Some(ticks) = futures::executor::block_on(profile.resolve()) else {
            continue;
        };
        time.timed += 1;
        time.device_s += ticks.duration().as_secs_f64();
        time.host_timed |= method == TimingMethod::System;
        first_start = first_start.min(ticks.start_duration_since(epoch).as_secs_f64());
        last_end = last_end.max(ticks.end_duration_since(epoch).as_secs_f64());
    }
    for (duration, method) in timings
        .read
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .iter()
    {
        time.timed += 1;
        time.device_s += duration.as_secs_f64();
        time.host_timed |= *method == TimingMethod::System;
    }
    if last_end > first_start {
        time.span_s = last_end - first_start;
    }
    (result, time)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::{Backend, BackendDevices};
    use burn::tensor::{Device, Distribution, Tensor};

    #[test]
    fn the_cpu_backend_launches_no_kernels() {
        let device = Device::flex();
        let (_, time) = time_kernels(|| {
            let x = Tensor::<2>::random([64, 64], Distribution::Default, &device);
            x.clone().matmul(x).sum().into_scalar::<f32>()
        });
        assert_eq!((time.launched, time.timed), (0, 0));
        assert_eq!(time.method(), "none");
    }

    /// On the Cube backend (wgpu; lavapipe where there is no GPU) a matmul and a sum launch
    /// kernels, each timed, and their time is positive and within the work's wall time.
    #[test]
    fn cube_kernels_are_counted_and_timed() {
        let device = Backend::Wgpu
            .device()
            .expect("a wgpu adapter (lavapipe where there is no GPU)");
        let x = Tensor::<2>::random([128, 128], Distribution::Default, &device);
        let _: f32 = x.clone().sum().into_scalar();
        let started = Instant::now();
        let (_, time) = time_kernels(|| x.clone().matmul(x).sum().into_scalar::<f32>());
        let wall = started.elapsed().as_secs_f64();
        assert!(time.launched >= 2, "{time:?}");
        assert!(time.timed >= 1 && time.timed <= time.launched, "{time:?}");
        assert!(
            time.device_s > 0.0 && time.device_s <= wall,
            "{time:?}, wall {wall}"
        );
        assert_ne!(time.method(), "none");
    }
}
