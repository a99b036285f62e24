//! The worker's session with the coordinator: connecting, registering, heartbeats that carry
//! its progress, waiting for assignments, and leaving.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use proto::convert::ConvertError;
use proto::convert::device_to_wire;
use proto::v1::coordinator_client::CoordinatorClient;
use proto::v1::{AwaitAssignmentRequest, HeartbeatRequest, LeaveRequest, RegisterRequest};
use settings::XFactorConfig;
use settings::work::{Assignment, GenerationFailure};
use tokio::runtime::Runtime;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

use crate::metrics;
use crate::options::{WorkerOptions, WorkerTls};
use crate::progress::Progress;

/// The coordinator's client with the job token attached.
pub type Client = CoordinatorClient<InterceptedService<Channel, proto::AttachToken>>;

/// Tells the coordinator this worker is gone, so its group re-forms at once.
pub fn leave(
    runtime: &Runtime,
    client: &mut Client,
    progress: &Progress,
    reason: &str,
) -> anyhow::Result<()> {
    runtime.block_on(say_goodbye(client, progress, reason));
    Ok(())
}

/// Tells the coordinator this worker leaves, waiting at most 5 s for its answer; a leave it
/// does not hear is noticed from the silence.
pub async fn say_goodbye(client: &mut Client, progress: &Progress, reason: &str) {
    let request = LeaveRequest {
        worker_id: progress.worker_id(),
        reason: reason.into(),
        session: progress.session(),
    };
    match tokio::time::timeout(Duration::from_secs(5), client.leave(request)).await {
        Ok(Ok(_)) => tracing::info!("left the job"),
        Ok(Err(status)) => {
            tracing::warn!(error = %status.message(), "the coordinator did not hear the leave; it will notice the silence")
        }
        Err(_) => {
            tracing::warn!(
                "the coordinator did not answer the leave in 5 s; it will notice the silence"
            )
        }
    }
}

