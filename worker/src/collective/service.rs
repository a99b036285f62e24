//! The receiving side of the ring: the Collective service and the mailbox it files chunks
//! into.
//!
//! A rank accepts one stream per generation, and only from its left neighbour: the stream must
//! present, as `x-xfactor-ring` metadata, the secret the coordinator gave that neighbour for
//! this generation. A stream that arrives before this rank has joined the generation waits
//! (unread, so HTTP/2 flow control holds its sender) until the rank joins, a newer generation
//! makes it stale, or [`ADMISSION_WAIT`] passes. The inbox is bounded, so a fast sender is
//! slowed down rather than buffered without limit.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use proto::v1::collective_server::Collective;
use proto::v1::{Chunk, PushAck};
use tokio::sync::{Notify, mpsc};
use tonic::{Request, Response, Status, Streaming};
use tracing::Instrument;

use super::Link;

/// The metadata key carrying the sender's ring secret.
pub const RING_SECRET_KEY: &str = "x-xfactor-ring";

/// Chunks held for the ring before the sender is slowed down (at most 16 MiB of 1 MiB chunks).
pub const INBOX_CHUNKS: usize = 16;

/// Most lanes a ring may have.
pub const MAX_LANES: usize = settings::work::MAX_RING_LANES;

/// Longest a stream waits for this rank to join its generation.
const ADMISSION_WAIT: Duration = Duration::from_secs(60);

/// A chunk, or why the left neighbour's stream broke.
pub(super) type Inbound = Result<Chunk, InboundFailure>;

/// Why the left neighbour's stream stopped delivering chunks.
#[derive(Debug, thiserror::Error)]
pub(super) enum InboundFailure {
    /// The stream itself failed (the peer died, the connection reset).
    #[error("{}", .0.message())]
    Stream(tonic::Status),
    /// A chunk of another generation arrived on this generation's stream.
    #[error("a chunk of generation {found} in the stream of generation {expected}")]
    WrongGeneration {
        /// The chunk's generation.
        found: u64,
        /// The stream's.
        expected: u64,
    },
}

/// This rank's secret for its outgoing stream and the one its left neighbour must present.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RingKeys {
    /// Sent with this rank's stream to its right neighbour.
    pub own: String,
    /// Demanded of the stream from the left neighbour.
    pub left: String,
}

/// The generation this rank's ring is in, and where its left neighbour's chunks go.
struct Joined {
    generation: u64,
    left_secret: String,
    doors: Doors,
}

/// Where an admitted left neighbour's traffic goes: its gRPC stream's chunks, or its lanes.
#[derive(Clone)]
pub(super) struct Doors {
    inbox: mpsc::Sender<Inbound>,
    pub(super) lanes: mpsc::Sender<AdmittedLane>,
}

/// A lane connection from the left neighbour, proven: which lane of how many. Its ring
/// answers it once taken (`lanes.rs`).
pub(super) struct AdmittedLane {
    pub(super) lane: u32,
    pub(super) lanes: u32,
    pub(super) stream: super::carrier::Carrier,
}

/// What a ring reads from after joining a generation.
pub(super) struct Inboxes {
    /// The chunks of the left neighbour's gRPC stream.
    pub(super) chunks: mpsc::Receiver<Inbound>,
    /// The left neighbour's lane connections, as they are admitted.
    pub(super) lanes: mpsc::Receiver<AdmittedLane>,
}

/// Where incoming chunks wait for the ring of the generation this rank is in.
#[derive(Default)]
pub struct Mailbox {
    joined: Mutex<Option<Joined>>,
    changed: Notify,
}

impl Mailbox {
    /// Joins `generation`, whose left neighbour must present `left_secret`; returns the
    /// inboxes its chunks and lanes arrive in. Streams of older generations are cut off.
    pub(super) fn join(&self, generation: u64, left_secret: &str) -> Inboxes {
        let (inbox, chunks) = mpsc::channel(INBOX_CHUNKS);
        let (lane_door, lanes) = mpsc::channel(MAX_LANES);
        *self.lock() = Some(Joined {
            generation,
            left_secret: left_secret.to_string(),
            doors: Doors {
                inbox,
                lanes: lane_door,
            },
        });
        self.changed.notify_waiters();
        Inboxes { chunks, lanes }
    }

    /// The doors for traffic of `generation` presenting `secret`, waiting for this rank to
    /// join that generation.
    pub(super) async fn admit(&self, generation: u64, secret: &str) -> Result<Doors, Status> {
        let (doors, left_secret) = self.joined(generation).await?;
        if proto::constant_time_equal(secret.as_bytes(), left_secret.as_bytes()) {
            return Ok(doors);
        }
        tracing::warn!(
            generation,
            "a stream without the left neighbour's secret was refused"
        );
        Err(Status::permission_denied(format!(
            "only this rank's left neighbour of generation {generation} may stream to it"
        )))
    }

