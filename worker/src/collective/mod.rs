//! The ring all-reduce between workers over gRPC streams.
//!
//! Each rank streams chunks to its right neighbour (one client stream per generation) and
//! receives its left neighbour's chunks through its own Collective service. The buffer is cut
//! into one segment per rank; `n - 1` reduce-scatter steps followed by `n - 1` all-gather steps
//! move `2 (n - 1) / n` of the buffer per rank, which is bandwidth-optimal. Segments travel as
//! chunks, and a chunk is forwarded as soon as it has been reduced, so the steps overlap
//! (pipelining) instead of waiting for whole segments. Every generation's streams carry
//! secrets the coordinator hands out with the assignment, so a rank accepts chunks only from
//! its left neighbour of that generation ([`service`]).

use std::time::{Duration, Instant};

use proto::v1::Chunk;
use proto::v1::collective_client::CollectiveClient;
use tokio::sync::mpsc;
use tokio_stream::wrappers::UnboundedReceiverStream;
use tokio_util::sync::CancellationToken;

mod carrier;
mod core;
mod desk;
mod handshake;
mod lane;
mod lanes;
mod opening;
mod records;
mod schedule;
mod service;
mod tls_handshake;
mod wire;

use core::{Attempt, GaveUp, Place, check_place, left_of, right_of, take_in, with_retries};
pub use desk::{MAX_HANDSHAKES, MAX_HANDSHAKES_PER_ADDRESS};
use lane::Lane;
use schedule::{Delivery, Schedule};
use service::{AdmittedLane, Inbound};
pub use service::{
    CollectiveService, INBOX_CHUNKS, MAX_LANES, Mailbox, RING_SECRET_KEY, RingKeys, server,
    spawn_server,
};
use wire::Encoding;
pub use wire::WireFormat;

/// Values per chunk (1 MiB of `f32`): big enough to amortise per-message costs, small enough to
/// pipeline.
pub const CHUNK_VALUES: usize = 256 * 1024;

/// What went wrong in a collective. The caller's buffer may be partly reduced and must be
/// discarded; the model was not touched.
#[derive(Debug, Clone, thiserror::Error)]
pub enum CollectiveError {
    /// The right neighbour could not be reached.
    #[error("cannot reach rank {rank} at {address}: {reason}")]
    Connect {
        /// Its rank.
        rank: usize,
        /// Its address.
        address: String,
        /// Why.
        reason: String,
    },
    /// The right neighbour's stream closed (it died or left).
    #[error("stream to rank {rank} closed: the peer is gone")]
    PeerGone {
        /// Its rank.
        rank: usize,
    },
    /// The left neighbour's stream failed or ended early.
    #[error("stream from rank {rank} broke: {reason}")]
    InboundBroken {
        /// Its rank.
        rank: usize,
        /// Why.
        reason: String,
    },
    /// A chunk did not match what the ring expected.
    #[error("rank {rank} sent a bad chunk: {detail}")]
    BadChunk {
        /// The rank whose authenticated stream delivered it: the left neighbour, the only one
        /// whose ring secret this rank's inbox admits (never the chunk's own `sender` field,
        /// which its writer chose).
        rank: usize,
        /// What was wrong.
        detail: String,
    },
    /// Nothing arrived for too long.
    #[error("no chunk from rank {rank} for {seconds:.0} s")]
    Timeout {
        /// The silent rank.
        rank: usize,
        /// How long we waited.
        seconds: f64,
    },
    /// The coordinator abandoned the generation.
    #[error("generation abandoned by the coordinator")]
    Cancelled,
    /// The task running the all-reduce died (a panic); the ring is gone with it.
    #[error("the all-reduce task died: {0}")]
    Aborted(String),
    /// The TLS settings could not be applied to the collective server.
    #[error("collective TLS: {0}")]
    Tls(String),
}

