//! Manifests cached next to the data: `.xfactor/manifest-<dataset>.json` under the dataset
//! root, stamped with a fingerprint of the listing it was built from.
//!
//! The coordinator lists the root once per job, rebuilds the cache only when the listing's
//! fingerprint changed, and hands the fingerprint to the workers; a worker then reads one small
//! object instead of listing millions, and refuses a cache that does not carry that fingerprint
//! (it would shard a different set of sequences than its peers).

use serde::{Deserialize, Serialize};

use crate::index::{CACHE_DIR, IndexError, check_indexed, index_paths};
use settings::data::{DatasetKind, ListingFingerprint};

use crate::manifest::Manifest;
use crate::store::{DataRoot, Listed, StoreError};

/// The fingerprint of a listing (sorted by path, as [`DataRoot::list`] returns it).
pub fn fingerprint(listing: &[Listed]) -> ListingFingerprint {
    let mut crc = crc32fast::Hasher::new();
    for object in listing {
        crc.update(object.path.as_bytes());
        crc.update(b"\n");
    }
    ListingFingerprint {
        objects: listing.len() as u64,
        bytes: listing.iter().map(|l| l.size).sum(),
        newest: listing.iter().map(|l| l.modified).max().unwrap_or(0),
        paths_crc: crc.finalize(),
    }
}

/// The cached form: a manifest and the listing it came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CachedManifest {
    /// The listing the manifest was built from.
    pub fingerprint: ListingFingerprint,
    /// Sequences that passed the dataset's rules.
    pub manifest: Manifest,
}

/// Why a cached manifest could not be used or written.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    /// Listing, reading or writing failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// Indexing found nothing usable.
    #[error(transparent)]
    Index(#[from] IndexError),
    /// The cache file is not a manifest.
    #[error("{uri}/{path}: not a manifest cache")]
    Corrupt {
        /// Dataset root.
        uri: String,
        /// The cache object.
        path: String,
        /// What failed to parse.
        #[source]
        source: serde_json::Error,
    },
    /// The cache describes another listing than the one expected.
    #[error(
        "{uri}/{path} was built from a different listing ({found:?}) than the coordinator's ({expected:?}); the data changed during the job"
    )]
    Stale {
        /// Dataset root.
        uri: String,
        /// The cache object.
        path: String,
        /// The fingerprint asked for.
        expected: ListingFingerprint,
        /// The cache's.
        found: ListingFingerprint,
    },
}

/// Object path of `dataset`'s cache under its root.
pub fn cache_path(dataset: DatasetKind) -> String {
    format!("{CACHE_DIR}/manifest-{}.json", dataset.name())
}

/// Whether the cache was (re)built or reused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CacheUse {
    /// The cached manifest matched the listing.
    Reused,
    /// The cache was missing, unreadable or stale, and was rebuilt.
    Rebuilt,
}

/// Lists `root`, reuses its cached manifest when the listing is unchanged, and otherwise
/// indexes the listing and rewrites the cache.
pub async fn load_or_index(
    root: &DataRoot,
    dataset: DatasetKind,
) -> Result<(CachedManifest, CacheUse), CacheError> {
    let path = cache_path(dataset);
    let listing: Vec<Listed> = root
        .list()
        .await?
        .into_iter()
        .filter(|l| !l.path.starts_with(CACHE_DIR))
        .collect();
    let fingerprint = fingerprint(&listing);
    if listing.iter().all(|l| l.path != path)
        && let Ok(bytes) = root.read(&path).await
        && let Ok(cached) = serde_json::from_slice::<CachedManifest>(&bytes)
        && cached.fingerprint == fingerprint
    {
        return Ok((cached, CacheUse::Reused));
    }
    let paths: Vec<&str> = listing.iter().map(|l| l.path.as_str()).collect();
    let indexed = check_indexed(root, dataset, &paths, index_paths(dataset, &paths))?;
    let cached = CachedManifest {
        fingerprint,
        manifest: indexed.manifest,
    };
    let json = serde_json::to_vec(&cached).map_err(|e| CacheError::Corrupt {
        uri: root.uri().to_string(),
        path: path.clone(),
        source: e,
    })?;
    root.write(&path, json).await?;
    Ok((cached, CacheUse::Rebuilt))
}

/// Reads the cached manifest of `dataset` and checks it was built from the listing `expected`.
pub async fn read_cached(
    root: &DataRoot,
    dataset: DatasetKind,
    expected: ListingFingerprint,
) -> Result<Manifest, CacheError> {
    let path = cache_path(dataset);
    let bytes = root.read(&path).await?;
    let cached: CachedManifest =
        serde_json::from_slice(&bytes).map_err(|e| CacheError::Corrupt {
            uri: root.uri().to_string(),
            path: path.clone(),
            source: e,
        })?;
    if cached.fingerprint != expected {
        return Err(CacheError::Stale {
            uri: root.uri().to_string(),
            path,
            expected,
            found: cached.fingerprint,
        });
    }
    Ok(cached.manifest)
}
