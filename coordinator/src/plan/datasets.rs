//! Stored datasets resolved for a plan: each root opened, indexed through its manifest cache
//! (rebuilt only when the listing changed) and cut to its train sequences, so workers get the
//! fingerprints they check their own reads against and the dry run can show the shards.

use data::cache::{CacheUse, load_or_index};
use data::split::{SplitError, read_split_file};
use data::store::DataRoot;
use data::{DatasetKind, Manifest, Split};
use settings::data::{DataSource, StoredDataset};

use super::PlanError;
use crate::config::DatasetConfig;

/// One stored dataset's train sequences with its kind and root, the shape the sharding
/// functions of `data::spec` take.
pub(super) type TrainManifest = (DatasetKind, DataRoot, Manifest);

/// Indexes every dataset of the YAML list in order: the source workers are sent, and the train
/// sequences of each for the shard summary.
pub(super) async fn index_datasets(
    datasets: &[DatasetConfig],
) -> Result<(DataSource, Vec<TrainManifest>), PlanError> {
    let mut stored = Vec::with_capacity(datasets.len());
    let mut manifests = Vec::with_capacity(datasets.len());
    for (index, dataset) in datasets.iter().enumerate() {
        let (entry, manifest) = index_dataset(index, dataset).await?;
        stored.push(entry);
        manifests.push(manifest);
    }
    Ok((DataSource::Stored(stored), manifests))
}

/// Opens and indexes dataset `index` of the list; an error names its position, kind and root.
async fn index_dataset(
    index: usize,
    dataset: &DatasetConfig,
) -> Result<(StoredDataset, TrainManifest), PlanError> {
    let (kind, uri) = (dataset.kind.name(), dataset.uri.0.clone());
    let root = DataRoot::open(&uri).map_err(|source| PlanError::Open {
        index,
        kind,
        uri: uri.clone(),
        source,
    })?;
    let (cached, used) =
        load_or_index(&root, dataset.kind)
            .await
            .map_err(|source| PlanError::Index {
                index,
                kind,
                uri: uri.clone(),
                source,
            })?;
    tracing::info!(
        dataset = kind,
        uri = %uri,
        sequences = cached.manifest.sequences.len(),
        cache = if used == CacheUse::Reused { "reused" } else { "rebuilt" },
        "indexed"
    );
    let split_file = dataset.split_file.as_ref().map(|name| name.0.clone());
    let train = train_sequences(&root, &cached.manifest, split_file.as_deref())
        .await
        .map_err(|source| PlanError::Split {
            index,
            kind,
            uri: uri.clone(),
            source,
        })?;
    let entry = StoredDataset {
        kind: dataset.kind,
        uri,
        fingerprint: cached.fingerprint,
        split_file,
    };
    Ok((entry, (dataset.kind, root, train)))
}

/// The manifest's train sequences: by the paper's split file when one is named (it decides
/// which sequences train, overriding the layout's own train/test rule), else by the layout.
async fn train_sequences(
    root: &DataRoot,
    manifest: &Manifest,
    split_file: Option<&str>,
) -> Result<Manifest, SplitError> {
    let mut train = manifest.clone();
    if let Some(name) = split_file {
        read_split_file(root, name).await?.apply(&mut train);
    }
    train.sequences.retain(|s| s.split == Split::Train);
    Ok(train)
}