/// How ranks reach each other: the job token every chunk stream carries, the longest wait for
/// a peer, and TLS when the job runs it (every rank must then serve and dial TLS).
#[derive(Clone)]
pub struct Link {
    /// The job token.
    pub token: String,
    /// Longest wait for a peer to connect or for its next chunk.
    pub timeout: Duration,
    /// TLS for the Collective service and for dialling peers; `None`: plain HTTP/2.
    pub tls: Option<PeerTls>,
    /// TCP lanes the ring runs on (`lane`; TLS sessions of their own when the job runs TLS),
    /// each on a thread of its own; 0: the chunks travel as messages of one gRPC stream. Every
    /// rank of a ring must use the same number.
    pub lanes: usize,
}

/// A rank's TLS: its own server identity and the trust it puts in its peers', for the gRPC
/// stream (through tonic) and for the lanes (rustls driven by the lane).
#[derive(Clone)]
pub struct PeerTls {
    /// This rank's certificate and key, for its Collective service.
    server: tonic::transport::ServerTlsConfig,
    /// The same identity for the lanes this rank accepts.
    lane_server: std::sync::Arc<rustls::ServerConfig>,
    /// Trust in the CA that signed the peers' certificates, for the lanes this rank dials.
    lane_client: std::sync::Arc<rustls::ClientConfig>,
    /// The CA that signed the peers' certificates.
    ca: std::path::PathBuf,
    /// The name every peer's certificate must carry; `None`: each peer's own host (name or
    /// IP address), so one certificate per host works.
    domain: Option<String>,
}

impl PeerTls {
    /// A rank's TLS from its certificate `cert` and key `key` (PEM), trusting peers whose
    /// certificates `ca` signed and carry `domain` (`None`: each peer's own host); a file
    /// that cannot be used is named.
    pub fn from_files(
        cert: &std::path::Path,
        key: &std::path::Path,
        ca: &std::path::Path,
        domain: Option<String>,
    ) -> Result<Self, proto::tls::TlsError> {
        let server = proto::tls::server_config(cert, key)?;
        proto::tls::client_config(ca, domain.as_deref().unwrap_or("localhost"))?;
        Ok(Self {
            server,
            lane_server: proto::tls::lane_server_config(cert, key)?,
            lane_client: proto::tls::lane_client_config(ca)?,
            ca: ca.to_path_buf(),
            domain,
        })
    }

    /// The name the peer at `address` must show.
    fn name_for<'a>(&'a self, address: &'a str) -> &'a str {
        let host = address
            .rsplit_once(':')
            .map_or(address, |(host, _)| host)
            .trim_start_matches('[')
            .trim_end_matches(']');
        self.domain.as_deref().unwrap_or(host)
    }

    fn client_for(
        &self,
        address: &str,
    ) -> Result<tonic::transport::ClientTlsConfig, proto::tls::TlsError> {
        proto::tls::client_config(&self.ca, self.name_for(address))
    }

    /// How lanes dial the peer at `address`; refused when its name is not a DNS name or an
    /// IP address.
    fn lane_client_for(
        &self,
        address: &str,
    ) -> Result<opening::LaneTlsClient, rustls::pki_types::InvalidDnsNameError> {
        let name = rustls::pki_types::ServerName::try_from(self.name_for(address).to_string())?;
        Ok(opening::LaneTlsClient {
            config: self.lane_client.clone(),
            name,
        })
    }
}

/// Figures of one all-reduce.
#[derive(Debug, Clone, Copy, Default)]
pub struct ReduceStats {
    /// Wall time.
    pub seconds: f64,
    /// Bytes this rank sent.
    pub bytes_sent: u64,
}

/// One rank's place in the ring of a generation.
pub struct Ring {
    rank: usize,
    world: usize,
    generation: u64,
    operation: u64,
    outbound: Option<mpsc::UnboundedSender<Chunk>>,
    inbox: Option<mpsc::Receiver<Inbound>>,
    cancel: CancellationToken,
    timeout: Duration,
    chunk_values: usize,
    wire: WireFormat,
    /// The ring's lanes; empty: it runs on the gRPC stream.
    lanes: Vec<Lane>,
}

