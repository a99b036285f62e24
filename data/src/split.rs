//! The paper's own train/test split files: a JSON object whose keys are the training sequence
//! ids. A dataset that names one uses it instead of the layout's rule (90/10 per category,
//! the DL3DV benchmark list, RE10K's folders), because the paper's files differ slightly from
//! those rules.

use std::collections::BTreeSet;

use crate::manifest::{Manifest, Split};
use crate::store::{DataRoot, StoreError};

/// Why a split file cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SplitError {
    /// Not JSON at all.
    #[error("split file {name} is not JSON: {source}")]
    Json {
        /// The file.
        name: String,
        /// Parser error, with line and column.
        #[source]
        source: serde_json::Error,
    },
    /// JSON, but not an object keyed by sequence id.
    #[error("split file {name} must be a JSON object whose keys are sequence ids")]
    NotAnObject {
        /// The file.
        name: String,
    },
    /// The file could not be opened or read.
    #[error("split file {name} could not be read")]
    Read {
        /// The file as the job names it.
        name: String,
        /// The store's error.
        #[source]
        source: StoreError,
    },
}

/// Reads the split file a dataset names: a path relative to the dataset's root, or a whole
/// path or URI of its own (`/splits/re10k.json`, `s3://bucket/splits/re10k.json`).
pub async fn read_split_file(dataset_root: &DataRoot, name: &str) -> Result<SplitFile, SplitError> {
    let read_error = |source| SplitError::Read {
        name: name.to_string(),
        source,
    };
    let bytes = if name.contains("://") || name.starts_with('/') {
        let (parent, file) = name.rsplit_once('/').unwrap_or(("", name));
        let parent = if parent.is_empty() || parent.ends_with(':') {
            format!("{parent}/")
        } else {
            parent.to_string()
        };
        DataRoot::open(&parent)
            .map_err(read_error)?
            .read(file)
            .await
            .map_err(read_error)?
    } else {
        dataset_root.read(name).await.map_err(read_error)?
    };
    SplitFile::parse(&bytes, name)
}

/// The sequence ids a split file lists.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SplitFile {
    ids: BTreeSet<String>,
}

impl SplitFile {
    /// Reads the keys of the JSON object in `bytes`; `name` only labels errors.
    pub fn parse(bytes: &[u8], name: &str) -> Result<Self, SplitError> {
        let value: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|source| SplitError::Json {
                name: name.to_string(),
                source,
            })?;
        let object = value.as_object().ok_or_else(|| SplitError::NotAnObject {
            name: name.to_string(),
        })?;
        Ok(Self {
            ids: object.keys().cloned().collect(),
        })
    }

    /// Whether the file lists `id`, either whole (`category/sequence`) or by its last part
    /// (`sequence`, as the paper's files key CO3Dv2 and MVImgNet).
    pub fn lists(&self, id: &str) -> bool {
        self.ids.contains(id)
            || id
                .rsplit('/')
                .next()
                .is_some_and(|last| self.ids.contains(last))
    }

    /// Marks the listed sequences of `manifest` as training and every other one as test.
    pub fn apply(&self, manifest: &mut Manifest) {
        for sequence in &mut manifest.sequences {
            sequence.split = if self.lists(&sequence.id) {
                Split::Train
            } else {
                Split::Test
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::index::index_paths;
    use settings::data::DatasetKind;

    #[test]
    fn a_split_file_replaces_the_ninety_ten_rule() {
        // Ten CO3Dv2 sequences: the 90/10 rule trains on the first nine.
        let paths: Vec<String> = (0..10)
            .flat_map(|s| (0..10).map(move |f| format!("apple/{s}00_1_2/images/frame{f:06}.jpg")))
            .collect();
        let refs: Vec<&str> = paths.iter().map(String::as_str).collect();
        let mut manifest = index_paths(DatasetKind::Co3dv2, &refs).manifest;
        assert_eq!(manifest.sequences[9].split, Split::Test);
        let file = br#"{"900_1_2": [], "apple/000_1_2": {"frames": 10}}"#;
        SplitFile::parse(file, "train.json")
            .unwrap()
            .apply(&mut manifest);
        let train: Vec<&str> = manifest
            .sequences
            .iter()
            .filter(|s| s.split == Split::Train)
            .map(|s| s.id.as_str())
            .collect();
        assert_eq!(train, vec!["apple/000_1_2", "apple/900_1_2"]);
    }

    #[test]
    fn split_files_are_read_beside_the_data_or_from_their_own_path() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("splits")).unwrap();
        std::fs::write(dir.path().join("splits/train.json"), br#"{"seq-a": 1}"#).unwrap();
        let root = DataRoot::open(&dir.path().to_string_lossy()).unwrap();
        let rt = tokio::runtime::Runtime::new().unwrap();
        let relative = rt
            .block_on(read_split_file(&root, "splits/train.json"))
            .unwrap();
        assert!(relative.lists("seq-a") && !relative.lists("seq-b"));
        let absolute = dir.path().join("splits/train.json");
        let absolute = rt
            .block_on(read_split_file(&root, &absolute.to_string_lossy()))
            .unwrap();
        assert_eq!(absolute, relative);
        let missing = rt
            .block_on(read_split_file(&root, "splits/test.json"))
            .unwrap_err();
        assert!(matches!(missing, SplitError::Read { .. }), "{missing}");
        assert!(
            missing.to_string().contains("splits/test.json"),
            "{missing}"
        );
    }

    #[test]
    fn malformed_split_files_are_named() {
        let error = SplitFile::parse(b"[1, 2]", "bad.json").unwrap_err();
        assert!(matches!(error, SplitError::NotAnObject { .. }), "{error}");
        assert!(
            SplitFile::parse(b"{", "cut.json")
                .unwrap_err()
                .to_string()
                .contains("cut.json")
        );
    }
}
