//! The data of one training stage as a job describes it, and the batch source one
//! data-parallel rank reads from it.
//!
//! A stored dataset is sharded by sequence: every epoch, [`shard_sequences`] gives each rank a
//! disjoint set of sequences, and the rank draws its samples from those. Generated scenes are
//! rendered identically by every rank and drawn by global sample index, so any split of the
//! global batch across ranks trains on the same samples.

use std::sync::{Arc, Mutex};

use settings::data::{DataSource, DataSpec, DatasetKind, StoredDataset};

use crate::batch::{BatchSource, SampleError, Samples};
use crate::cache::{CacheError, read_cached};
use crate::manifest::{Manifest, Split};
use crate::scenes::SceneConfig;
use crate::shard::shard_sequences;
use crate::source::{DatasetSource, IndexedDataset};
use crate::split::{SplitError, read_split_file};
use crate::store::{DataRoot, StoreError};
use crate::synthetic::SyntheticDataset;

/// Why a rank could not open its data.
#[derive(Debug, thiserror::Error)]
pub enum SpecError {
    /// A root could not be opened.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A manifest cache was missing, corrupt or stale.
    #[error(transparent)]
    Cache(#[from] CacheError),
    /// A dataset's split file could not be read or parsed.
    #[error(transparent)]
    Split(#[from] SplitError),
    /// No training sequences.
    #[error("the job's datasets hold no training sequences")]
    NoTrainingSequences,
}

/// Train-split sequences of every stored dataset, read from the manifest caches.
pub async fn training_manifests(
    datasets: &[StoredDataset],
) -> Result<Vec<(DatasetKind, DataRoot, Manifest)>, SpecError> {
    let mut manifests = Vec::new();
    for dataset in datasets {
        let root = DataRoot::open(&dataset.uri)?;
        let mut manifest = read_cached(&root, dataset.kind, dataset.fingerprint).await?;
        if let Some(name) = &dataset.split_file {
            read_split_file(&root, name).await?.apply(&mut manifest);
        }
        manifest.sequences.retain(|s| s.split == Split::Train);
        manifests.push((dataset.kind, root, manifest));
    }
    Ok(manifests)
}

/// Global samples `(first, count)` of `rank` among `world_size` ranks: contiguous, sizes
/// differing by at most one, together exactly the global batch.
pub fn rank_slice(global_batch: usize, world_size: usize, rank: usize) -> (u64, usize) {
    let world_size = world_size.max(1);
    let begin = rank * global_batch / world_size;
    let end = (rank + 1) * global_batch / world_size;
    (begin as u64, end - begin)
}

/// Steps per epoch: enough that the global batch draws about one sample per sequence.
pub fn steps_per_epoch(sequences: usize, global_batch: usize) -> u64 {
    sequences.div_ceil(global_batch.max(1)).max(1) as u64
}

/// Sequence ids (`dataset/id`) of `rank`'s shard in `epoch`, over the concatenated manifests.
pub fn shard_ids(
    manifests: &[(DatasetKind, DataRoot, Manifest)],
    world_size: usize,
    rank: usize,
    seed: u64,
    epoch: u64,
) -> Vec<String> {
    let all: Vec<(DatasetKind, &str, usize)> = manifests
        .iter()
        .flat_map(|(kind, _, m)| {
            m.sequences
                .iter()
                .map(move |s| (*kind, s.id.as_str(), s.frames.len()))
        })
        .collect();
    let counts: Vec<usize> = all.iter().map(|(_, _, frames)| *frames).collect();
    let shards = shard_sequences(&counts, world_size, seed, epoch);
    shards
        .get(rank)
        .map(|shard| {
            shard
                .iter()
                .map(|&i| format!("{}/{}", all[i].0.name(), all[i].1))
                .collect()
        })
        .unwrap_or_default()
}

/// The batch source of one rank.
pub struct RankSource {
    inner: RankData,
}

enum RankData {
    Generated(SyntheticDataset),
    Stored(StoredShards),
}

struct StoredShards {
    manifests: Vec<(DatasetKind, DataRoot, Manifest)>,
    spec: DataSpec,
    world_size: usize,
    rank: usize,
    epoch_steps: u64,
    current: Mutex<Option<(u64, Arc<DatasetSource>)>>,
    skipped_before: std::sync::atomic::AtomicU64,
}

impl RankSource {
    /// Opens `spec` for `rank` of `world_size`. Generated scenes are rendered here (every rank
    /// renders the same ones); stored datasets read their manifest caches.
    pub async fn open(spec: &DataSpec, world_size: usize, rank: usize) -> Result<Self, SpecError> {
        let inner = match &spec.source {
            DataSource::Generated {
                scenes,
                trajectories,
                frames,
            } => {
                let scene = SceneConfig {
                    image_size: spec.image_size,
                    ..SceneConfig::default()
                };
                let mut dataset =
                    SyntheticDataset::generate(spec.seed, *scenes, *trajectories, *frames, &scene);
                dataset.views = spec.sampler.frames;
                RankData::Generated(dataset)
            }
            DataSource::Stored(datasets) => {
                let manifests = training_manifests(datasets).await?;
                let sequences: usize = manifests.iter().map(|(_, _, m)| m.sequences.len()).sum();
                if sequences == 0 {
                    return Err(SpecError::NoTrainingSequences);
                }
                RankData::Stored(StoredShards {
                    epoch_steps: steps_per_epoch(sequences, spec.global_batch),
                    manifests,
                    spec: spec.clone(),
                    world_size,
                    rank,
                    current: Mutex::new(None),
                    skipped_before: Default::default(),
                })
            }
        };
        Ok(Self { inner })
    }

    /// Sequence ids of this rank's shard in the epoch of `step` (empty for generated scenes,
    /// which are not sharded).
    pub fn shard_at(&self, step: u64) -> Vec<String> {
        match &self.inner {
            RankData::Generated(_) => Vec::new(),
            RankData::Stored(stored) => shard_ids(
                &stored.manifests,
                stored.world_size,
                stored.rank,
                stored.spec.seed,
                step / stored.epoch_steps,
            ),
        }
    }

    /// The newest skipped frames of the current epoch's loader, `dataset path: why`.
    pub fn skipped_examples(&self) -> Vec<String> {
        match &self.inner {
            RankData::Generated(_) => Vec::new(),
            RankData::Stored(stored) => stored
                .current
                .lock()
                .map(|c| {
                    c.as_ref()
                        .map_or_else(Vec::new, |(_, s)| s.skipped_examples())
                })
                .unwrap_or_default(),
        }
    }

    /// Frames skipped as corrupt, missing or unreadable so far.
    pub fn skipped_frames(&self) -> u64 {
        match &self.inner {
            RankData::Generated(_) => 0,
            RankData::Stored(stored) => {
                let current = stored
                    .current
                    .lock()
                    .map(|c| c.as_ref().map_or(0, |(_, s)| s.skipped_frames()))
                    .unwrap_or(0);
                stored
                    .skipped_before
                    .load(std::sync::atomic::Ordering::Relaxed)
                    + current
            }
        }
    }
}

impl StoredShards {
    /// The loader over this rank's shard of `epoch`, built on first use.
    fn epoch_source(&self, epoch: u64) -> Result<Arc<DatasetSource>, SampleError> {
        let mut current = self
            .current
            .lock()
            .map_err(|_| SampleError::LoaderPoisoned)?;
        if let Some((loaded, source)) = current.as_ref()
            && *loaded == epoch
        {
            return Ok(source.clone());
        }
        if let Some((_, old)) = current.take() {
            self.skipped_before
                .fetch_add(old.skipped_frames(), std::sync::atomic::Ordering::Relaxed);
        }
        let ids: std::collections::HashSet<String> = shard_ids(
            &self.manifests,
            self.world_size,
            self.rank,
            self.spec.seed,
            epoch,
        )
        .into_iter()
        .collect();
        let datasets: Vec<IndexedDataset> = self
            .manifests
            .iter()
            .map(|(kind, root, manifest)| {
                let mut manifest = manifest.clone();
                manifest
                    .sequences
                    .retain(|s| ids.contains(&format!("{}/{}", kind.name(), s.id)));
                IndexedDataset {
                    kind: *kind,
                    root: root.clone(),
                    manifest,
                }
            })
            .filter(|d| !d.manifest.sequences.is_empty())
            .collect();
        let source = Arc::new(
            DatasetSource::new(
                datasets,
                self.spec.sampler.clone(),
                Split::Train,
                self.spec.image_size,
                self.spec.seed,
            )
            .map_err(|source| SampleError::LoaderStart { epoch, source })?,
        );
        *current = Some((epoch, source.clone()));
        Ok(source)
    }
}

impl BatchSource for RankSource {
    fn samples(&self, step: u64, first_sample: u64, count: usize) -> Result<Samples, SampleError> {
        match &self.inner {
            RankData::Generated(dataset) => dataset.samples(step, first_sample, count),
            RankData::Stored(stored) => {
                stored
                    .epoch_source(step / stored.epoch_steps)?
                    .samples(step, first_sample, count)
            }
        }
    }
}