impl Ring {
    /// Joins the ring of `generation`: opens the stream to the right neighbour (presenting
    /// `keys.own`) and takes this rank's inbox, which admits only the stream presenting
    /// `keys.left`. `cancel` cancelled aborts any all-reduce in progress.
    pub async fn connect(
        mailbox: &Mailbox,
        rank: usize,
        peers: &[String],
        generation: u64,
        keys: &RingKeys,
        link: &Link,
        cancel: CancellationToken,
    ) -> Result<Self, CollectiveError> {
        let world = peers.len().max(1);
        let mut ring = Self {
            rank,
            world,
            generation,
            operation: 0,
            outbound: None,
            inbox: None,
            cancel,
            timeout: link.timeout,
            chunk_values: CHUNK_VALUES,
            wire: WireFormat::F32,
            lanes: Vec::new(),
        };
        if world == 1 {
            return Ok(ring);
        }
        // Joined first, so the left neighbour's stream is admitted while this rank dials.
        let inboxes = mailbox.join(generation, &keys.left);
        let address = &peers[ring.right_rank()];
        if link.lanes > 0 {
            let hello = proto::v1::LaneHello {
                generation,
                lane: 0,
                lanes: link.lanes as u32,
                nonce: Vec::new(),
            };
            let tls =
                match &link.tls {
                    Some(tls) => Some(tls.lane_client_for(address).map_err(|e| {
                        CollectiveError::Connect {
                            rank: ring.right_rank(),
                            address: address.clone(),
                            reason: format!("its name cannot be a certificate's: {e}"),
                        }
                    })?),
                    None => None,
                };
            ring.lanes = ring
                .open_lanes(address, hello, &keys.own, tls.as_ref(), inboxes.lanes)
                .await?;
        } else {
            ring.inbox = Some(inboxes.chunks);
            ring.outbound = Some(ring.open_stream(address, keys, link).await?);
        }
        Ok(ring)
    }

    /// Opens the gRPC stream to the right neighbour at `address`, presenting `keys.own`;
    /// returns where its chunks are queued.
    async fn open_stream(
        &self,
        address: &str,
        keys: &RingKeys,
        link: &Link,
    ) -> Result<mpsc::UnboundedSender<Chunk>, CollectiveError> {
        let right = self.right_rank();
        let failed = |reason: String| CollectiveError::Connect {
            rank: right,
            address: address.to_string(),
            reason,
        };
        let scheme = proto::tls::scheme(link.tls.is_some());
        let mut endpoint = tonic::transport::Endpoint::from_shared(format!("{scheme}://{address}"))
            .map_err(|e| failed(e.to_string()))?;
        if let Some(tls) = &link.tls {
            endpoint = endpoint
                .tls_config(tls.client_for(address).map_err(|e| failed(e.to_string()))?)
                .map_err(|e| failed(e.to_string()))?;
        }
        let endpoint = endpoint
            .tcp_nodelay(true)
            .initial_stream_window_size(Some(16 * 1024 * 1024))
            .initial_connection_window_size(Some(32 * 1024 * 1024))
            .connect_timeout(Duration::from_secs(2));
        let deadline = tokio::time::Instant::now() + self.timeout;
        // A right neighbour that died before the ring formed would hold this rank here for
        // the whole timeout; the coordinator's end of the generation releases it at once.
        let endpoint = &endpoint;
        let channel = with_retries(deadline, &self.cancel, || async move {
            let connected = endpoint.connect().await;
            connected.map_err(|e| Attempt::Again(e.to_string()))
        })
        .await
        .map_err(|gave_up| self.connect_failed(address, gave_up))?;
        let attach = proto::AttachToken::new(&link.token).map_err(|e| failed(e.to_string()))?;
        let mut client = CollectiveClient::with_interceptor(channel, attach)
            .max_encoding_message_size(proto::MAX_MESSAGE_BYTES);
        let secret = tonic::metadata::MetadataValue::try_from(keys.own.as_str())
            .map_err(|e| failed(format!("ring secret: {e}")))?;
        let (sender, receiver) = mpsc::unbounded_channel();
        let mut request = tonic::Request::new(UnboundedReceiverStream::new(receiver));
        request.metadata_mut().insert(RING_SECRET_KEY, secret);
        tokio::spawn(async move {
            if let Err(status) = client.push(request).await {
                tracing::warn!(peer = right, error = %status.message(), "collective stream ended");
            }
        });
        Ok(sender)
    }

