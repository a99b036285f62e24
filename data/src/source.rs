//! A training [`BatchSource`] over indexed datasets: the mixture picks a dataset, a sequence is
//! drawn uniformly, the window sampler picks frames, and the frames are read (concurrently,
//! each object once) and decoded. A corrupt frame is skipped, logged with its path and counted,
//! and the sample is redrawn from the next sub-stream, so results stay deterministic.

use std::sync::atomic::{AtomicU64, Ordering};

use futures::future::try_join_all;

use crate::decode::decode_frame;
use settings::data::{DatasetKind, SamplerConfig};

use crate::batch::Image;
use crate::batch::{BatchSource, Samples};
use crate::manifest::{Manifest, Split};
use crate::rng::Stream;
use crate::sampler::WindowSampler;
use crate::store::DataRoot;

/// Tag of the sampling streams.
const SOURCE_STREAM: u64 = 0x0044_4154_4153;
/// Redraws allowed per sample before giving up (only reached when most frames are corrupt).
const MAX_REDRAWS: u64 = 16;

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
        })
    }

    /// Frames skipped so far because they could not be decoded.
    pub fn skipped_frames(&self) -> u64 {
        self.skipped_frames.load(Ordering::Relaxed)
    }

    /// `(frame index, image)` of every frame of global sample `sample` at `step`.
    pub fn sample(&self, step: u64, sample: u64) -> Result<Vec<(u64, Image)>, String> {
        let available: Vec<DatasetKind> = self
            .datasets
            .iter()
            .filter(|d| d.manifest.sequences.iter().any(|s| s.split == self.split))
            .map(|d| d.kind)
            .collect();
        for redraw in 0..MAX_REDRAWS {
            let mut stream = Stream::new(&[self.seed, SOURCE_STREAM, step, sample, redraw]);
            let kind = self
                .sampler
                .choose_dataset(&available, &mut stream)
                .ok_or_else(|| format!("no dataset has {:?} sequences to sample", self.split))?;
            let dataset = self
                .datasets
                .iter()
                .find(|d| d.kind == kind)
                .ok_or_else(|| format!("dataset {} is not configured", kind.name()))?;
            let settings = self
                .sampler
                .dataset(kind)
                .ok_or_else(|| format!("dataset {} has no sampler settings", kind.name()))?;
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
            let bytes = self
                .runtime
                .block_on(try_join_all(paths.iter().map(|p| dataset.root.read(p))))
                .map_err(|e| e.to_string())?;
            let decoded: Result<Vec<Image>, _> = bytes
                .iter()
                .zip(&paths)
                .map(|(data, path)| decode_frame(data, path, self.image_size))
                .collect();
            match decoded {
                Ok(images) => {
                    return Ok(window
                        .frames
                        .iter()
                        .map(|&f| f as u64)
                        .zip(images)
                        .collect());
                }
                Err(error) => {
                    self.skipped_frames.fetch_add(1, Ordering::Relaxed);
                    tracing::warn!(uri = dataset.root.uri(), %error, "skipping corrupt frame");
                }
            }
        }
        Err(format!(
            "step {step} sample {sample}: no decodable frames after {MAX_REDRAWS} draws"
        ))
    }
}

impl BatchSource for DatasetSource {
    fn samples(&self, step: u64, first_sample: u64, count: usize) -> Result<Samples, String> {
        let samples: Vec<Vec<(u64, Image)>> = (first_sample..first_sample + count as u64)
            .map(|sample| self.sample(step, sample))
            .collect::<Result<_, _>>()?;
        if self.sampler.frames == 2 {
            return Ok(Samples::Pairs(
                samples
                    .into_iter()
                    .map(|mut frames| {
                        let second = frames.pop().map(|(_, image)| image);
                        let first = frames.pop().map(|(_, image)| image);
                        first
                            .zip(second)
                            .ok_or_else(|| "a pair needs two frames".to_string())
                    })
                    .collect::<Result<_, _>>()?,
            ));
        }
        Ok(Samples::Views(samples))
    }
}
