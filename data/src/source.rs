//! A training [`BatchSource`] over indexed datasets: the mixture picks a dataset, a sequence is
//! drawn uniformly, the window sampler picks frames, and the frames are read (concurrently,
//! each object once) and decoded. A frame that is corrupt, missing (deleted after indexing) or
//! unreadable is skipped, logged with its path and counted, and the sample is redrawn from the
//! next sub-stream, so results stay deterministic. The newest few skipped frames are kept as
//! examples for the job's report.

use std::collections::VecDeque;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use futures::future::join_all;

use crate::decode::decode_frame;
use settings::data::{DatasetKind, SamplerConfig};

use crate::batch::{BatchSource, FrameError, SampleError, Samples};
use crate::frame::Image;
use crate::manifest::{Manifest, Split};
use crate::rng::Stream;
use crate::sampler::WindowSampler;
use crate::store::DataRoot;

/// Tag of the sampling streams.
const SOURCE_STREAM: u64 = 0x0044_4154_4153;
/// Redraws allowed per sample before giving up (only reached when most frames are corrupt).
const MAX_REDRAWS: u64 = 16;
/// Skipped frames kept as examples.
pub const SKIPPED_EXAMPLES: usize = 8;

/// One indexed dataset and where it lives.
#[derive(Debug, Clone)]
pub struct IndexedDataset {
    /// Which dataset.
    pub kind: DatasetKind,
    /// Its root.
    pub root: DataRoot,
    /// Its sequences (only those of the wanted split are sampled).
    pub manifest: Manifest,
}

/// Samples for training from several indexed datasets.
pub struct DatasetSource {
    datasets: Vec<IndexedDataset>,
    sampler: SamplerConfig,
    split: Split,
    image_size: usize,
    seed: u64,
    runtime: tokio::runtime::Runtime,
    skipped_frames: AtomicU64,
    skipped_examples: Mutex<VecDeque<String>>,
}

impl DatasetSource {
    /// Builds a source; `image_size` is the training resolution.
    pub fn new(
        datasets: Vec<IndexedDataset>,
        sampler: SamplerConfig,
        split: Split,
        image_size: usize,
        seed: u64,
    ) -> std::io::Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        Ok(Self {
            datasets,
            sampler,
            split,
            image_size,
            seed,
            runtime,
            skipped_frames: AtomicU64::new(0),
            skipped_examples: Mutex::new(VecDeque::new()),
        })
    }

    /// Frames skipped so far because they were corrupt, missing or unreadable.
    pub fn skipped_frames(&self) -> u64 {
        self.skipped_frames.load(Ordering::Relaxed)
    }

    /// The newest skipped frames, `dataset uri/path: why`.
    pub fn skipped_examples(&self) -> Vec<String> {
        self.skipped_examples
            .lock()
            .map(|examples| examples.iter().cloned().collect())
            .unwrap_or_default()
    }

    fn skip(&self, dataset: &IndexedDataset, path: &str, why: &dyn std::error::Error) {
        self.skipped_frames.fetch_add(1, Ordering::Relaxed);
        let mut reason = why.to_string();
        let mut cause = why.source();
        while let Some(next) = cause {
            reason = format!("{reason}: {next}");
            cause = next.source();
        }
        tracing::warn!(dataset = dataset.kind.name(), uri = dataset.root.uri(), path, %reason, "skipping frame");
        if let Ok(mut examples) = self.skipped_examples.lock() {
            if examples.len() == SKIPPED_EXAMPLES {
                examples.pop_front();
            }
            examples.push_back(format!("{} {path}: {reason}", dataset.kind.name()));
        }
    }

    /// `(frame index, image)` of every frame of global sample `sample` at `step`.
    pub fn sample(&self, step: u64, sample: u64) -> Result<Vec<(u64, Image)>, SampleError> {
        let available: Vec<DatasetKind> = self
            .datasets
            .iter()
            .filter(|d| d.manifest.sequences.iter().any(|s| s.split == self.split))
            .map(|d| d.kind)
            .collect();
        let mut last_unusable = None;
        for redraw in 0..MAX_REDRAWS {
            let mut stream = Stream::new(&[self.seed, SOURCE_STREAM, step, sample, redraw]);
            let kind = self
                .sampler
                .choose_dataset(&available, &mut stream)
                .ok_or(SampleError::NoSequences { split: self.split })?;
            let dataset = self
                .datasets
                .iter()
                .find(|d| d.kind == kind)
                .ok_or(SampleError::DatasetNotConfigured { dataset: kind })?;
            let settings = self
                .sampler
                .dataset(kind)
                .ok_or(SampleError::NoSamplerSettings { dataset: kind })?;
            let sequences: Vec<_> = dataset
                .manifest
                .sequences
                .iter()
                .filter(|s| s.split == self.split)
                .collect();
            let sequence = sequences[stream.below(sequences.len() as u64) as usize];
            let Some(window) =
                self.sampler
                    .draw_window(settings, sequence.frames.len(), step, &mut stream)
            else {
                continue;
            };
            let paths: Vec<&str> = window
                .frames
                .iter()
                .map(|&f| sequence.frames[f].as_str())
                .collect();
            match self.read_frames(dataset, &paths) {
                Ok(images) => {
                    return Ok(window
                        .frames
                        .iter()
                        .map(|&f| f as u64)
                        .zip(images)
                        .collect());
                }
                Err(unusable) => last_unusable = Some(unusable),
            }
        }
        Err(SampleError::NoUsableFrames {
            step,
            sample,
            draws: MAX_REDRAWS,
            last: last_unusable,
        })
    }

    /// Reads the frames at `paths` of `dataset` (concurrently, each object once) and decodes
    /// them. The first frame that cannot be read or decoded is skipped (logged and counted) and
    /// returned, so the caller redraws the sample.
    fn read_frames(
        &self,
        dataset: &IndexedDataset,
        paths: &[&str],
    ) -> Result<Vec<Image>, FrameError> {
        let reads = self
            .runtime
            .block_on(join_all(paths.iter().map(|p| dataset.root.read(p))));
        reads
            .into_iter()
            .zip(paths)
            .map(|(read, path)| {
                read.map_err(FrameError::from)
                    .and_then(|bytes| {
                        decode_frame(&bytes, path, self.image_size).map_err(FrameError::from)
                    })
                    .inspect_err(|unusable| self.skip(dataset, path, unusable))
            })
            .collect()
    }
}

impl BatchSource for DatasetSource {
    fn samples(&self, step: u64, first_sample: u64, count: usize) -> Result<Samples, SampleError> {
        let samples: Vec<Vec<(u64, Image)>> = (first_sample..first_sample + count as u64)
            .map(|sample| self.sample(step, sample))
            .collect::<Result<_, _>>()?;
        if self.sampler.frames == 2 {
            return Ok(Samples::Pairs(
                samples
                    .into_iter()
                    .zip(first_sample..)
                    .map(|(mut frames, sample)| {
                        let held = frames.len();
                        let second = frames.pop().map(|(_, image)| image);
                        let first = frames.pop().map(|(_, image)| image);
                        first.zip(second).ok_or(SampleError::IncompletePair {
                            step,
                            sample,
                            frames: held,
                        })
                    })
                    .collect::<Result<_, _>>()?,
            ));
        }
        Ok(Samples::Views(samples))
    }
}