    /// Ranks in the ring.
    pub fn world_size(&self) -> usize {
        self.world
    }

    /// The rank whose chunks this rank receives.
    fn left_rank(&self) -> usize {
        left_of(self.rank, self.world)
    }

    /// The rank this rank sends its chunks to.
    fn right_rank(&self) -> usize {
        right_of(self.rank, self.world)
    }

    /// The error of a connection to the right neighbour at `address` that gave up.
    fn connect_failed(&self, address: &str, gave_up: GaveUp) -> CollectiveError {
        match gave_up {
            GaveUp::Cancelled => CollectiveError::Cancelled,
            GaveUp::Failed(reason) => CollectiveError::Connect {
                rank: self.right_rank(),
                address: address.to_string(),
                reason,
            },
        }
    }

    /// This ring with gradients carried as `wire` (every rank of a generation must use the
    /// same; a chunk of another width fails the size check and names its sender).
    pub fn with_wire(mut self, wire: WireFormat) -> Self {
        self.wire = wire;
        self
    }

    /// Changes the chunk size (tests use small chunks to exercise the pipeline).
    pub fn set_chunk_values(&mut self, values: usize) {
        self.chunk_values = values.max(1);
    }

    /// The cut of a buffer of `len` values.
    fn schedule(&self, len: usize) -> Schedule {
        Schedule {
            world: self.world,
            rank: self.rank,
            chunk_values: self.chunk_values,
            len,
        }
    }

    fn send(
        &self,
        ring_step: u32,
        segment: usize,
        begin: usize,
        values: &[f32],
        encoding: &Encoding,
    ) -> Result<usize, CollectiveError> {
        let chunk = Chunk {
            generation: self.generation,
            operation: self.operation,
            ring_step,
            segment: segment as u32,
            offset: begin as u64,
            values: encoding.encode(begin, values),
            sender: self.rank as u32,
        };
        let bytes = chunk.values.len();
        let gone = CollectiveError::PeerGone {
            rank: self.right_rank(),
        };
        let outbound = self.outbound.as_ref().ok_or(gone)?;
        outbound
            .send(chunk)
            .map_err(|_| CollectiveError::PeerGone {
                rank: self.right_rank(),
            })
            .map(|()| bytes)
    }

    async fn receive(&mut self) -> Result<Chunk, CollectiveError> {
        let left = self.left_rank();
        let timeout = self.timeout;
        let inbox = self.inbox.as_mut().ok_or(CollectiveError::InboundBroken {
            rank: left,
            reason: "no inbox".into(),
        })?;
        let cancel = &self.cancel;
        if cancel.is_cancelled() {
            return Err(CollectiveError::Cancelled);
        }
        tokio::select! {
            message = inbox.recv() => match message {
                Some(Ok(chunk)) => Ok(chunk),
                Some(Err(failure)) => Err(CollectiveError::InboundBroken { rank: left, reason: failure.to_string() }),
                None => Err(CollectiveError::InboundBroken { rank: left, reason: "stream closed".into() }),
            },
            () = cancel.cancelled() => Err(CollectiveError::Cancelled),
            () = tokio::time::sleep(timeout) => Err(CollectiveError::Timeout { rank: left, seconds: timeout.as_secs_f64() }),
        }
    }