    /// The doors of `generation` and the secret its left neighbour holds, once this rank has
    /// joined it (waiting at most [`ADMISSION_WAIT`]); a lane proves the secret without
    /// presenting it (`handshake.rs`).
    pub(super) async fn joined(&self, generation: u64) -> Result<(Doors, String), Status> {
        let deadline = tokio::time::Instant::now() + ADMISSION_WAIT;
        loop {
            let changed = self.changed.notified();
            let current = {
                let joined = self.lock();
                match joined.as_ref() {
                    Some(joined) if joined.generation == generation => {
                        return Ok((joined.doors.clone(), joined.left_secret.clone()));
                    }
                    Some(joined) => Some(joined.generation),
                    None => None,
                }
            };
            if let Some(current) = current.filter(|&current| current > generation) {
                return Err(Status::failed_precondition(format!(
                    "generation {generation} is over: this rank is in generation {current}"
                )));
            }
            if tokio::time::timeout_at(deadline, changed).await.is_err() {
                return Err(Status::deadline_exceeded(format!(
                    "this rank did not join generation {generation} within {} s",
                    ADMISSION_WAIT.as_secs()
                )));
            }
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Option<Joined>> {
        self.joined.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The Collective service: admits the left neighbour's stream and files its chunks into the
/// mailbox.
#[derive(Clone, Default)]
pub struct CollectiveService {
    mailbox: Arc<Mailbox>,
}

impl CollectiveService {
    /// The mailbox rings read from.
    pub fn mailbox(&self) -> Arc<Mailbox> {
        self.mailbox.clone()
    }
}

#[tonic::async_trait]
impl Collective for CollectiveService {
    async fn push(&self, request: Request<Streaming<Chunk>>) -> Result<Response<PushAck>, Status> {
        let span = tracing::debug_span!("rpc_collective_push", peer = ?request.remote_addr());
        let secret = request
            .metadata()
            .get(RING_SECRET_KEY)
            .and_then(|value| value.to_str().ok())
            .unwrap_or_default()
            .to_string();
        self.receive_stream(request.into_inner(), secret)
            .instrument(span)
            .await
    }
}

impl CollectiveService {
    async fn receive_stream(
        &self,
        mut stream: Streaming<Chunk>,
        secret: String,
    ) -> Result<Response<PushAck>, Status> {
        let Some(first) = stream.message().await? else {
            return Ok(Response::new(PushAck { chunks: 0 }));
        };
        let generation = first.generation;
        let inbox = self.mailbox.admit(generation, &secret).await?.inbox;
        let mut next = Some(first);
        let mut chunks = 0u64;
        loop {
            let chunk = match next.take() {
                Some(chunk) => chunk,
                None => match stream.message().await {
                    Ok(Some(chunk)) => chunk,
                    Ok(None) => return Ok(Response::new(PushAck { chunks })),
                    Err(status) => {
                        let _ = inbox
                            .send(Err(InboundFailure::Stream(status.clone())))
                            .await;
                        return Err(status);
                    }
                },
            };
            if chunk.generation != generation {
                let failure = InboundFailure::WrongGeneration {
                    found: chunk.generation,
                    expected: generation,
                };
                let reason = failure.to_string();
                let _ = inbox.send(Err(failure)).await;
                return Err(Status::invalid_argument(reason));
            }
            chunks += 1;
            if inbox.send(Ok(chunk)).await.is_err() {
                return Err(Status::cancelled("this rank left the generation"));
            }
        }
    }
}

/// Serves `service` on `listener` (see [`server`]) on a task of its own until the process
/// ends; the returned reporter changes what the health service says.
pub fn spawn_server(
    listener: tokio::net::TcpListener,
    service: CollectiveService,
    link: &Link,
) -> Result<tonic_health::server::HealthReporter, super::CollectiveError> {
    let (reporter, serving) = server(listener, service, link)?;
    tokio::spawn(serving);
    Ok(reporter)
}

/// The server of `service` on `listener` behind the job-token check (and TLS when `link` has
/// it), with flow-control windows sized for megabyte chunks, and `grpc.health.v1` beside it
/// without the check; lane connections on the same port go to the mailbox
/// (`desk.rs`). It serves until dropped. Also returns the health service's reporter.
pub fn server(
    listener: tokio::net::TcpListener,
    service: CollectiveService,
    link: &Link,
) -> Result<
    (
        tonic_health::server::HealthReporter,
        impl std::future::Future<Output = ()> + Send + 'static,
    ),
    super::CollectiveError,
> {
    let mailbox = service.mailbox();
    let server = tonic::service::interceptor::InterceptedService::new(
        proto::v1::collective_server::CollectiveServer::new(service)
            .max_decoding_message_size(proto::MAX_MESSAGE_BYTES),
        proto::RequireToken::new(&link.token),
    );
    let mut builder = tonic::transport::Server::builder();
    if let Some(tls) = &link.tls {
        builder = builder
            .tls_config(tls.server.clone())
            .map_err(|e| super::CollectiveError::Tls(e.to_string()))?;
    }
    let (reporter, health) = tonic_health::server::health_reporter();
    let serving = reporter.clone();
    let (grpc, incoming) = mpsc::channel(MAX_LANES);
    let lanes = super::desk::LaneDesk::new(
        mailbox.clone(),
        link.tls.as_ref().map(|tls| tls.lane_server.clone()),
    );
    let run = async move {
        serving
            .set_serving::<proto::v1::collective_server::CollectiveServer<CollectiveService>>()
            .await;
        // Beside the token-checked service, not behind it: probes carry no token.
        let served = builder
            .initial_stream_window_size(Some(16 * 1024 * 1024))
            .initial_connection_window_size(Some(32 * 1024 * 1024))
            .max_frame_size(Some(1024 * 1024))
            .add_service(server)
            .add_service(health)
            .serve_with_incoming(tokio_stream::wrappers::ReceiverStream::new(incoming));
        tokio::select! {
            served = served => if let Err(error) = served {
                tracing::warn!(%error, "the collective server stopped");
            },
            () = lanes.route(listener, grpc) => {}
        }
    };
    Ok((reporter, run))
}
