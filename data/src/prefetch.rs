//! A prefetching wrapper around any [`BatchSource`]: worker threads assemble the micro-batches
//! the trainer will ask for next (read + decode in parallel) into a bounded queue, so data
//! loading overlaps the backward pass.

use std::collections::BTreeMap;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;

use crate::batch::{BatchSource, SampleError, Samples};

/// The request pattern the trainer follows: for each step, micro-batches of `micro_batch`
/// samples covering `first_sample..first_sample + global_batch` (a data-parallel rank asks for
/// its slice of the global batch only).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Schedule {
    /// First step to prefetch.
    pub start_step: u64,
    /// First sample of each step this consumer asks for (0 for a single process).
    pub first_sample: u64,
    /// Samples per step.
    pub global_batch: usize,
    /// Samples per request.
    pub micro_batch: usize,
}

impl Schedule {
    fn per_step(&self) -> u64 {
        (self.global_batch / self.micro_batch.max(1)).max(1) as u64
    }

    fn key(&self, index: u64) -> (u64, u64) {
        let per_step = self.per_step();
        (
            self.start_step + index / per_step,
            self.first_sample + (index % per_step) * self.micro_batch as u64,
        )
    }

    fn index(&self, step: u64, first: u64, count: usize) -> Option<u64> {
        let offset = first.checked_sub(self.first_sample)?;
        let aligned = count == self.micro_batch
            && step >= self.start_step
            && offset < self.global_batch as u64
            && offset.is_multiple_of(self.micro_batch.max(1) as u64);
        aligned
            .then(|| (step - self.start_step) * self.per_step() + offset / self.micro_batch as u64)
    }
}

struct State {
    next_claim: u64,
    consumed: u64,
    /// Results by request index, each removed when handed out (errors included), so none is
    /// ever handed out twice.
    ready: BTreeMap<u64, Result<Samples, SampleError>>,
    stop: bool,
}

struct Shared {
    state: Mutex<State>,
    changed: Condvar,
    depth: u64,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Serves a [`BatchSource`]'s samples from a queue filled ahead of time by worker threads.
pub struct Prefetched<S: BatchSource + Send + 'static> {
    inner: Arc<S>,
    schedule: Schedule,
    shared: Arc<Shared>,
    workers: Vec<JoinHandle<()>>,
}

impl<S: BatchSource + Send + 'static> Prefetched<S> {
    /// Starts `workers` threads keeping up to `depth` micro-batches ready.
    pub fn new(inner: S, schedule: Schedule, depth: usize, workers: usize) -> Self {
        let inner = Arc::new(inner);
        let shared = Arc::new(Shared {
            state: Mutex::new(State {
                next_claim: 0,
                consumed: 0,
                ready: BTreeMap::new(),
                stop: false,
            }),
            changed: Condvar::new(),
            depth: depth.max(1) as u64,
        });
        let workers = (0..workers.max(1))
            .map(|_| {
                let (inner, shared) = (Arc::clone(&inner), Arc::clone(&shared));
                std::thread::spawn(move || fill(&*inner, schedule, &shared))
            })
            .collect();
        Self {
            inner,
            schedule,
            shared,
            workers,
        }
    }

    /// Micro-batches assembled and waiting (the loader's queue depth).
    pub fn queued(&self) -> usize {
        self.shared.lock().ready.len()
    }

    /// The wrapped source.
    pub fn inner(&self) -> &S {
        &self.inner
    }
}

fn fill<S: BatchSource>(source: &S, schedule: Schedule, shared: &Shared) {
    loop {
        let index = {
            let mut state = shared.lock();
            while !state.stop && state.next_claim >= state.consumed + shared.depth {
                state = shared
                    .changed
                    .wait(state)
                    .unwrap_or_else(PoisonError::into_inner);
            }
            if state.stop {
                return;
            }
            let index = state.next_claim.max(state.consumed);
            state.next_claim = index + 1;
            index
        };
        let (step, first) = schedule.key(index);
        let samples = source.samples(step, first, schedule.micro_batch);
        let mut state = shared.lock();
        if index >= state.consumed {
            state.ready.insert(index, samples);
        }
        shared.changed.notify_all();
    }
}

