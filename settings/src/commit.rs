//! The manifest written last into every committed checkpoint or report: what the uploader
//! wrote, so the coordinator can verify a commit and a worker can download it completely.

use serde::{Deserialize, Serialize};

use crate::phase::Phase;

/// Name of the manifest object inside a checkpoint prefix.
pub const MANIFEST_NAME: &str = "COMMIT.json";

/// The manifest written last into a checkpoint.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CommitManifest {
    /// The phase that wrote it, as its number.
    #[serde(rename = "stage", with = "crate::phase::as_number")]
    pub phase: Phase,
    /// Steps done.
    pub step: u64,
    /// Every file with its size.
    pub files: Vec<CommitFile>,
}

/// One file of a checkpoint.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CommitFile {
    /// Name within the checkpoint.
    pub name: String,
    /// Size in bytes.
    pub bytes: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manifests_of_older_builds_still_read() {
        let old =
            r#"{"stage": 2, "step": 10, "files": [{"name": "model.safetensors", "bytes": 5}]}"#;
        let manifest: CommitManifest = serde_json::from_str(old).unwrap();
        assert_eq!(manifest.phase, Phase::Stage2);
        assert_eq!(manifest.files[0].bytes, 5);
        let again: CommitManifest =
            serde_json::from_str(&serde_json::to_string(&manifest).unwrap()).unwrap();
        assert_eq!(again, manifest);
    }
}
