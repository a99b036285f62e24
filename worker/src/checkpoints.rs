//! Moving checkpoint directories to and from the object store, and committing them. A
//! checkpoint is complete only once its `COMMIT.json` (file names, sizes and CRC-32s) exists, and that
//! file is written last; the coordinator verifies it before accepting the commit.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, anyhow, bail};
use data::store::{DataRoot, StoreError};
use proto::convert::phase_to_wire;
use proto::v1::CheckpointCommit;
use settings::Phase;
use settings::commit::{CommitFile, CommitManifest, MANIFEST_NAME};
use tokio::runtime::Runtime;

use crate::session::{Client, Progress};

/// Uploads `files` under `location`, then `COMMIT.json` with each one's size and CRC-32.
async fn upload(
    files: &[(String, Vec<u8>)],
    location: &str,
    mut manifest: CommitManifest,
) -> anyhow::Result<()> {
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
    /// The files to upload; read into memory when the commit starts, so the directory may be
    /// reused at once.
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

/// A commit in flight on the worker's runtime: its checkpoint uploading (retried with
/// back-off, [`UPLOAD_ATTEMPTS`] in all, `COMMIT.json` last), then the coordinator asked to
/// commit it. Rank 0 trains on meanwhile, so a slow store never holds its peers in the
/// all-reduce. Dropped unfinished (its generation failed), the upload is abandoned: without
/// `COMMIT.json` and never committed, what it wrote is not a checkpoint.
pub struct InFlightCommit {
    /// Where it goes.
    pub location: String,
    /// The step it saves.
    pub step: u64,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl InFlightCommit {
    /// Reads `request.dir` and starts uploading and committing it in the background.
    pub fn start(
        runtime: &Runtime,
        client: &Client,
        progress: &Progress,
        request: CommitRequest<'_>,
    ) -> anyhow::Result<Self> {
        let files = read_files(request.dir)?;
        let location = request.location;
        tracing::info!(%location, step = request.step, "uploading checkpoint");
        let mut client = client.clone();
        let metrics = Arc::clone(&progress.metrics);
        let commit = CheckpointCommit {
            worker_id: progress.worker_id(),
            generation: request.generation,
            phase: phase_to_wire(request.phase) as i32,
            step: request.step,
            location: location.clone(),
            session: progress.session(),
        };
        let manifest = CommitManifest {
            phase: request.phase,
            step: request.step,
            files: Vec::new(),
        };
        let task = runtime.spawn(async move {
            let started = std::time::Instant::now();
            upload_with_retries(&files, &commit.location, manifest).await?;
            metrics.observe(
                &crate::metrics::CHECKPOINT_UPLOAD,
                &[],
                started.elapsed().as_secs_f64(),
            );
            let location = commit.location.clone();
            let ack = client
                .commit_checkpoint(commit)
                .await
                .map_err(|s| anyhow!("commit of {location} failed: {}", s.message()))?
                .into_inner();
            if !ack.accepted {
                bail!("commit of {location} refused: {}", ack.reason);
            }
            tracing::info!(%location, "committed");
            Ok(())
        });
        Ok(Self {
            location,
            step: request.step,
            task,
        })
    }

    /// Whether it has ended, committed or failed.
    pub fn is_finished(&self) -> bool {
        self.task.is_finished()
    }

    /// Blocks until it ends; fails when the upload kept failing or the coordinator did not
    /// take the commit. The caller's generation then fails, which it reports, so the group
    /// re-forms from the last commit.
    pub fn wait(mut self, runtime: &Runtime) -> anyhow::Result<()> {
        let location = self.location.clone();
        runtime
            .block_on(&mut self.task)
            .map_err(|e| anyhow!("the commit of {location} did not run to its end: {e}"))?
    }
}

impl Drop for InFlightCommit {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Uploads `request.dir` and asks the coordinator to commit it, waiting for both.
pub fn commit(
    runtime: &Runtime,
    client: &Client,
    progress: &Progress,
    request: CommitRequest<'_>,
) -> anyhow::Result<()> {
    InFlightCommit::start(runtime, client, progress, request)?.wait(runtime)
}

fn read_files(dir: &Path) -> anyhow::Result<Vec<(String, Vec<u8>)>> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .with_context(|| format!("checkpoint directory {}", dir.display()))?
        .collect::<Result<_, _>>()?;
    entries.sort_by_key(|e| e.file_name());
    entries
        .into_iter()
        .map(|entry| {
            let name = entry.file_name().to_string_lossy().into_owned();
            let bytes = std::fs::read(entry.path())
                .with_context(|| format!("checkpoint file {}", entry.path().display()))?;
            Ok((name, bytes))
        })
        .collect()
}

async fn upload_with_retries(
    files: &[(String, Vec<u8>)],
    location: &str,
    manifest: CommitManifest,
) -> anyhow::Result<()> {
    let mut attempt = 1;
    loop {
        match upload(files, location, manifest.clone()).await {
            Ok(()) => return Ok(()),
            Err(error) if attempt >= UPLOAD_ATTEMPTS => {
                return Err(error.context(format!(
                    "uploading the checkpoint to {location} failed {attempt} times"
                )));
            }
            Err(error) => {
                let pause = Duration::from_secs(1 << (attempt - 1));
                tracing::warn!(%location, attempt, error = %format!("{error:#}"), "checkpoint upload failed; retrying in {} s", pause.as_secs());
                tokio::time::sleep(pause).await;
                attempt += 1;
            }
        }
    }
}
