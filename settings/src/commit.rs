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
    /// Name within the checkpoint: a plain file name.
    pub name: String,
    /// Size in bytes.
    pub bytes: u64,
    /// CRC-32 of the contents, checked when the checkpoint is loaded (absent in manifests of
    /// older builds, which are checked by size alone).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crc32: Option<u32>,
}

/// A manifest that cannot be trusted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ManifestError {
    /// A file name that could reach outside the checkpoint (`../x`, `/etc/x`, `a/b`).
    #[error("{MANIFEST_NAME} names `{0}`, which is not a plain file name")]
    UnsafeName(String),
    /// The same name twice.
    #[error("{MANIFEST_NAME} lists `{0}` twice")]
    Duplicate(String),
}

impl CommitManifest {
    /// Checks that every listed name is a plain file name, listed once, so joining it to a
    /// scratch directory or a store prefix stays inside it.
    pub fn validate(&self) -> Result<(), ManifestError> {
        let mut seen = std::collections::BTreeSet::new();
        for file in &self.files {
            if !is_plain_file_name(&file.name) {
                return Err(ManifestError::UnsafeName(file.name.clone()));
            }
            if !seen.insert(file.name.as_str()) {
                return Err(ManifestError::Duplicate(file.name.clone()));
            }
        }
        Ok(())
    }
}

/// A name without separators, not `.`/`..`, not empty, without control characters.
fn is_plain_file_name(name: &str) -> bool {
    !name.is_empty()
        && name != "."
        && name != ".."
        && !name.contains(['/', '\\', ':'])
        && !name.chars().any(char::is_control)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest(names: &[&str]) -> CommitManifest {
        CommitManifest {
            phase: Phase::Stage1,
            step: 1,
            files: names
                .iter()
                .map(|name| CommitFile {
                    name: name.to_string(),
                    bytes: 1,
                    crc32: Some(7),
                })
                .collect(),
        }
    }

    #[test]
    fn names_that_leave_the_checkpoint_are_refused() {
        assert_eq!(
            manifest(&["model.safetensors", "state.json"]).validate(),
            Ok(())
        );
        for bad in ["../x", "/etc/x", "a/b", "..", "", "c:\\x", "a\nb"] {
            assert_eq!(
                manifest(&[bad]).validate(),
                Err(ManifestError::UnsafeName(bad.to_string())),
                "{bad:?}"
            );
        }
        assert_eq!(
            manifest(&["a", "a"]).validate(),
            Err(ManifestError::Duplicate("a".into()))
        );
    }

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
