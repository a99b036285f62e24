//! The job on a web page: a snapshot of the job (`job/snapshot.rs`), drawn as a self-refreshing
//! HTML page (`page.rs`) and served with its JSON twin on the metrics port to holders of the
//! job token (`routes.rs`).

pub mod page;
pub mod routes;

use crate::job::snapshot::StatusSnapshot;

/// Why the status page's snapshot could not be read.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    /// The address is not `HOST:PORT`.
    #[error("`{0}` is not the coordinator's metrics address (HOST:PORT)")]
    Address(String),
    /// Nothing answered.
    #[error("cannot reach the status page at {address}: {source}")]
    Unreachable {
        /// Where.
        address: String,
        /// Why.
        source: std::io::Error,
    },
    /// It answered with something other than the snapshot.
    #[error("the status page at {address} answered {status}: {body}")]
    Refused {
        /// Where.
        address: String,
        /// The HTTP status.
        status: u16,
        /// What it said.
        body: String,
    },
}

/// The snapshot `/api/status` serves at the metrics address `address` to the holder of `token`.
pub async fn fetch(address: &str, token: &str) -> Result<StatusSnapshot, FetchError> {
    let socket = tokio::net::lookup_host(address)
        .await
        .ok()
        .and_then(|mut found| found.next())
        .ok_or_else(|| FetchError::Address(address.to_string()))?;
    let bearer = format!("Bearer {token}");
    let answer = telemetry::http::request(
        socket,
        "GET",
        "/api/status",
        &[("Authorization", &bearer)],
        "",
    )
    .await
    .map_err(|source| FetchError::Unreachable {
        address: address.to_string(),
        source,
    })?;
    let refused = |body: String| FetchError::Refused {
        address: address.to_string(),
        status: answer.status,
        body,
    };
    if answer.status != 200 {
        return Err(refused(answer.body.trim().to_string()));
    }
    serde_json::from_str(&answer.body).map_err(|e| refused(format!("not a status snapshot: {e}")))
}

/// The snapshot as `xfactor-coordinator status` prints it: one `key=value` line for the job,
/// then one per worker.
pub fn summary(s: &StatusSnapshot) -> Vec<String> {
    let eta = s.eta_s.map_or("-".to_string(), |eta| format!("{eta:.0}"));
    let mut lines = vec![format!(
        "job={} phase={} state=\"{}\" generation={} step={}/{} job_steps={}/{} eta_s={eta} last_loss={} faults={} last_commit={}",
        s.job,
        s.phase,
        s.state,
        s.generation,
        s.step,
        s.stage_steps,
        s.job_steps_done,
        s.job_steps_total,
        s.last_loss,
        s.faults.len(),
        s.commits.first().map_or("-", |c| c.location.as_str()),
    )];
    lines.extend(s.workers.iter().map(|w| {
        format!(
            "worker={} name={} device={} state=\"{}\" samples_per_s={:.1} heartbeat_age_s={:.1} faults={}",
            w.id, w.name, w.device, w.state, w.samples_per_s, w.heartbeat_age_s, w.faults
        )
    }));
    lines
}
