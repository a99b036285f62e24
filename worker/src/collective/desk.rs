//! The collective port's front desk: every connection is sorted by its first bytes into a
//! lane (plain, or TLS when the ring runs it), a gRPC connection (HTTP/2's preface or TLS) or
//! a stranger's (closed), and a lane is admitted only once it has proved that it holds the
//! left neighbour's ring secret (`handshake.rs`).
//!
//! Anyone who can reach the port can connect to it, so what a stranger can make a rank hold
//! is bounded before anything is authenticated: at most [`MAX_HANDSHAKES`] connections are
//! being sorted or handshaking at once, at most [`MAX_HANDSHAKES_PER_ADDRESS`] of them from one
//! address (a connection past either limit is closed at once, and the neighbour's own lanes,
//! from its own address, keep their room); each has [`HANDSHAKE_WAIT`] to show itself, finish
//! its TLS handshake, say hello and answer the challenge; a handshake message is at most 1 KiB; only whole openings
//! reach the gRPC server; and refusals are logged at most once per [`WARNING_INTERVAL`], with
//! the count of those not logged.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;

use super::carrier::Carrier;
use super::opening::{
    HandshakeError, LANE_MAGIC, TLS_LANE_MAGIC, answer, challenge, read_hello, read_magic, refuse,
};
use super::service::{AdmittedLane, Doors, MAX_LANES, Mailbox};
use super::tls_handshake::{self, TlsHandshakeError};

/// Connections being sorted or handshaking at once, from everyone.
pub const MAX_HANDSHAKES: usize = 512;

/// Connections being sorted or handshaking at once from one address: room for every lane of
/// a neighbour's ring, retried.
pub const MAX_HANDSHAKES_PER_ADDRESS: usize = 2 * MAX_LANES;

/// Longest a new connection may take to show what it is, and a lane to say hello and to
/// answer the challenge.
const HANDSHAKE_WAIT: Duration = Duration::from_secs(5);

/// Refusals of strangers are logged at most this often.
const WARNING_INTERVAL: Duration = Duration::from_secs(10);

/// HTTP/2's client connection preface.
const HTTP2_PREFACE: &[u8; 24] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";

/// The first byte of a TLS handshake record.
const TLS_HANDSHAKE: u8 = 0x16;

/// The listener's desk for lane connections: they share the Collective port with gRPC and
/// are told apart by their first bytes.
pub(super) struct LaneDesk {
    mailbox: Arc<Mailbox>,
    tls: Option<Arc<rustls::ServerConfig>>,
    handshakes: Mutex<InProgress>,
    refusals: Warnings,
}

/// Connections being sorted or handshaking, in all and by address.
#[derive(Default)]
struct InProgress {
    total: usize,
    by_address: HashMap<IpAddr, usize>,
}

/// A connection's room among the handshakes in progress; given back when dropped.
struct Slot {
    desk: Arc<LaneDesk>,
    address: IpAddr,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut handshakes = self.desk.lock_handshakes();
        handshakes.total = handshakes.total.saturating_sub(1);
        if let Some(count) = handshakes.by_address.get_mut(&self.address) {
            *count = count.saturating_sub(1);
            if *count == 0 {
                handshakes.by_address.remove(&self.address);
            }
        }
    }
}

/// What a connection opened with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Opening {
    /// [`LANE_MAGIC`] or, for a TLS lane, [`TLS_LANE_MAGIC`].
    Lane,
    /// HTTP/2's whole preface, or a TLS record (the gRPC server's TLS takes it from there).
    Grpc,
    /// Anything else, or nothing within [`HANDSHAKE_WAIT`]: closed.
    Neither,
}

impl LaneDesk {
    /// The desk of a rank whose ring files lanes into `mailbox`; with `tls`, the ring runs
    /// over TLS with these settings, and a plain lane is refused.
    pub(super) fn new(mailbox: Arc<Mailbox>, tls: Option<Arc<rustls::ServerConfig>>) -> Self {
        Self {
            mailbox,
            tls,
            handshakes: Mutex::new(InProgress::default()),
            refusals: Warnings::default(),
        }
    }

