//! One coordinator per checkpoint URI: a lease object, `coordinator.lease.json`, beside
//! `job.json`. A starting coordinator claims it with a conditional write; the holder renews it
//! every [`RENEW_EVERY`] and releases it when it stops. A second coordinator finds the lease
//! renewed while it watches and refuses to start, naming the holder; a coordinator restarted
//! after its predecessor was killed sees the renewals stop and takes over once the lease is
//! [`LEASE_TIMEOUT`] old. A holder whose renewal finds the lease taken stops (it was fenced).

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use data::store::{DataRoot, ObjectVersion, StoreError};
use serde::{Deserialize, Serialize};
use tokio::sync::Mutex;

/// Name of the lease object under the checkpoint URI.
pub const LEASE_OBJECT: &str = "coordinator.lease.json";

/// A lease not renewed for this long belongs to a coordinator that is gone.
pub const LEASE_TIMEOUT: Duration = Duration::from_secs(15);

/// How often the holder renews its lease.
pub const RENEW_EVERY: Duration = Duration::from_secs(5);

/// What the lease object holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Record {
    /// Who holds it: host, process id and start time.
    holder: String,
    /// Seconds since the epoch at the holder's last renewal.
    renewed_unix_s: f64,
    /// Set when the holder stopped cleanly: the next coordinator need not wait.
    released: bool,
}

