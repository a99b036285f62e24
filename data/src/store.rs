//! Dataset roots on any object store: plain paths, `file://`, `s3://`, `gs://`, `az://` (and the
//! other Azure schemes), and `memory://` for tests. Credentials come from the usual environment
//! variables (`AWS_*`, `GOOGLE_*`, `AZURE_*`).

use std::sync::Arc;
use std::time::Duration;

use futures::TryStreamExt;
use object_store::local::LocalFileSystem;
use object_store::memory::InMemory;
use object_store::path::Path;
use object_store::{ObjectMeta, ObjectStore, ObjectStoreExt, PutPayload};

/// How often a failed read is retried (cloud stores also retry inside object_store).
const READ_ATTEMPTS: u32 = 3;

/// Why a dataset root could not be opened, listed or read.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The URI names no store this build can open.
    #[error("cannot open dataset root `{uri}`")]
    Open {
        /// The URI as given.
        uri: String,
        /// What was wrong with it.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The object does not exist: a new job's `job.json`, or a frame deleted after indexing.
    #[error("{uri}: `{path}` does not exist")]
    NotFound {
        /// The root.
        uri: String,
        /// Object path relative to the root.
        path: String,
    },
    /// The store was reached but the operation failed, or it could not be reached.
    #[error("{uri}: {action} `{path}` failed")]
    Io {
        /// The root.
        uri: String,
        /// `list`, `read` or `write`.
        action: &'static str,
        /// Object path relative to the root.
        path: String,
        /// The store's error (boxed: it is large, and errors travel through every read).
        #[source]
        source: Box<object_store::Error>,
    },
}

/// An object store and the prefix a dataset lives under.
#[derive(Debug, Clone)]
pub struct DataRoot {
    store: Arc<dyn ObjectStore>,
    prefix: Path,
    uri: String,
}

/// One object under a root.
#[derive(Debug, Clone, PartialEq)]
pub struct Listed {
    /// Path relative to the root, `/`-separated.
    pub path: String,
    /// Size in bytes.
    pub size: u64,
    /// Last modification, seconds since the epoch.
    pub modified: i64,
}

impl DataRoot {
    /// Opens a root from a plain path or a URI.
    pub fn open(uri: &str) -> Result<Self, StoreError> {
        let open_error = |source: Box<dyn std::error::Error + Send + Sync>| StoreError::Open {
            uri: uri.to_string(),
            source,
        };
        if !uri.contains("://") {
            let path = std::path::Path::new(uri);
            let absolute = std::fs::canonicalize(path)
                .map_err(|e| open_error(format!("{e} (no such local directory)").into()))?;
            if !absolute.is_dir() {
                return Err(open_error("not a directory".into()));
            }
            let store =
                LocalFileSystem::new_with_prefix(&absolute).map_err(|e| open_error(e.into()))?;
            return Ok(Self {
                store: Arc::new(store),
                prefix: Path::default(),
                uri: uri.to_string(),
            });
        }
        let url = url::Url::parse(uri).map_err(|e| open_error(e.into()))?;
        if url.scheme() == "file" {
            let local = url
                .to_file_path()
                .map_err(|()| open_error("not a local file path".into()))?;
            let mut root = Self::open(&local.to_string_lossy())?;
            root.uri = uri.to_string();
            return Ok(root);
        }
        let credentials = std::env::vars().filter(|(key, _)| {
            ["AWS_", "GOOGLE_", "AZURE_"]
                .iter()
                .any(|prefix| key.starts_with(prefix))
        });
        let (store, prefix) =
            object_store::parse_url_opts(&url, credentials).map_err(|e| open_error(e.into()))?;
        Ok(Self {
            store: Arc::from(store),
            prefix,
            uri: uri.to_string(),
        })
    }

    /// Opens a root to write into (checkpoints, generated data): a local directory is created
    /// first; object-store prefixes need no creating.
    pub fn create(uri: &str) -> Result<Self, StoreError> {
        let local = if uri.contains("://") {
            url::Url::parse(uri)
                .ok()
                .filter(|url| url.scheme() == "file")
                .and_then(|url| url.to_file_path().ok())
        } else {
            Some(std::path::PathBuf::from(uri))
        };
        if let Some(dir) = local {
            std::fs::create_dir_all(&dir).map_err(|e| StoreError::Open {
                uri: uri.to_string(),
                source: Box::new(e),
            })?;
        }
        Self::open(uri)
    }

    /// A root over an existing store (the in-memory store of tests).
    pub fn from_store(store: Arc<dyn ObjectStore>, prefix: &str, label: &str) -> Self {
        Self {
            store,
            prefix: Path::from(prefix),
            uri: label.to_string(),
        }
    }

    /// An empty in-memory root.
    pub fn in_memory(label: &str) -> Self {
        Self::from_store(Arc::new(InMemory::new()), "", label)
    }

    /// The URI the root was opened from.
    pub fn uri(&self) -> &str {
        &self.uri
    }

    fn absolute(&self, relative: &str) -> Path {
        if self.prefix.as_ref().is_empty() {
            Path::from(relative)
        } else {
            Path::from(format!("{}/{relative}", self.prefix.as_ref()))
        }
    }

    fn io_error(
        &self,
        action: &'static str,
        path: &str,
        source: object_store::Error,
    ) -> StoreError {
        StoreError::Io {
            uri: self.uri.clone(),
            action,
            path: path.to_string(),
            source: Box::new(source),
        }
    }

    /// Every object under the root, sorted by path.
    pub async fn list(&self) -> Result<Vec<Listed>, StoreError> {
        let prefix = (!self.prefix.as_ref().is_empty()).then_some(&self.prefix);
        let objects: Vec<ObjectMeta> = self
            .store
            .list(prefix)
            .try_collect()
            .await
            .map_err(|e| self.io_error("list", "", e))?;
        let strip = self.prefix.as_ref().len();
        let mut listed: Vec<Listed> = objects
            .into_iter()
            .map(|meta| {
                let full = meta.location.as_ref();
                let path = if strip == 0 {
                    full.to_string()
                } else {
                    full.get(strip + 1..).unwrap_or_default().to_string()
                };
                Listed {
                    path,
                    size: meta.size,
                    modified: meta.last_modified.timestamp(),
                }
            })
            .collect();
        listed.sort_by(|a, b| a.path.cmp(&b.path));
        Ok(listed)
    }

    /// The whole object at `relative`, retried with back-off on failure.
    pub async fn read(&self, relative: &str) -> Result<Vec<u8>, StoreError> {
        let location = self.absolute(relative);
        let mut attempt = 0;
        loop {
            attempt += 1;
            let result = async { self.store.get(&location).await?.bytes().await }.await;
            match result {
                Ok(bytes) => return Ok(bytes.to_vec()),
                Err(object_store::Error::NotFound { .. }) => {
                    return Err(StoreError::NotFound {
                        uri: self.uri.clone(),
                        path: relative.to_string(),
                    });
                }
                Err(error) if attempt >= READ_ATTEMPTS => {
                    return Err(self.io_error("read", relative, error));
                }
                Err(error) => {
                    tracing::warn!(uri = %self.uri, path = relative, %error, attempt, "read failed, retrying");
                    tokio::time::sleep(Duration::from_millis(100 << attempt)).await;
                }
            }
        }
    }

    /// Writes `bytes` at `relative` (manifests, generated datasets).
    pub async fn write(&self, relative: &str, bytes: Vec<u8>) -> Result<(), StoreError> {
        self.store
            .put(&self.absolute(relative), PutPayload::from(bytes))
            .await
            .map(|_| ())
            .map_err(|e| self.io_error("write", relative, e))
    }
}