/// Connects to the coordinator, retrying for a while (it may start after the workers).
pub async fn connect(
    address: &str,
    token: &str,
    tls: Option<&WorkerTls>,
) -> anyhow::Result<Client> {
    let mut endpoint = tonic::transport::Endpoint::from_shared(address.to_string())
        .with_context(|| format!("coordinator address `{address}` is not a URL"))?
        .connect_timeout(Duration::from_secs(2));
    if let Some(tls) = tls {
        if endpoint.uri().scheme_str() != Some("https") {
            bail!("--tls-ca needs an https:// coordinator address, got `{address}`");
        }
        let host = endpoint.uri().host().unwrap_or("localhost").to_string();
        endpoint = endpoint
            .tls_config(tls.client(&host)?)
            .with_context(|| format!("TLS with the CA {}", tls.ca.display()))?;
    }
    let deadline = Instant::now() + Duration::from_secs(60);
    let channel = loop {
        match endpoint.connect().await {
            Ok(channel) => break channel,
            Err(e) if Instant::now() >= deadline => {
                bail!("cannot reach the coordinator at {address}: {e}")
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    };
    Ok(
        CoordinatorClient::with_interceptor(channel, proto::AttachToken::new(token)?)
            .max_decoding_message_size(proto::MAX_MESSAGE_BYTES),
    )
}

/// Registers this worker; returns the heartbeat interval the coordinator expects.
pub async fn register(
    client: &mut Client,
    options: &WorkerOptions,
    address: &str,
    progress: &Progress,
) -> anyhow::Result<Duration> {
    let request = RegisterRequest {
        protocol_version: proto::PROTOCOL_VERSION,
        model_config_version: XFactorConfig::SCHEMA_VERSION,
        worker_name: options.name.clone(),
        collective_address: address.to_string(),
        device: options.device.map(|device| device_to_wire(device) as i32),
        expected_model: options.expected_model_config.as_ref().map(Into::into),
        ring_tls: options
            .tls
            .as_ref()
            .is_some_and(|tls| tls.identity.is_some()),
    };
    // A coordinator coming up (or a connection cut) answers as the long poll's do: waited out
    // for as long as `connect` waits; a refusal of the worker itself ends it.
    let deadline = Instant::now() + Duration::from_secs(60);
    let reply = loop {
        match client.register(request.clone()).await {
            Ok(reply) => break reply.into_inner(),
            Err(status)
                if poll_failure(status.code()) == PollFailure::CoordinatorSide
                    && Instant::now() < deadline =>
            {
                tracing::warn!(code = ?status.code(), message = status.message(), "registration failed on the coordinator's side or the connection; retrying");
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(status) => bail!(
                "the coordinator refused registration ({:?}): {}",
                status.code(),
                status.message()
            ),
        }
    };
    progress.worker.store(reply.worker_id, Ordering::SeqCst);
    progress.known.store(true, Ordering::SeqCst);
    *progress
        .session
        .write()
        .unwrap_or_else(std::sync::PoisonError::into_inner) = reply.session;
    tracing::info!(worker = reply.worker_id, job = %reply.job_name, collective = %address, "registered");
    // A floor of 50 ms keeps heartbeats from becoming a busy loop whatever the reply says.
    let interval = proto::convert::seconds_from_wire(
        reply.heartbeat_interval_s,
        0.0,
        "RegisterReply.heartbeat_interval_s",
    )?;
    Ok(interval.max(Duration::from_millis(50)))
}

/// Why no assignment came.
#[derive(Debug, thiserror::Error)]
pub enum AwaitError {
    /// The coordinator no longer knows this worker (it restarted, or removed the worker):
    /// register again.
    #[error("the coordinator does not know this worker: {0}")]
    Unknown(String),
    /// The coordinator refused the request.
    #[error("the coordinator refused the request for work: {0}")]
    Refused(String),
    /// The coordinator sent an assignment this build cannot act on.
    #[error("the coordinator's assignment is malformed")]
    Malformed(#[source] ConvertError),
}

/// Whose fault a failed request to the coordinator (for work, or to register) was, by its
/// status code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PollFailure {
    /// The coordinator or the connection to it: it is restarting, it failed, or the long poll
    /// was cut (a reset connection arrives as `Unknown`, `Internal` or `Cancelled` as often as
    /// `Unavailable`). The worker waits and asks again.
    CoordinatorSide,
    /// The coordinator does not know this worker (it restarted, or removed it): register again.
    NotKnown,
    /// The request itself was refused (a wrong token, another protocol): asking again cannot
    /// help, so the worker ends.
    Refused,
}

fn poll_failure(code: tonic::Code) -> PollFailure {
    use tonic::Code;
    match code {
        Code::Unavailable
        | Code::Unknown
        | Code::Internal
        | Code::Cancelled
        | Code::DeadlineExceeded
        | Code::Aborted
        | Code::ResourceExhausted
        | Code::DataLoss => PollFailure::CoordinatorSide,
        Code::NotFound => PollFailure::NotKnown,
        Code::Ok
        | Code::InvalidArgument
        | Code::AlreadyExists
        | Code::PermissionDenied
        | Code::FailedPrecondition
        | Code::OutOfRange
        | Code::Unimplemented
        | Code::Unauthenticated => PollFailure::Refused,
    }
}

/// Blocks until the coordinator has work for this worker after generation `after`, retrying
/// while the coordinator is unavailable (it may be restarting). `failure` tells it why this
/// worker's part of `after` failed.
pub async fn await_assignment(
    client: &mut Client,
    progress: &Progress,
    after: u64,
    failure: Option<&GenerationFailure>,
) -> Result<Assignment, AwaitError> {
    loop {
        let request = AwaitAssignmentRequest {
            worker_id: progress.worker_id(),
            after_generation: after,
            session: progress.session(),
            failure: failure.map(Into::into),
        };
        let status = match client.await_assignment(request).await {
            Ok(reply) => {
                return Assignment::try_from(&reply.into_inner()).map_err(AwaitError::Malformed);
            }
            Err(status) => status,
        };
        match poll_failure(status.code()) {
            PollFailure::CoordinatorSide => {
                tracing::warn!(code = ?status.code(), message = status.message(), "the request for work failed on the coordinator's side or the connection; retrying");
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
            PollFailure::NotKnown => {
                return Err(AwaitError::Unknown(status.message().to_string()));
            }
            PollFailure::Refused => {
                return Err(AwaitError::Refused(status.message().to_string()));
            }
        }
    }
}

/// Sends a heartbeat with the step every `interval`; a reply saying the generation ended
/// cancels the step in flight.
pub async fn heartbeats(mut client: Client, progress: Arc<Progress>, interval: Duration) {
    loop {
        tokio::time::sleep(interval).await;
        let generation = progress.generation.load(Ordering::SeqCst);
        let request = HeartbeatRequest {
            worker_id: progress.worker_id(),
            generation,
            step: progress.step.load(Ordering::SeqCst),
            activity: progress.activity.load(Ordering::SeqCst),
            session: progress.session(),
            device: progress
                .device
                .get()
                .as_ref()
                .map(proto::convert::device_in_use_to_wire),
        };
        match client.heartbeat(request).await {
            Ok(reply) => {
                progress.metrics.add(&metrics::HEARTBEATS, &[], 1.0);
                let reply = reply.into_inner();
                progress.known.store(reply.known, Ordering::SeqCst);
                if !reply.generation_current
                    && generation == progress.generation.load(Ordering::SeqCst)
                {
                    progress.generation_token().cancel();
                }
            }
            Err(status) => {
                progress.metrics.add(&metrics::HEARTBEAT_FAILURES, &[], 1.0);
                tracing::warn!(error = %status.message(), "heartbeat failed");
            }
        }
    }
}

#[cfg(test)]
#[path = "session_tests.rs"]
mod tests;
