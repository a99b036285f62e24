//! The coordinator's side of the checkpoint store: the job state (`job.json`), verification of
//! committed checkpoints against their manifest, and the loss curves.

use data::store::{DataRoot, ObjectVersion, StoreError};
use settings::commit::{CommitManifest, MANIFEST_NAME, ManifestError};
use tokio::sync::Mutex;

use super::ServeError;
use crate::job::Durable;
pub use telemetry::logging::chain;

/// Name of the job-state object under the checkpoint URI.
pub const DURABLE_OBJECT: &str = "job.json";

/// Reads the job state a previous coordinator left, with the version [`write_durable`] must
/// name to replace it. Only a missing `job.json` means a new job: a store that cannot be read,
/// or a file that is not a job state, stops the start, so a committed result is never
/// orphaned by starting over.
pub async fn read_durable(
    checkpoints: &DataRoot,
    job: &str,
) -> Result<Option<(Durable, ObjectVersion)>, ServeError> {
    let uri = checkpoints.uri().to_string();
    let (bytes, version) = match checkpoints.read_versioned(DURABLE_OBJECT).await {
        Ok(read) => read,
        Err(StoreError::NotFound { .. }) => return Ok(None),
        Err(source) => return Err(ServeError::ReadState { uri, source }),
    };
    let durable: Durable =
        serde_json::from_slice(&bytes).map_err(|source| ServeError::CorruptState {
            uri: uri.clone(),
            source,
        })?;
    if durable.job != job {
        return Err(ServeError::OtherJob {
            uri,
            found: durable.job,
            expected: job.to_string(),
        });
    }
    Ok(Some((durable, version)))
}

/// Why `job.json` was not written.
#[derive(Debug, thiserror::Error)]
pub enum DurableWriteError {
    /// Another writer replaced or created `job.json` after this coordinator last read or wrote
    /// it: most likely a second coordinator runs on the same checkpoint URI.
    #[error(
        "{uri}/{DURABLE_OBJECT} was changed by another writer since this coordinator last read or wrote it; not overwritten (is a second coordinator using this checkpoint.uri?)"
    )]
    Stale {
        /// The checkpoint URI.
        uri: String,
        /// The store's refusal.
        #[source]
        source: StoreError,
    },
    /// The store could not be written.
    #[error("{uri}/{DURABLE_OBJECT} could not be written")]
    Store {
        /// The checkpoint URI.
        uri: String,
        /// What failed.
        #[source]
        source: StoreError,
    },
    /// The state did not serialise (not expected of plain data).
    #[error("the job state does not serialise")]
    Encode(#[source] serde_json::Error),
}

/// Writes `durable` as `job.json`, on the condition that the object is still the version in
/// `version` (absent when `None`), and records the new version there. The lock is held across
/// the write, so this process's writes are ordered; another process's write in between makes
/// this one fail with [`DurableWriteError::Stale`] instead of silently replacing it.
pub async fn write_durable(
    checkpoints: &DataRoot,
    durable: &Durable,
    version: &Mutex<Option<ObjectVersion>>,
) -> Result<(), DurableWriteError> {
    write_durable_held(checkpoints, durable, &mut *version.lock().await).await
}

/// [`write_durable`] for a caller that holds the version's lock already, so that no other
/// write of `job.json` comes between what it read and what it writes.
pub async fn write_durable_held(
    checkpoints: &DataRoot,
    durable: &Durable,
    held: &mut Option<ObjectVersion>,
) -> Result<(), DurableWriteError> {
    let json = serde_json::to_vec_pretty(durable).map_err(DurableWriteError::Encode)?;
    let uri = checkpoints.uri().to_string();
    let written = checkpoints
        .write_if(DURABLE_OBJECT, json, held.as_ref())
        .await
        .map_err(|source| match source {
            StoreError::Changed { .. } => DurableWriteError::Stale { uri, source },
            source => DurableWriteError::Store { uri, source },
        })?;
    *held = Some(written);
    Ok(())
}

/// Why a commit was refused after checking the store.
#[derive(Debug, thiserror::Error)]
pub enum CommitCheck {
    /// The location or its manifest could not be read.
    #[error("{location}: manifest unreadable")]
    Unreadable {
        /// The commit's location.
        location: String,
        /// What failed.
        #[source]
        source: StoreError,
    },
    /// The manifest is not one.
    #[error("{location}/{MANIFEST_NAME} is not a commit manifest")]
    Malformed {
        /// The commit's location.
        location: String,
        /// The parser's error.
        #[source]
        source: serde_json::Error,
    },
    /// The manifest names a file outside the checkpoint, or one twice.
    #[error("{location}: refused")]
    Unsafe {
        /// The commit's location.
        location: String,
        /// What is wrong with it.
        #[source]
        source: ManifestError,
    },
    /// A listed file is absent.
    #[error("{location}/{name} is missing")]
    Missing {
        /// The commit's location.
        location: String,
        /// The file.
        name: String,
    },
    /// A listed file has another size.
    #[error("{location}/{name} holds {found} bytes, {MANIFEST_NAME} says {expected}")]
    Size {
        /// The commit's location.
        location: String,
        /// The file.
        name: String,
        /// Its size in the store.
        found: u64,
        /// Its size in the manifest.
        expected: u64,
    },
}

/// Checks that every file a checkpoint's manifest lists exists with its size.
pub async fn verify(location: &str) -> Result<CommitManifest, CommitCheck> {
    let unreadable = |source| CommitCheck::Unreadable {
        location: location.to_string(),
        source,
    };
    let root = DataRoot::open(location).map_err(unreadable)?;
    let bytes = root.read(MANIFEST_NAME).await.map_err(unreadable)?;
    let manifest: CommitManifest =
        serde_json::from_slice(&bytes).map_err(|source| CommitCheck::Malformed {
            location: location.to_string(),
            source,
        })?;
    manifest.validate().map_err(|source| CommitCheck::Unsafe {
        location: location.to_string(),
        source,
    })?;
    let listed = root.list().await.map_err(unreadable)?;
    for file in &manifest.files {
        match listed.iter().find(|l| l.path == file.name) {
            Some(found) if found.size == file.bytes => {}
            Some(found) => {
                return Err(CommitCheck::Size {
                    location: location.to_string(),
                    name: file.name.clone(),
                    found: found.size,
                    expected: file.bytes,
                });
            }
            None => {
                return Err(CommitCheck::Missing {
                    location: location.to_string(),
                    name: file.name.clone(),
                });
            }
        }
    }
    Ok(manifest)
}
