//! The ring's lanes: TCP connections (plain, or TLS sessions driven by hand: `carrier.rs`)
//! that carry chunks as views of the buffer.
//!
//! Over gRPC every chunk is copied four times in user space (into its message, into the
//! encoder's buffer, into the decoder's, and out into the sum), which bounds the ring at about
//! a gigabyte a second per core. A lane writes each chunk straight from the buffer to its
//! socket and reads it straight into the sum's place (a kept value) or into one staging buffer
//! it is added from, so the kernel's two copies are the only ones. The handshake and every
//! chunk's header are the proto's messages, each preceded by its length; the connection's
//! opening, where both sides prove that they hold the ring's secret without sending it, is
//! `opening.rs`.
//!
//! One lane is one thread and one connection each way, driven by a single loop that writes
//! whatever its right neighbour can take and reads whatever its left neighbour sent, so it
//! never waits on one direction while the other could move. A ring of several lanes cuts the
//! buffer into one range per lane and runs the lanes on threads of their own, so a host with
//! cores to spare fills a link no single core could.

use std::time::Instant;

use prost::Message;
use proto::v1::LaneChunk;
use tokio_util::sync::CancellationToken;

use super::CollectiveError;
use super::carrier::Carrier;
use super::core::{Place, check_place, left_of, right_of, take_in};
use super::opening::framed;
use super::schedule::{Delivery, Schedule};
use super::wire::{Encoding, float_bytes, float_bytes_mut};

/// Longest chunk header a lane reads.
const MAX_HEADER_BYTES: usize = 64;

/// One lane of a ring: its connections to the right and from the left neighbour, on a
/// single-threaded runtime of its own so that it can run on any thread.
pub(super) struct Lane {
    right: Carrier,
    left: Carrier,
    /// Always present until dropped; taken then to shut it down without blocking, since a
    /// ring may be dropped on any runtime's thread.
    runtime: Option<tokio::runtime::Runtime>,
}

impl Drop for Lane {
    fn drop(&mut self) {
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

/// What one lane's part of an all-reduce needs to know.
pub(super) struct LaneJob<'a> {
    /// The cut of the lane's range.
    pub(super) schedule: Schedule,
    /// How its values travel (positions relative to the lane's range).
    pub(super) encoding: Encoding,
    /// Which all-reduce of the generation.
    pub(super) operation: u64,
    /// Longest wait for the neighbours.
    pub(super) timeout: std::time::Duration,
    /// Set when the generation is abandoned.
    pub(super) cancel: &'a CancellationToken,
}

impl Lane {
    /// A lane over the carriers `right` (dialled) and `left` (accepted), moved onto a
    /// runtime of the lane's own.
    pub(super) fn new(right: Carrier, left: Carrier) -> std::io::Result<Self> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()?;
        let (right, left) = (right.moved_onto(&runtime)?, left.moved_onto(&runtime)?);
        Ok(Self {
            right,
            left,
            runtime: Some(runtime),
        })
    }

    /// Sums `values` (this lane's range) with the other ranks' in place; returns the bytes
    /// sent. Blocks the calling thread, which must not be a runtime's.
    pub(super) fn all_reduce(
        &mut self,
        job: &LaneJob<'_>,
        values: &mut [f32],
    ) -> Result<u64, CollectiveError> {
        let Self {
            right,
            left,
            runtime,
        } = self;
        let runtime = runtime
            .as_ref()
            .ok_or_else(|| CollectiveError::Aborted("the lane's runtime is gone".into()))?;
        runtime.block_on(Pump::new(job, right, left).run(values))
    }
}

/// A chunk on its way out: its header, then its values read from the buffer when written.
struct Outgoing {
    header: Vec<u8>,
    begin: usize,
    end: usize,
    /// Whether the pump's encoding buffer holds this chunk's values as the wire carries them,
    /// when that is not float32 (bf16); made once, when the chunk is first at the front.
    encoded: bool,
    written: usize,
}

/// Where the chunk coming in stands.
enum Incoming {
    /// Its header's length prefix, then the header.
    Header { raw: Vec<u8>, got: usize },
    /// Its values: into the buffer itself (`direct`) or into the staging buffer.
    Values {
        delivery: Delivery,
        bytes: usize,
        direct: bool,
        got: usize,
    },
}

/// The loop of one lane's all-reduce: writes what the right neighbour can take, reads what
/// the left one sent, and waits only when neither can move.
struct Pump<'a, 'j> {
    job: &'a LaneJob<'j>,
    right: &'a mut Carrier,
    left: &'a mut Carrier,
    outgoing: std::collections::VecDeque<Outgoing>,
    deliveries: std::iter::Peekable<Box<dyn Iterator<Item = Delivery>>>,
    incoming: Incoming,
    staging: Vec<u8>,
    /// The front chunk's values as the wire carries them (bf16), reused chunk after chunk.
    encoded: Vec<u8>,
    bytes_sent: u64,
    last_progress: Instant,
}

