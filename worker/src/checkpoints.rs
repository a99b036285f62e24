//! Moving checkpoint directories to and from the object store. A checkpoint is complete only
//! once its `COMMIT.json` (file names, sizes and CRC-32s) exists, and that file is written
//! last; a download verifies every file against it. Errors say whose fault a failure is: the
//! store's ([`TransferError::Store`]), the checkpoint's ([`TransferError::Corrupt`]) or this
//! machine's disk ([`TransferError::Local`]), because the coordinator acts differently on each.

use std::path::{Path, PathBuf};

use data::store::{DataRoot, StoreError};
use settings::commit::{CommitFile, CommitManifest, MANIFEST_NAME};

/// A committed checkpoint that does not verify: the store holds something other than what
/// its `COMMIT.json` says. The coordinator falls back to the commit before it.
#[derive(Debug, thiserror::Error)]
#[error("checkpoint {location} is corrupt: {reason}")]
pub struct CorruptCheckpoint {
    /// Where it is.
    pub location: String,
    /// What does not match.
    pub reason: String,
}

/// Why a checkpoint did not move.
#[derive(Debug, thiserror::Error)]
pub enum TransferError {
    /// The store could not be opened, read or written: the store's fault, not this worker's.
    #[error("the checkpoint store failed")]
    Store(#[from] StoreError),
    /// The checkpoint is there but does not verify.
    #[error(transparent)]
    Corrupt(#[from] CorruptCheckpoint),
    /// `COMMIT.json` could not be encoded.
    #[error("cannot encode {MANIFEST_NAME}")]
    Manifest(#[source] serde_json::Error),
    /// This machine's scratch disk failed.
    #[error("cannot {action} {}", path.display())]
    Local {
        /// `read`, `write` or `create`.
        action: &'static str,
        /// The local file or directory.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },
}

fn local(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> TransferError {
    let path = path.to_path_buf();
    move |source| TransferError::Local {
        action,
        path,
        source,
    }
}

/// Uploads `files` under `location`, then `COMMIT.json` with each one's size and CRC-32.
pub async fn upload(
    files: &[(String, Vec<u8>)],
    location: &str,
    mut manifest: CommitManifest,
) -> Result<(), TransferError> {
    let root = DataRoot::create(location)?;
    manifest.files.clear();
    for (name, bytes) in files {
        manifest.files.push(CommitFile {
            name: name.clone(),
            bytes: bytes.len() as u64,
            crc32: Some(crc32fast::hash(bytes)),
        });
        root.write(name, bytes.clone()).await?;
    }
    let manifest = serde_json::to_vec_pretty(&manifest).map_err(TransferError::Manifest)?;
    root.write(MANIFEST_NAME, manifest).await?;
    Ok(())
}

/// Downloads the committed checkpoint at `location` into `dir`; fails when it has no
/// `COMMIT.json`, the manifest names a file outside the checkpoint, or a file's size or CRC-32
/// differs from it. A checkpoint that is there but does not verify fails with
/// [`TransferError::Corrupt`]; a store that cannot be reached, with [`TransferError::Store`].
pub async fn download(location: &str, dir: &Path) -> Result<CommitManifest, TransferError> {
    let corrupt = |reason: String| CorruptCheckpoint {
        location: location.to_string(),
        reason,
    };
    let root = DataRoot::open(location)?;
    let manifest: CommitManifest = serde_json::from_slice(&root.read(MANIFEST_NAME).await?)
        .map_err(|e| corrupt(format!("{MANIFEST_NAME}: {e}")))?;
    manifest.validate().map_err(|e| corrupt(e.to_string()))?;
    std::fs::create_dir_all(dir).map_err(local("create", dir))?;
    for file in &manifest.files {
        let bytes = match root.read(&file.name).await {
            Ok(bytes) => bytes,
            Err(StoreError::NotFound { .. }) => {
                return Err(corrupt(format!("{} is missing", file.name)).into());
            }
            Err(error) => return Err(error.into()),
        };
        if bytes.len() as u64 != file.bytes {
            return Err(corrupt(format!(
                "{}: {} bytes, {MANIFEST_NAME} says {}",
                file.name,
                bytes.len(),
                file.bytes
            ))
            .into());
        }
        if let Some(expected) = file.crc32 {
            let found = crc32fast::hash(&bytes);
            if found != expected {
                return Err(corrupt(format!(
                    "{}: CRC-32 {found:08x}, {MANIFEST_NAME} says {expected:08x}: the file changed after it was committed",
                    file.name
                ))
                .into());
            }
        }
        let path = dir.join(&file.name);
        std::fs::write(&path, bytes).map_err(local("write", &path))?;
    }
    Ok(manifest)
}

/// The files of a checkpoint directory, sorted by name, read into memory so the directory may
/// be reused at once.
pub fn read_files(dir: &Path) -> Result<Vec<(String, Vec<u8>)>, TransferError> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .and_then(|entries| entries.collect::<Result<Vec<_>, _>>())
        .map_err(local("read", dir))?;
    entries.sort_by_key(|e| e.file_name());
    entries
        .into_iter()
        .map(|entry| {
            let name = entry.file_name().to_string_lossy().into_owned();
            let bytes = std::fs::read(entry.path()).map_err(local("read", &entry.path()))?;
            Ok((name, bytes))
        })
        .collect()
}

/// Empties `dir` for a new checkpoint; a directory that is not there is already empty.
pub fn clear(dir: &Path) -> Result<(), TransferError> {
    match std::fs::remove_dir_all(dir) {
        Err(error) if error.kind() != std::io::ErrorKind::NotFound => {
            Err(local("clear", dir)(error))
        }
        _ => Ok(()),
    }
}
