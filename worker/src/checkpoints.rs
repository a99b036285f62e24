//! Moving checkpoint directories to and from the object store, and committing them. A
//! checkpoint is complete only once its `COMMIT.json` (file names and sizes) exists, and that
//! file is written last; the coordinator verifies it before accepting the commit.

use std::path::Path;
use std::time::Duration;

use anyhow::{anyhow, bail};
use data::store::{DataRoot, StoreError};
use proto::convert::phase_to_wire;
use proto::v1::CheckpointCommit;
use settings::Phase;
use settings::commit::{CommitFile, CommitManifest, MANIFEST_NAME};
use tokio::runtime::Runtime;

use crate::session::{Client, Progress};

/// Uploads every file of `dir` under `location`, then `COMMIT.json`.
pub async fn upload(dir: &Path, location: &str, phase: Phase, step: u64) -> anyhow::Result<()> {
    let root = DataRoot::create(location)?;
    let mut files = Vec::new();
    let mut entries: Vec<_> = std::fs::read_dir(dir)?.collect::<Result<_, _>>()?;
    entries.sort_by_key(|e| e.file_name());
    for entry in entries {
        let name = entry.file_name().to_string_lossy().into_owned();
        let bytes = std::fs::read(entry.path())?;
        files.push(CommitFile {
            name: name.clone(),
            bytes: bytes.len() as u64,
            crc32: Some(crc32fast::hash(&bytes)),
        });
        root.write(&name, bytes).await?;
    }
    let manifest = CommitManifest { phase, step, files };
    root.write(MANIFEST_NAME, serde_json::to_vec_pretty(&manifest)?)
        .await?;
    Ok(())
}

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

/// Downloads the committed checkpoint at `location` into `dir`; fails when it has no
/// `COMMIT.json`, the manifest names a file outside the checkpoint, or a file's size or CRC-32
/// differs from it. A checkpoint that is there but does not verify fails with
/// [`CorruptCheckpoint`]; a store that cannot be reached, with its own error.
pub async fn download(location: &str, dir: &Path) -> anyhow::Result<CommitManifest> {
    let corrupt = |reason: String| CorruptCheckpoint {
        location: location.to_string(),
        reason,
    };
    let root = DataRoot::open(location)?;
    let manifest: CommitManifest = serde_json::from_slice(&root.read(MANIFEST_NAME).await?)
        .map_err(|e| corrupt(format!("{MANIFEST_NAME}: {e}")))?;
    manifest.validate().map_err(|e| corrupt(e.to_string()))?;
    std::fs::create_dir_all(dir)?;
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
        std::fs::write(dir.join(&file.name), bytes)?;
    }
    Ok(manifest)
}

/// Tries of a checkpoint upload before the generation fails (pauses of 1 s, 2 s between).
pub const UPLOAD_ATTEMPTS: u32 = 3;

/// What one commit uploads and where.
pub struct CommitRequest<'a> {
    /// The files to upload.
    pub dir: &'a Path,
    /// The URI prefix they go under.
    pub location: String,
    /// The phase that wrote them.
    pub phase: Phase,
    /// Steps done.
    pub step: u64,
    /// The generation committing.
    pub generation: u64,
}

/// Uploads `request.dir` with its manifest last (retried with back-off, [`UPLOAD_ATTEMPTS`] in
/// all), then asks the coordinator to commit it; fails when the upload keeps failing, the
/// commit fails or the coordinator refuses it. The caller's generation then fails, which it
/// reports, so the group re-forms from the last commit instead of waiting for this one.
pub fn commit(
    runtime: &Runtime,
    client: &mut Client,
    progress: &Progress,
    request: CommitRequest<'_>,
) -> anyhow::Result<()> {
    let location = request.location;
    let started = std::time::Instant::now();
    let mut attempt = 1;
    while let Err(error) =
        runtime.block_on(upload(request.dir, &location, request.phase, request.step))
    {
        if attempt >= UPLOAD_ATTEMPTS {
            return Err(error.context(format!(
                "uploading the checkpoint to {location} failed {attempt} times"
            )));
        }
        let pause = Duration::from_secs(1 << (attempt - 1));
        tracing::warn!(%location, attempt, error = %format!("{error:#}"), "checkpoint upload failed; retrying in {} s", pause.as_secs());
        std::thread::sleep(pause);
        attempt += 1;
    }
    let upload_s = started.elapsed().as_secs_f64();
    progress
        .metrics
        .observe(&crate::metrics::CHECKPOINT_UPLOAD, &[], upload_s);
    let ack = runtime
        .block_on(client.commit_checkpoint(CheckpointCommit {
            worker_id: progress.worker_id(),
            generation: request.generation,
            phase: phase_to_wire(request.phase) as i32,
            step: request.step,
            location: location.clone(),
            session: progress.session(),
        }))
        .map_err(|s| anyhow!("commit of {location} failed: {}", s.message()))?
        .into_inner();
    if !ack.accepted {
        bail!("commit of {location} refused: {}", ack.reason);
    }
    tracing::info!(%location, "committed");
    Ok(())
}
