//! Dataset roots on any object store: plain paths, `file://`, `s3://`, `gs://`, `az://` (and the
//! other Azure schemes), and `memory://` for tests. Credentials come from the usual environment
//! variables (`AWS_*`, `GOOGLE_*`, `AZURE_*`).

use std::sync::Arc;
use std::time::Duration;

use futures::TryStreamExt;
use object_store::local::LocalFileSystem;
use object_store::memory::InMemory;
use object_store::path::Path;
use object_store::{
    ObjectMeta, ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload, UpdateVersion,
};

/// How often a failed read is retried (cloud stores also retry inside object_store).
const READ_ATTEMPTS: u32 = 3;

/// Longest wait for one read of an object before it counts as a failed attempt: a read that
/// never returns (a hung network mount, a FIFO with no writer) must not hang a step, least of
/// all a lone worker's, which has no peer waiting on it to expose the stall. Three attempts
/// later the frame is skipped and counted like a missing one.
pub const READ_TIMEOUT: Duration = Duration::from_secs(120);

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
    /// A conditional write was refused: the object exists although it was expected not to,
    /// or it changed since the version the writer holds was read or written.
    #[error("{uri}: `{path}` was changed by another writer since this one read or wrote it")]
    Changed {
        /// The root.
        uri: String,
        /// Object path relative to the root.
        path: String,
        /// The store's refusal, when the store checked the condition itself.
        #[source]
        source: Option<Box<object_store::Error>>,
    },
}

/// The version of an object a conditional write expects to replace: the store's e-tag and,
/// where it keeps versions, the version id.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ObjectVersion {
    /// HTTP entity tag (local disks derive one from inode, size and modification time).
    pub e_tag: Option<String>,
    /// Version id of versioned buckets.
    pub version: Option<String>,
}

