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

use super::kernels::kernel_kind;

/// Where the device time of some work went.
#[derive(Debug, Clone, Default, PartialEq)]
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
    /// The timed kernels' device time by kind (the first field of cubecl's label), in
    /// seconds, the largest first: where a step's device time goes.
    pub by_kind: Vec<(String, f64)>,
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

    /// `kind:milliseconds` for the `top` kinds that took the most device time, `;`-separated
    /// (no spaces, so it is one `key=value` figure).
    pub fn top(&self, top: usize) -> String {
        let parts: Vec<String> = self
            .by_kind
            .iter()
            .take(top)
            .map(|(kind, seconds)| format!("{kind}:{:.1}", seconds * 1e3))
            .collect();
        parts.join(";")
    }

    /// Orders `by_kind` largest first, as its readers expect.
    fn sort_by_time(&mut self) {
        self.by_kind
            .sort_by(|a, b| b.1.total_cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    }

    /// Adds one kernel's device time to the totals.
    fn add(&mut self, kernel: &str, seconds: f64, method: TimingMethod) {
        self.timed += 1;
        self.device_s += seconds;
        self.host_timed |= method == TimingMethod::System;
        let kind = kernel_kind(kernel);
        match self.by_kind.iter_mut().find(|(known, _)| *known == kind) {
            Some((_, total)) => *total += seconds,
            None => self.by_kind.push((kind, seconds)),
        }
    }
}

/// What the observer collected while installed.
#[derive(Default)]
struct Timings {
    launched: AtomicU64,
    unread: Mutex<Vec<(&'static str, ProfileDuration)>>,
    read: Mutex<Vec<(&'static str, Duration, TimingMethod)>>,
}

impl LaunchObserver for Timings {
    fn launched(&self, _kernel: &'static str) {
        self.launched.fetch_add(1, Ordering::Relaxed);
    }

    fn timing(&self) -> TimingRequest {
        TimingRequest::Deferred
    }

    fn profiled(&self, kernel: &'static str, profile: ProfileDuration) {
        self.unread
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push((kernel, profile));
    }

    /// Where the profiling logger is on, it reads each measurement itself and hands over the
    /// length (the kernels then ran one at a time).
    fn timed(&self, kernel: &'static str, duration: Duration, method: TimingMethod) {
        self.read
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push((kernel, duration, method));
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
    for (kernel, profile) in unread {
        let method = profile.timing_method();
        let Some(ticks) = futures::executor::block_on(profile.resolve()) else {
            continue;
        };
        time.add(kernel, ticks.duration().as_secs_f64(), method);
        first_start = first_start.min(ticks.start_duration_since(epoch).as_secs_f64());
        last_end = last_end.max(ticks.end_duration_since(epoch).as_secs_f64());
    }
    for (kernel, duration, method) in timings
        .read
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .iter()
    {
        time.add(kernel, duration.as_secs_f64(), *method);
    }
    if last_end > first_start {
        time.span_s = last_end - first_start;
    }
    time.sort_by_time();
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
        let split: f64 = time.by_kind.iter().map(|(_, seconds)| seconds).sum();
        assert!((split - time.device_s).abs() <= 1e-9, "{time:?}");
        assert!(time.by_kind.windows(2).all(|pair| pair[0].1 >= pair[1].1));
    }

    #[test]
    fn device_time_is_split_by_kind_largest_first() {
        let mut time = KernelTime::default();
        time.add(
            "Matmul | f32 | CubeTensor_1a2b3c4d",
            0.004,
            TimingMethod::Device,
        );
        time.add("reduce_sum_deadbeef", 0.001, TimingMethod::Device);
        time.add(
            "Matmul | f32 | CubeTensor_0badcafe",
            0.002,
            TimingMethod::Device,
        );
        time.sort_by_time();
        assert_eq!((time.timed, time.method()), (3, "device"));
        assert_eq!(time.top(1), "Matmul:6.0");
        assert_eq!(time.top(5), "Matmul:6.0;reduce_sum:1.0");
    }
}
