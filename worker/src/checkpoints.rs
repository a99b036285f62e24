//! Moving checkpoint directories to and from the object store. A checkpoint is complete only
//! once its `COMMIT.json` (file names and sizes) exists, and that file is written last.

use std::path::Path;

use serde::{Deserialize, Serialize};
use trainer_core::data::store::DataRoot;

/// The manifest written last into a checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CommitManifest {
    /// Stage.
    pub stage: u32,
    /// Steps done.
    pub step: u64,
    /// Every file with its size.
    pub files: Vec<CommitFile>,
}

/// One file of a checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CommitFile {
    /// Name within the checkpoint.
    pub name: String,
    /// Size in bytes.
    pub bytes: u64,
}

/// Uploads every file of `dir` under `location`, then `COMMIT.json`.
pub async fn upload(dir: &Path, location: &str, stage: u32, step: u64) -> anyhow::Result<()> {
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
        });
        root.write(&name, bytes).await?;
    }
    let manifest = CommitManifest { stage, step, files };
    root.write("COMMIT.json", serde_json::to_vec_pretty(&manifest)?)
        .await?;
    Ok(())
}

/// Downloads the committed checkpoint at `location` into `dir`; fails when it has no
/// `COMMIT.json` or a file's size differs from it.
pub async fn download(location: &str, dir: &Path) -> anyhow::Result<CommitManifest> {
    let root = DataRoot::open(location)?;
    let manifest: CommitManifest = serde_json::from_slice(&root.read("COMMIT.json").await?)
        .map_err(|e| anyhow::anyhow!("{location}/COMMIT.json: {e}"))?;
    std::fs::create_dir_all(dir)?;
    for file in &manifest.files {
        let bytes = root.read(&file.name).await?;
        anyhow::ensure!(
            bytes.len() as u64 == file.bytes,
            "{location}/{}: {} bytes, COMMIT.json says {}",
            file.name,
            bytes.len(),
            file.bytes
        );
        std::fs::write(dir.join(&file.name), bytes)?;
    }
    Ok(manifest)
}