/// An object store and the prefix a dataset lives under.
#[derive(Debug, Clone)]
pub struct DataRoot {
    store: Arc<dyn ObjectStore>,
    prefix: Path,
    uri: String,
    read_timeout: Duration,
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
        Self::open_with(uri, &[])
    }

    /// Opens a root with store options on top of the environment's: `(key, value)` pairs named
    /// like the variables (`AWS_ENDPOINT`, `AWS_ALLOW_HTTP`, ...). Lets one process (a test
    /// harness) reach a store without changing its own environment.
    pub fn open_with(uri: &str, options: &[(String, String)]) -> Result<Self, StoreError> {
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
                read_timeout: READ_TIMEOUT,
            });
        }
        let url = url::Url::parse(uri).map_err(|e| open_error(e.into()))?;
        if url.scheme() == "file" {
            let local = url
                .to_file_path()
                .map_err(|()| open_error("not a local file path".into()))?;
            let mut root = Self::open_with(&local.to_string_lossy(), options)?;
            root.uri = uri.to_string();
            return Ok(root);
        }
        let credentials = std::env::vars()
            .filter(|(key, _)| {
                ["AWS_", "GOOGLE_", "AZURE_"]
                    .iter()
                    .any(|prefix| key.starts_with(prefix))
            })
            .chain(options.iter().cloned());
        let (store, prefix) =
            object_store::parse_url_opts(&url, credentials).map_err(|e| open_error(e.into()))?;
        Ok(Self {
            store: Arc::from(store),
            prefix,
            uri: uri.to_string(),
            read_timeout: READ_TIMEOUT,
        })
    }

    /// Opens a root to write into (checkpoints, generated data): a local directory is created
    /// first; object-store prefixes need no creating.
    pub fn create(uri: &str) -> Result<Self, StoreError> {
        Self::create_with(uri, &[])
    }

    /// [`DataRoot::create`] with store options, as [`DataRoot::open_with`].
    pub fn create_with(uri: &str, options: &[(String, String)]) -> Result<Self, StoreError> {
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
        Self::open_with(uri, options)
    }

    /// A root over an existing store (the in-memory store of tests).
    pub fn from_store(store: Arc<dyn ObjectStore>, prefix: &str, label: &str) -> Self {
        Self {
            store,
            prefix: Path::from(prefix),
            uri: label.to_string(),
            read_timeout: READ_TIMEOUT,
        }
    }

    /// The same root with another limit on each read attempt (default [`READ_TIMEOUT`]).
    pub fn with_read_timeout(mut self, limit: Duration) -> Self {
        self.read_timeout = limit;
        self
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
            let attempt_read = async { self.store.get(&location).await?.bytes().await };
            let result = tokio::time::timeout(self.read_timeout, attempt_read)
                .await
                .unwrap_or_else(|_| {
                    Err(object_store::Error::Generic {
                        store: "read",
                        source: format!(
                            "no answer within {:.1} s",
                            self.read_timeout.as_secs_f64()
                        )
                        .into(),
                    })
                });
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

    /// The object at `relative` with the version a later [`DataRoot::write_if`] must name.
    pub async fn read_versioned(
        &self,
        relative: &str,
    ) -> Result<(Vec<u8>, ObjectVersion), StoreError> {
        let location = self.absolute(relative);
        let result = async {
            let got = self.store.get(&location).await?;
            let version = ObjectVersion {
                e_tag: got.meta.e_tag.clone(),
                version: got.meta.version.clone(),
            };
            Ok((got.bytes().await?.to_vec(), version))
        }
        .await;
        result.map_err(|error| match error {
            object_store::Error::NotFound { .. } => StoreError::NotFound {
                uri: self.uri.clone(),
                path: relative.to_string(),
            },
            error => self.io_error("read", relative, error),
        })
    }

    /// Writes `bytes` at `relative` only if the object is still as the writer last saw it:
    /// absent when `expected` is `None`, at that version otherwise. Returns the new version.
    /// A refusal is [`StoreError::Changed`], so two writers of one object (two coordinators
    /// on one checkpoint URI) cannot silently overwrite each other.
    ///
    /// S3 (`If-Match`/`If-None-Match`), GCS, Azure and the in-memory store check the condition
    /// themselves. object_store's local file system cannot replace an object conditionally, so
    /// there the current e-tag is compared first and the file then replaced by an atomic
    /// rename: a writer racing inside that window is not caught, which on one host's disk
    /// means two coordinators started at the same instant.
    pub async fn write_if(
        &self,
        relative: &str,
        bytes: Vec<u8>,
        expected: Option<&ObjectVersion>,
    ) -> Result<ObjectVersion, StoreError> {
        let location = self.absolute(relative);
        let changed = |source: Option<object_store::Error>| StoreError::Changed {
            uri: self.uri.clone(),
            path: relative.to_string(),
            source: source.map(Box::new),
        };
        let mode = match expected {
            None => PutMode::Create,
            Some(version) => PutMode::Update(UpdateVersion {
                e_tag: version.e_tag.clone(),
                version: version.version.clone(),
            }),
        };
        let payload = PutPayload::from(bytes);
        let put = self
            .store
            .put_opts(&location, payload.clone(), mode.into())
            .await;
        let result = match (put, expected) {
            (Err(object_store::Error::NotImplemented { .. }), Some(version)) => {
                let current = match self.store.head(&location).await {
                    Ok(meta) => meta,
                    Err(object_store::Error::NotFound { .. }) => return Err(changed(None)),
                    Err(error) => return Err(self.io_error("write", relative, error)),
                };
                if current.e_tag != version.e_tag {
                    return Err(changed(None));
                }
                self.store
                    .put_opts(&location, payload, PutOptions::default())
                    .await
            }
            (put, _) => put,
        };
        match result {
            Ok(put) => Ok(ObjectVersion {
                e_tag: put.e_tag,
                version: put.version,
            }),
            Err(
                error @ (object_store::Error::AlreadyExists { .. }
                | object_store::Error::Precondition { .. }),
            ) => Err(changed(Some(error))),
            Err(error) => Err(self.io_error("write", relative, error)),
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