impl<S: BatchSource + Send + 'static> BatchSource for Prefetched<S> {
    fn samples(&self, step: u64, first: u64, count: usize) -> Result<Samples, SampleError> {
        let Some(index) = self.schedule.index(step, first, count) else {
            return self.inner.samples(step, first, count);
        };
        let mut state = self.shared.lock();
        if index < state.consumed {
            drop(state);
            return self.inner.samples(step, first, count);
        }
        state.consumed = index;
        state.ready.retain(|&queued, _| queued >= index);
        self.shared.changed.notify_all();
        loop {
            if let Some(samples) = state.ready.remove(&index) {
                state.consumed = index + 1;
                self.shared.changed.notify_all();
                return samples;
            }
            if state.next_claim <= index {
                // Nobody is working on it (the trainer jumped ahead): make it here.
                state.next_claim = index + 1;
                drop(state);
                let samples = self.inner.samples(step, first, count);
                let mut state = self.shared.lock();
                state.consumed = index + 1;
                self.shared.changed.notify_all();
                return samples;
            }
            state = self
                .shared
                .changed
                .wait(state)
                .unwrap_or_else(PoisonError::into_inner);
        }
    }
}

impl<S: BatchSource + Send + 'static> Drop for Prefetched<S> {
    fn drop(&mut self) {
        self.shared.lock().stop = true;
        self.shared.changed.notify_all();
        for worker in self.workers.drain(..) {
            let _ = worker.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::Image;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::time::Duration;

    /// A slow source whose samples encode their `(step, sample)` and that counts its calls.
    struct Slow {
        calls: Arc<AtomicU64>,
    }

    impl BatchSource for Slow {
        fn samples(&self, step: u64, first: u64, count: usize) -> Result<Samples, SampleError> {
            self.calls.fetch_add(1, Ordering::SeqCst);
            std::thread::sleep(Duration::from_millis(5));
            let image = |v: u64| Image {
                height: 1,
                width: 1,
                pixels: vec![v as f32; 3],
            };
            Ok(Samples::Pairs(
                (first..first + count as u64)
                    .map(|s| (image(step * 1000 + s), image(0)))
                    .collect(),
            ))
        }
    }

    fn first_values(samples: Samples) -> Vec<f32> {
        match samples {
            Samples::Pairs(pairs) => pairs.iter().map(|(a, _)| a.pixels[0]).collect(),
            Samples::Views(_) => Vec::new(),
        }
    }

    #[test]
    fn serves_the_same_samples_in_order_with_a_bounded_queue() {
        let calls = Arc::new(AtomicU64::new(0));
        let schedule = Schedule {
            start_step: 3,
            first_sample: 0,
            global_batch: 8,
            micro_batch: 4,
        };
        let source = Prefetched::new(
            Slow {
                calls: Arc::clone(&calls),
            },
            schedule,
            3,
            2,
        );
        for step in 3..7u64 {
            for first in [0u64, 4] {
                let expected: Vec<f32> = (first..first + 4)
                    .map(|s| (step * 1000 + s) as f32)
                    .collect();
                assert_eq!(
                    first_values(source.samples(step, first, 4).unwrap()),
                    expected
                );
                let consumed = (step - 3) * 2 + first / 4 + 1;
                assert!(calls.load(Ordering::SeqCst) <= consumed + 3 + 2);
            }
        }
        std::thread::sleep(Duration::from_millis(50));
        assert!(source.queued() <= 3);
        // Out-of-plan requests still work (a resumed run asking for an earlier step).
        assert_eq!(first_values(source.samples(1, 0, 4).unwrap())[0], 1000.0);
    }

    #[test]
    fn a_rank_prefetches_only_its_slice_of_the_batch() {
        let calls = Arc::new(AtomicU64::new(0));
        let schedule = Schedule {
            start_step: 0,
            first_sample: 6,
            global_batch: 6,
            micro_batch: 3,
        };
        let source = Prefetched::new(
            Slow {
                calls: Arc::clone(&calls),
            },
            schedule,
            2,
            1,
        );
        for step in 0..3u64 {
            for first in [6u64, 9] {
                let values = first_values(source.samples(step, first, 3).unwrap());
                assert_eq!(values[0], (step * 1000 + first) as f32);
            }
        }
        std::thread::sleep(Duration::from_millis(50));
        assert_eq!(source.queued(), 2, "the queue holds the next step's slice");
        assert!(calls.load(Ordering::SeqCst) <= 6 + 2);
    }
}