    /// [`Ring::all_reduce`] from a thread outside the runtime: on the ring's lanes, on
    /// threads of their own; on the gRPC stream, as a task on `runtime`'s worker threads,
    /// where the stream's I/O runs, so chunks go from socket to reduction without a hand-off
    /// between threads. Blocking; returns the ring and the summed values.
    pub fn all_reduce_on(
        mut self,
        runtime: &tokio::runtime::Runtime,
        mut values: Vec<f32>,
        exact_tail: usize,
    ) -> Result<(Self, Vec<f32>, ReduceStats), CollectiveError> {
        if !self.lanes.is_empty() {
            let stats = self.reduce_on_lanes(&mut values, exact_tail)?;
            return Ok((self, values, stats));
        }
        let task = runtime.spawn(async move {
            let stats = self.all_reduce(&mut values, exact_tail).await;
            stats.map(|stats| (self, values, stats))
        });
        runtime
            .block_on(task)
            .map_err(|e| CollectiveError::Aborted(e.to_string()))?
    }

    /// Sums `values` element-wise across all ranks, in place; every rank ends with the same
    /// sum. The last `exact_tail` values travel in float32 whatever the ring's wire. On lanes
    /// the calling thread blocks (a multi-threaded runtime moves its other tasks away first).
    pub async fn all_reduce(
        &mut self,
        values: &mut [f32],
        exact_tail: usize,
    ) -> Result<ReduceStats, CollectiveError> {
        if !self.lanes.is_empty() {
            let multi_threaded = tokio::runtime::Handle::current().runtime_flavor()
                == tokio::runtime::RuntimeFlavor::MultiThread;
            return if multi_threaded {
                tokio::task::block_in_place(|| self.reduce_on_lanes(values, exact_tail))
            } else {
                self.reduce_on_lanes(values, exact_tail)
            };
        }
        let start = Instant::now();
        let (n, r) = (self.world, self.rank);
        if n == 1 {
            return Ok(ReduceStats::default());
        }
        let schedule = self.schedule(values.len());
        let encoding = Encoding {
            wire: self.wire,
            exact_from: values.len().saturating_sub(exact_tail),
        };
        let mut bytes_sent = 0u64;
        for (a, b) in schedule.first_sends() {
            bytes_sent += self.send(0, r, a, &values[a..b], &encoding)? as u64;
        }
        for delivery in schedule.deliveries() {
            let chunk = self.receive().await?;
            self.check(&chunk, &delivery, &encoding)?;
            let target = &mut values[delivery.begin..delivery.end];
            if take_in(&schedule, &encoding, &delivery, target, Some(&chunk.values)) {
                let step = delivery.step as u32 + 1;
                bytes_sent +=
                    self.send(step, delivery.segment, delivery.begin, target, &encoding)? as u64;
            }
        }
        self.operation += 1;
        Ok(ReduceStats {
            seconds: start.elapsed().as_secs_f64(),
            bytes_sent,
        })
    }

    /// Checks a chunk from the stream against `delivery`, the chunk the schedule delivers
    /// next: the stream's own fields (its sender, its generation), then its place.
    fn check(
        &self,
        chunk: &Chunk,
        delivery: &Delivery,
        encoding: &Encoding,
    ) -> Result<(), CollectiveError> {
        let left = self.left_rank();
        let bad = |detail: String| Err(CollectiveError::BadChunk { rank: left, detail });
        if chunk.sender as usize != left {
            return bad(format!(
                "its stream carried a chunk claiming to be from rank {}",
                chunk.sender
            ));
        }
        if chunk.generation != self.generation {
            return bad(format!(
                "generation {}, expected generation {}",
                chunk.generation, self.generation
            ));
        }
        let place = Place {
            operation: chunk.operation,
            ring_step: u64::from(chunk.ring_step),
            segment: u64::from(chunk.segment),
            offset: chunk.offset,
            value_bytes: chunk.values.len() as u64,
        };
        check_place(&place, self.operation, delivery, encoding).or_else(|m| bad(m.0))
    }
}