impl<'a, 'j> Pump<'a, 'j> {
    fn new(job: &'a LaneJob<'j>, right: &'a mut Carrier, left: &'a mut Carrier) -> Self {
        let deliveries: Box<dyn Iterator<Item = Delivery>> = Box::new(job.schedule.deliveries());
        let mut pump = Self {
            job,
            right,
            left,
            outgoing: std::collections::VecDeque::new(),
            deliveries: deliveries.peekable(),
            incoming: Incoming::Header {
                raw: vec![0; 4],
                got: 0,
            },
            staging: Vec::new(),
            encoded: Vec::new(),
            bytes_sent: 0,
            last_progress: Instant::now(),
        };
        let segment = job.schedule.rank;
        for (begin, end) in job.schedule.first_sends() {
            pump.queue(0, segment, begin, end);
        }
        pump
    }

    fn left_rank(&self) -> usize {
        left_of(self.job.schedule.rank, self.job.schedule.world)
    }

    fn right_rank(&self) -> usize {
        right_of(self.job.schedule.rank, self.job.schedule.world)
    }

    /// Queues the chunk `begin..end` of `segment` for ring step `step`.
    fn queue(&mut self, step: usize, segment: usize, begin: usize, end: usize) {
        let header = LaneChunk {
            operation: self.job.operation,
            ring_step: step as u32,
            segment: segment as u32,
            offset: begin as u64,
            value_bytes: self.job.encoding.chunk_bytes(begin, end) as u64,
        };
        self.outgoing.push_back(Outgoing {
            header: framed(&header),
            begin,
            end,
            encoded: false,
            written: 0,
        });
    }

    async fn run(mut self, values: &mut [f32]) -> Result<u64, CollectiveError> {
        loop {
            let wrote = self.write_some(values)?;
            let read = self.read_some(values)?;
            if self.outgoing.is_empty() && self.deliveries.peek().is_none() && self.right.flushed()
            {
                return Ok(self.bytes_sent);
            }
            if wrote || read {
                self.last_progress = Instant::now();
            } else {
                self.wait().await?;
            }
        }
    }

    /// Waits until a socket is ready, the generation is abandoned, or the neighbours have
    /// been silent for the whole timeout.
    async fn wait(&mut self) -> Result<(), CollectiveError> {
        let deadline = tokio::time::Instant::from_std(self.last_progress + self.job.timeout);
        let writing = !self.outgoing.is_empty() || !self.right.flushed();
        let reading = self.deliveries.peek().is_some();
        let (left_rank, right_rank) = (self.left_rank(), self.right_rank());
        let cancel = self.job.cancel;
        tokio::select! {
            ready = self.left.readable(), if reading => ready.map_err(|e| CollectiveError::InboundBroken {
                rank: left_rank,
                reason: e.to_string(),
            }),
            ready = self.right.writable(), if writing => ready.map_err(|_| CollectiveError::PeerGone { rank: right_rank }),
            () = cancel.cancelled() => Err(CollectiveError::Cancelled),
            () = tokio::time::sleep_until(deadline) => Err(CollectiveError::Timeout {
                rank: if writing { right_rank } else { left_rank },
                seconds: self.job.timeout.as_secs_f64(),
            }),
        }
    }