/// Why the lease could not be claimed or kept.
#[derive(Debug, thiserror::Error)]
pub enum LeaseError {
    /// Another coordinator is alive on this checkpoint URI.
    #[error(
        "another coordinator ({holder}) runs this job on {uri}: its lease was renewed {seconds_ago:.0} s ago; stop it first"
    )]
    Held {
        /// The checkpoint URI.
        uri: String,
        /// The other coordinator.
        holder: String,
        /// How long ago it renewed.
        seconds_ago: f64,
    },
    /// While this coordinator ran, another one took the lease: this one must stop.
    #[error("{uri}: the lease was taken over by another coordinator; this one stops")]
    Lost {
        /// The checkpoint URI.
        uri: String,
    },
    /// The lease object could not be read, parsed or written.
    #[error("{uri}/{LEASE_OBJECT} could not be used")]
    Store {
        /// The checkpoint URI.
        uri: String,
        /// What failed.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// This coordinator's hold on the checkpoint URI.
pub struct Lease {
    root: DataRoot,
    holder: String,
    version: Mutex<Option<ObjectVersion>>,
}

fn now_unix_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

impl Lease {
    /// Claims the lease under `root` for `holder`, waiting while an unreleased lease ages
    /// towards [`LEASE_TIMEOUT`]; refuses when the lease is renewed meanwhile (its holder is
    /// alive).
    pub async fn claim(root: DataRoot, holder: String) -> Result<Self, LeaseError> {
        let uri = root.uri().to_string();
        let store_error = |source: Box<dyn std::error::Error + Send + Sync>| LeaseError::Store {
            uri: uri.clone(),
            source,
        };
        let mut first_seen: Option<f64> = None;
        loop {
            let (current, version) = match root.read_versioned(LEASE_OBJECT).await {
                Ok((bytes, version)) => {
                    let record: Record =
                        serde_json::from_slice(&bytes).map_err(|e| store_error(e.into()))?;
                    (Some(record), Some(version))
                }
                Err(StoreError::NotFound { .. }) => (None, None),
                Err(e) => return Err(store_error(e.into())),
            };
            if let Some(other) = current
                .as_ref()
                .filter(|r| !r.released && r.holder != holder)
            {
                let age = now_unix_s() - other.renewed_unix_s;
                let renewed_since = first_seen.is_some_and(|seen| other.renewed_unix_s > seen);
                if renewed_since {
                    return Err(LeaseError::Held {
                        uri,
                        holder: other.holder.clone(),
                        seconds_ago: age.max(0.0),
                    });
                }
                if age < LEASE_TIMEOUT.as_secs_f64() {
                    if first_seen.is_none() {
                        tracing::warn!(holder = %other.holder, seconds_ago = age, "the checkpoint URI is leased by another coordinator; waiting to see whether it is alive");
                    }
                    first_seen.get_or_insert(other.renewed_unix_s);
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    continue;
                }
                tracing::warn!(holder = %other.holder, seconds_ago = age, "taking over the lease of a coordinator that stopped renewing it");
            }
            let lease = Self {
                root: root.clone(),
                holder: holder.clone(),
                version: Mutex::new(version),
            };
            match lease.write(false).await {
                Ok(()) => return Ok(lease),
                // Another coordinator wrote in between: look again.
                Err(LeaseError::Lost { .. }) => continue,
                Err(error) => return Err(error),
            }
        }
    }

    /// Renews the lease; [`LeaseError::Lost`] when another coordinator took it.
    pub async fn renew(&self) -> Result<(), LeaseError> {
        self.write(false).await
    }

    /// Marks the lease released, so the next coordinator starts at once.
    pub async fn release(&self) {
        if let Err(error) = self.write(true).await {
            tracing::warn!(%error, "the lease was not released; the next coordinator waits for it to expire");
        }
    }

    async fn write(&self, released: bool) -> Result<(), LeaseError> {
        let uri = self.root.uri().to_string();
        let record = Record {
            holder: self.holder.clone(),
            renewed_unix_s: now_unix_s(),
            released,
        };
        let bytes = serde_json::to_vec_pretty(&record).map_err(|e| LeaseError::Store {
            uri: uri.clone(),
            source: e.into(),
        })?;
        let mut version = self.version.lock().await;
        let mut adopted = false;
        loop {
            match self
                .root
                .write_if(LEASE_OBJECT, bytes.clone(), version.as_ref())
                .await
            {
                Ok(written) => {
                    *version = Some(written);
                    return Ok(());
                }
                // A renewal whose answer was lost (the store hung, the client gave up and
                // retried) may still have landed: the lease then names this coordinator under
                // a version it never saw. Adopted once; anyone else's lease means fenced.
                Err(StoreError::Changed { .. }) if !adopted => {
                    adopted = true;
                    match self.own_version().await {
                        Some(current) => *version = Some(current),
                        None => return Err(LeaseError::Lost { uri }),
                    }
                }
                Err(StoreError::Changed { .. }) => return Err(LeaseError::Lost { uri }),
                Err(e) => {
                    return Err(LeaseError::Store {
                        uri,
                        source: e.into(),
                    });
                }
            }
        }
    }

    /// The lease's current version when it still names this coordinator as its holder.
    async fn own_version(&self) -> Option<ObjectVersion> {
        let (bytes, version) = self.root.read_versioned(LEASE_OBJECT).await.ok()?;
        let record: Record = serde_json::from_slice(&bytes).ok()?;
        (record.holder == self.holder).then_some(version)
    }
}

/// This process's name for the lease: host, process id and start time.
pub fn holder_name() -> String {
    let host = std::env::var("HOSTNAME")
        .ok()
        .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "unknown-host".to_string());
    format!(
        "{host} pid {} started {:.0}",
        std::process::id(),
        now_unix_s()
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_live_holder_refuses_a_second_and_a_release_lets_the_next_in() {
        let root = DataRoot::in_memory("lease");
        let first = Lease::claim(root.clone(), "first".into()).await.unwrap();
        let renewing = tokio::spawn(async move {
            for _ in 0..6 {
                tokio::time::sleep(Duration::from_millis(400)).await;
                first.renew().await.unwrap();
            }
            first
        });
        let refused = Lease::claim(root.clone(), "second".into())
            .await
            .err()
            .unwrap();
        assert!(
            matches!(&refused, LeaseError::Held { holder, .. } if holder == "first"),
            "{refused}"
        );
        let first = renewing.await.unwrap();
        first.release().await;
        let second = Lease::claim(root.clone(), "second".into()).await.unwrap();
        assert!(matches!(first.renew().await, Err(LeaseError::Lost { .. })));
        second.renew().await.unwrap();
    }

    #[tokio::test]
    async fn a_renewal_that_landed_unseen_is_adopted_and_anyone_elses_lease_fences() {
        let root = DataRoot::in_memory("lease-unseen");
        let lease = Lease::claim(root.clone(), "first".into()).await.unwrap();
        // The store took a renewal whose answer never came back: same holder, new version.
        let landed = Record {
            holder: "first".into(),
            renewed_unix_s: now_unix_s(),
            released: false,
        };
        let bytes = serde_json::to_vec(&landed).unwrap();
        root.write(LEASE_OBJECT, bytes).await.unwrap();
        lease.renew().await.unwrap();
        lease.renew().await.unwrap();
        let taken = Record {
            holder: "second".into(),
            ..landed
        };
        root.write(LEASE_OBJECT, serde_json::to_vec(&taken).unwrap())
            .await
            .unwrap();
        assert!(matches!(lease.renew().await, Err(LeaseError::Lost { .. })));
    }
}