    /// Accepts connections until the listener fails: lanes are admitted here, gRPC
    /// connections handed to the gRPC server through `grpc`, the rest closed. Each connection
    /// is sorted on a task of its own, so a silent one holds up nobody.
    pub(super) async fn route(
        self,
        listener: TcpListener,
        grpc: mpsc::Sender<std::io::Result<TcpStream>>,
    ) {
        let desk = Arc::new(self);
        loop {
            let (stream, peer) = match listener.accept().await {
                Ok(accepted) => accepted,
                Err(error) => {
                    // Out of descriptors, say: handshakes in progress end within their wait.
                    desk.refusals.warn(&format!(
                        "the collective listener could not accept: {error}"
                    ));
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            };
            let Some(slot) = Self::enter(&desk, peer.ip()) else {
                desk.refusals.warn(&format!(
                    "connection from {peer} closed: too many handshakes in progress"
                ));
                continue;
            };
            // Chunks are small and latency-bound at the pipeline's ends.
            let _ = stream.set_nodelay(true);
            let grpc = grpc.clone();
            tokio::spawn(async move {
                match sort(&stream).await {
                    Opening::Lane => slot.desk.clone().admit(stream, slot).await,
                    Opening::Grpc => {
                        drop(slot);
                        let _ = grpc.send(Ok(stream)).await;
                    }
                    Opening::Neither => slot.desk.refusals.warn(&format!(
                        "connection from {peer} closed: it opened with neither a lane's magic, HTTP/2's preface nor a TLS hello"
                    )),
                }
            });
        }
    }

    /// A slot for a connection from `address`, if the limits leave room.
    fn enter(desk: &Arc<Self>, address: IpAddr) -> Option<Slot> {
        let mut handshakes = desk.lock_handshakes();
        let from_address = handshakes.by_address.get(&address).copied().unwrap_or(0);
        if handshakes.total >= MAX_HANDSHAKES || from_address >= MAX_HANDSHAKES_PER_ADDRESS {
            return None;
        }
        handshakes.total += 1;
        handshakes.by_address.insert(address, from_address + 1);
        Some(Slot {
            desk: desk.clone(),
            address,
        })
    }

    fn lock_handshakes(&self) -> std::sync::MutexGuard<'_, InProgress> {
        self.handshakes.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Reads a lane's magic, runs TLS when it asks for it, reads its hello, challenges it,
    /// and hands a proven lane to its ring, which answers it once taken. `slot` is held until
    /// the lane is handed on or refused.
    async fn admit(self: Arc<Self>, tcp: TcpStream, slot: Slot) {
        let opened = tokio::time::timeout(HANDSHAKE_WAIT, self.open(tcp)).await;
        let (mut stream, hello) = match opened {
            Ok(Ok(opened)) => opened,
            Ok(Err(failed)) => {
                self.refusals.warn(&failed.to_string());
                return;
            }
            Err(_) => return,
        };
        let generation = hello.generation;
        let (doors, secret) = match self.check(&hello).await {
            Ok(admitted) => admitted,
            Err(refusal) => {
                self.refusals.warn(&format!(
                    "a lane of generation {generation} was refused: {refusal}"
                ));
                let _ = refuse(&mut stream, &refusal.to_string()).await;
                return;
            }
        };
        let proven =
            tokio::time::timeout(HANDSHAKE_WAIT, challenge(&mut stream, &hello, &secret)).await;
        if !matches!(proven, Ok(Ok(true))) {
            self.refusals.warn(&format!(
                "a lane of generation {generation} did not prove the ring's secret"
            ));
            return;
        }
        drop(slot);
        let lane = AdmittedLane {
            lane: hello.lane,
            lanes: hello.lanes,
            stream,
        };
        if let Err(mpsc::error::SendError(mut lane)) = doors.lanes.send(lane).await {
            let _ = answer(&mut lane.stream, "this rank's ring is no longer open").await;
        }
    }

    /// A lane connection up to its hello: its magic, then TLS if it asked for it and this
    /// rank's ring runs it (a lane that asks otherwise than the ring runs is refused, a
    /// plain one with a reason), then its hello.
    async fn open(
        &self,
        mut tcp: TcpStream,
    ) -> Result<(Carrier, proto::v1::LaneHello), OpeningFailed> {
        let wants_tls = read_magic(&mut tcp).await?;
        let mut stream = match (&self.tls, wants_tls) {
            (None, false) => Carrier::Plain(tcp),
            (Some(config), true) => {
                let records = tls_handshake::as_server(tcp, config.clone())
                    .await
                    .map_err(OpeningFailed::Tls)?;
                Carrier::Tls(Box::new(records))
            }
            (Some(_), false) => {
                let _ = refuse(&mut tcp, &LaneRefusal::Tls.to_string()).await;
                return Err(OpeningFailed::PlainToTls);
            }
            (None, true) => return Err(OpeningFailed::TlsToPlain),
        };
        let hello = read_hello(&mut stream).await?;
        Ok((stream, hello))
    }

    /// Where `hello`'s lane goes and the secret its dialler must prove, once this rank has
    /// joined its generation.
    async fn check(&self, hello: &proto::v1::LaneHello) -> Result<(Doors, String), LaneRefusal> {
        if hello.lanes == 0 || hello.lane >= hello.lanes || hello.lanes as usize > MAX_LANES {
            return Err(LaneRefusal::NoSuchLane {
                lane: hello.lane,
                lanes: hello.lanes,
            });
        }
        self.mailbox
            .joined(hello.generation)
            .await
            .map_err(|status| LaneRefusal::Ring(status.message().to_string()))
    }
}

/// Why a lane connection never got as far as its hello (logged, rate-limited).
#[derive(Debug, thiserror::Error)]
enum OpeningFailed {
    /// Its magic or hello could not be read.
    #[error("a lane connection sent no readable hello: {0}")]
    Unreadable(#[from] HandshakeError),
    /// The TLS handshake failed.
    #[error("a lane's TLS handshake failed: {0}")]
    Tls(TlsHandshakeError),
    /// A plain lane to a ring that runs TLS (refused with the reason).
    #[error("a plain lane was refused: this rank's ring runs over TLS")]
    PlainToTls,
    /// A TLS lane to a ring that runs without (closed: it cannot read a refusal).
    #[error("a TLS lane was closed: this rank's ring runs without TLS")]
    TlsToPlain,
}

/// Why a lane was not admitted (sent back as its challenge's refusal).
#[derive(Debug, thiserror::Error)]
enum LaneRefusal {
    /// This rank's ring runs over TLS and the lane did not ask for it.
    #[error("this rank's ring runs over TLS, and the lane is plain")]
    Tls,
    /// The lane's place is impossible.
    #[error("lane {lane} of {lanes} (at most {MAX_LANES} lanes)")]
    NoSuchLane {
        /// Which lane it claimed to be.
        lane: u32,
        /// Of how many.
        lanes: u32,
    },
    /// The ring's own admission refused it (a stale generation, or this rank never joined
    /// its generation).
    #[error("{0}")]
    Ring(String),
}

/// Warnings about strangers, at most one per [`WARNING_INTERVAL`]: a flood must not flood
/// the log too.
#[derive(Default)]
struct Warnings {
    state: Mutex<(Option<Instant>, u64)>,
}

impl Warnings {
    /// Logs `message` unless one was logged within the interval; counts it then, and says how
    /// many were left out with the next one logged.
    fn warn(&self, message: &str) {
        let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        let (last, suppressed) = &mut *state;
        let now = Instant::now();
        if last.is_some_and(|last| now.duration_since(last) < WARNING_INTERVAL) {
            *suppressed += 1;
            return;
        }
        tracing::warn!(suppressed_since_last = *suppressed, "{message}");
        *last = Some(now);
        *suppressed = 0;
    }
}

/// What `stream` opens with, from its first bytes (waiting for them at most
/// [`HANDSHAKE_WAIT`]); gRPC clients speak first too. Only whole openings pass, so junk never
/// reaches the gRPC server.
async fn sort(stream: &TcpStream) -> Opening {
    let sniff = async {
        let mut first = [0u8; HTTP2_PREFACE.len()];
        loop {
            let seen = match stream.peek(&mut first).await {
                Ok(0) | Err(_) => return Opening::Neither,
                Ok(seen) => seen,
            };
            if let Some(opening) = classify(&first[..seen]) {
                return opening;
            }
            // A prefix of an opening so far: look again once more has come.
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    };
    tokio::time::timeout(HANDSHAKE_WAIT, sniff)
        .await
        .unwrap_or(Opening::Neither)
}

/// What the bytes `seen` so far open; `None` while they are a prefix of an opening.
fn classify(seen: &[u8]) -> Option<Opening> {
    let prefix_of = |whole: &[u8]| whole.starts_with(&seen[..seen.len().min(whole.len())]);
    if seen.first() == Some(&TLS_HANDSHAKE) {
        return Some(Opening::Grpc);
    }
    if seen.starts_with(LANE_MAGIC) || seen.starts_with(TLS_LANE_MAGIC) {
        return Some(Opening::Lane);
    }
    if seen.starts_with(HTTP2_PREFACE) {
        return Some(Opening::Grpc);
    }
    if prefix_of(LANE_MAGIC) || prefix_of(TLS_LANE_MAGIC) || prefix_of(HTTP2_PREFACE) {
        return None;
    }
    Some(Opening::Neither)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn openings_are_sorted_only_once_whole() {
        assert_eq!(classify(b"XFLA"), None);
        assert_eq!(classify(b"XFLANE01"), Some(Opening::Lane));
        assert_eq!(classify(b"XFLANE1S"), Some(Opening::Lane));
        assert_eq!(classify(b"PRI * HTTP/2.0"), None);
        assert_eq!(classify(HTTP2_PREFACE), Some(Opening::Grpc));
        assert_eq!(classify(&[TLS_HANDSHAKE, 3, 1]), Some(Opening::Grpc));
        assert_eq!(classify(b"GET / HTTP/1.1"), Some(Opening::Neither));
        assert_eq!(classify(b"XFLANE02"), Some(Opening::Neither));
        assert_eq!(classify(&[0xff; 24]), Some(Opening::Neither));
    }

    #[test]
    fn warnings_within_the_interval_are_counted_not_logged() {
        let warnings = Warnings::default();
        for _ in 0..1000 {
            warnings.warn("refused");
        }
        let suppressed = warnings.state.lock().unwrap().1;
        assert_eq!(suppressed, 999);
    }

    #[test]
    fn handshakes_are_capped_per_address_and_in_all_and_slots_come_back() {
        let desk = Arc::new(LaneDesk::new(Arc::new(Mailbox::default()), None));
        let stranger: IpAddr = "10.0.0.9".parse().unwrap();
        let slots: Vec<Slot> = (0..MAX_HANDSHAKES_PER_ADDRESS)
            .map(|_| LaneDesk::enter(&desk, stranger).unwrap())
            .collect();
        assert!(
            LaneDesk::enter(&desk, stranger).is_none(),
            "the stranger's room is full"
        );
        let neighbour: IpAddr = "10.0.0.2".parse().unwrap();
        assert!(
            LaneDesk::enter(&desk, neighbour).is_some(),
            "the neighbour keeps its room"
        );
        drop(slots);
        assert_eq!(desk.lock_handshakes().total, 0);
        assert!(desk.lock_handshakes().by_address.is_empty());
        let many: Vec<Slot> = (0..MAX_HANDSHAKES)
            .map(|i| {
                let address = IpAddr::from([10, 1, (i / 200) as u8, (i % 200) as u8]);
                LaneDesk::enter(&desk, address).unwrap()
            })
            .collect();
        assert!(
            LaneDesk::enter(&desk, neighbour).is_none(),
            "no room left at all"
        );
        drop(many);
        assert!(LaneDesk::enter(&desk, neighbour).is_some());
    }
}