    /// Writes as much of the first queued chunk as the socket takes; whether anything went.
    fn write_some(&mut self, values: &[f32]) -> Result<bool, CollectiveError> {
        let right_rank = self.right_rank();
        let encoding = self.job.encoding;
        let Some(out) = self.outgoing.front_mut() else {
            // What a TLS session still holds back goes out after the last chunk.
            return self
                .right
                .flush_some()
                .map_err(|_| CollectiveError::PeerGone { rank: right_rank });
        };
        let header_len = out.header.len();
        let result = if out.written < header_len {
            self.right.try_write(&out.header[out.written..])
        } else {
            let at = out.written - header_len;
            let range = &values[out.begin..out.end];
            if encoding.is_plain(out.begin, out.end) {
                self.right.try_write(&float_bytes(range)[at..])
            } else {
                if !out.encoded {
                    encoding.encode_into(out.begin, range, &mut self.encoded);
                    out.encoded = true;
                }
                self.right.try_write(&self.encoded[at..])
            }
        };
        match result {
            Ok(sent) => {
                out.written += sent;
                let value_bytes = encoding.chunk_bytes(out.begin, out.end);
                if out.written == header_len + value_bytes {
                    self.bytes_sent += value_bytes as u64;
                    self.outgoing.pop_front();
                }
                Ok(sent > 0)
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => Ok(false),
            Err(_) => Err(CollectiveError::PeerGone { rank: right_rank }),
        }
    }

    /// Reads what the left neighbour sent, up to the end of the current header or chunk, and
    /// takes in whatever it completes; whether anything came.
    fn read_some(&mut self, values: &mut [f32]) -> Result<bool, CollectiveError> {
        let left_rank = self.left_rank();
        let broken = |reason: String| CollectiveError::InboundBroken {
            rank: left_rank,
            reason,
        };
        if self.deliveries.peek().is_none() {
            return Ok(false);
        }
        let result = match &mut self.incoming {
            Incoming::Header { raw, got } => self.left.try_read(&mut raw[*got..]),
            Incoming::Values {
                delivery,
                bytes,
                direct: true,
                got,
            } => self.left.try_read(
                &mut float_bytes_mut(&mut values[delivery.begin..delivery.end])[*got..*bytes],
            ),
            Incoming::Values { bytes, got, .. } => {
                self.staging.resize(*bytes, 0);
                self.left.try_read(&mut self.staging[*got..])
            }
        };
        let read = match result {
            Ok(0) => return Err(broken("the connection closed".into())),
            Ok(read) => read,
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return Ok(false),
            Err(e) => return Err(broken(e.to_string())),
        };
        self.advance(read, values)?;
        Ok(true)
    }

    /// Counts `read` bytes into the current header or chunk and acts on whatever completed.
    fn advance(&mut self, read: usize, values: &mut [f32]) -> Result<(), CollectiveError> {
        match &mut self.incoming {
            Incoming::Header { raw, got } => {
                *got += read;
                if *got < raw.len() {
                    return Ok(());
                }
                if raw.len() == 4 {
                    let length = u32::from_le_bytes([raw[0], raw[1], raw[2], raw[3]]) as usize;
                    if length > MAX_HEADER_BYTES {
                        return self.bad(format!("a {length}-byte chunk header"));
                    }
                    if length > 0 {
                        self.incoming = Incoming::Header {
                            raw: vec![0; 4 + length],
                            got: 4,
                        };
                        return Ok(());
                    }
                }
                let header = match LaneChunk::decode(&raw[4..]) {
                    Ok(header) => header,
                    Err(e) => return self.bad(format!("an unreadable chunk header: {e}")),
                };
                self.expect(&header)
            }
            Incoming::Values {
                delivery,
                bytes,
                direct,
                got,
            } => {
                *got += read;
                if *got < *bytes {
                    return Ok(());
                }
                let (delivery, direct) = (*delivery, *direct);
                self.take_in(delivery, direct, values);
                self.incoming = Incoming::Header {
                    raw: vec![0; 4],
                    got: 0,
                };
                Ok(())
            }
        }
    }

    /// Checks a chunk's header against the chunk the ring delivers next.
    fn expect(&mut self, header: &LaneChunk) -> Result<(), CollectiveError> {
        let Some(&delivery) = self.deliveries.peek() else {
            return self.bad("a chunk after the all-reduce's last".into());
        };
        let place = Place {
            operation: header.operation,
            ring_step: u64::from(header.ring_step),
            segment: u64::from(header.segment),
            offset: header.offset,
            value_bytes: header.value_bytes,
        };
        if let Err(misplaced) =
            check_place(&place, self.job.operation, &delivery, &self.job.encoding)
        {
            return self.bad(misplaced.0);
        }
        let bytes = self.job.encoding.chunk_bytes(delivery.begin, delivery.end);
        let direct = !self.job.schedule.adds(delivery.step)
            && self.job.encoding.is_plain(delivery.begin, delivery.end);
        self.incoming = Incoming::Values {
            delivery,
            bytes,
            direct,
            got: 0,
        };
        Ok(())
    }

    /// A received chunk into the buffer, and on around the ring when a step follows.
    fn take_in(&mut self, delivery: Delivery, direct: bool, values: &mut [f32]) {
        let target = &mut values[delivery.begin..delivery.end];
        let received = (!direct).then_some(&self.staging[..]);
        let onwards = take_in(
            &self.job.schedule,
            &self.job.encoding,
            &delivery,
            target,
            received,
        );
        self.deliveries.next();
        if onwards {
            let (step, segment) = (delivery.step + 1, delivery.segment);
            self.queue(step, segment, delivery.begin, delivery.end);
        }
    }

    fn bad<T>(&self, detail: String) -> Result<T, CollectiveError> {
        Err(CollectiveError::BadChunk {
            rank: self.left_rank(),
            detail,
        })
    }
}
