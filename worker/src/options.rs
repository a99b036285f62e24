//! How the worker process was started: its command-line choices, gathered by `main.rs` and
//! read by every layer below. A leaf: it imports nothing else of the worker but the
//! collective's TLS settings.

use std::path::PathBuf;
use std::time::Duration;

use settings::{DeviceChoice, DeviceSet, XFactorConfig};

use crate::collective::PeerTls;

/// How a worker is started.
#[derive(Debug, Clone)]
pub struct WorkerOptions {
    /// Coordinator URL, `http://host:port`.
    pub coordinator: String,
    /// The job token.
    pub token: String,
    /// Where the Collective service binds (`127.0.0.1:0` picks a free port).
    pub listen: String,
    /// Address peers should use, when it differs from the bound one (NAT, `0.0.0.0`).
    pub advertise: Option<String>,
    /// The device to train on; `None` follows the job.
    pub device: Option<DeviceChoice>,
    /// The devices of that backend it drives, one model replica each; `None` follows the job.
    pub devices: Option<DeviceSet>,
    /// Recompute activations in the backward pass instead of keeping them: less device
    /// memory (the paper's model at its batch), more time per step.
    pub activation_checkpointing: bool,
    /// Threads per micro-batch; `None` follows the job (0 there: every core).
    pub threads: Option<usize>,
    /// Name in logs.
    pub name: String,
    /// When set: the model config this worker insists on.
    pub expected_model_config: Option<XFactorConfig>,
    /// Longest wait for a peer's chunk.
    pub collective_timeout: Duration,
    /// After a SIGTERM, how long a worker still busy in its step gets before it leaves anyway.
    pub shutdown_grace: Duration,
    /// Scratch space for checkpoints on their way to and from the store.
    pub scratch: PathBuf,
    /// `host:port` for Prometheus `/metrics`; `None`: no endpoint.
    pub metrics_address: Option<String>,
    /// TLS towards the coordinator and between ranks; `None`: plain HTTP/2.
    pub tls: Option<WorkerTls>,
    /// Fault drill: from this step on, perturb this replica's all-reduced gradients (a
    /// silently faulty accelerator) so the job's divergence handling can be exercised.
    pub drill_diverge_from_step: Option<u64>,
}

/// A worker's TLS files. With `identity`, its Collective service runs TLS too and peers are
/// dialled over TLS (every worker of a job must then have one).
#[derive(Debug, Clone)]
pub struct WorkerTls {
    /// CA that signed the coordinator's (and peers') certificates.
    pub ca: PathBuf,
    /// Name the certificates must carry; `None`: the host of the address dialled.
    pub domain: Option<String>,
    /// This worker's certificate and key, for its Collective service.
    pub identity: Option<(PathBuf, PathBuf)>,
}

impl WorkerTls {
    pub(crate) fn client(&self, host: &str) -> anyhow::Result<tonic::transport::ClientTlsConfig> {
        let domain = self.domain.as_deref().unwrap_or(host);
        Ok(proto::tls::client_config(&self.ca, domain)?)
    }

    pub(crate) fn peers(&self) -> anyhow::Result<Option<PeerTls>> {
        let Some((cert, key)) = &self.identity else {
            return Ok(None);
        };
        Ok(Some(PeerTls::from_files(
            cert,
            key,
            &self.ca,
            self.domain.clone(),
        )?))
    }
}
