//! A TLS lane's record layer: TLS 1.3 records (RFC 8446, section 5) sealed and opened in the
//! lane's own buffers under the traffic keys rustls hands over once its handshake is done
//! (`tls_handshake.rs`).
//!
//! rustls's buffered session copies a record three times on its way in (into its deframer,
//! into its plaintext queue, out to the reader) and allocates one buffer per record on its
//! way out. Here plaintext is copied once, into the outgoing buffer, and sealed where it
//! lies; records are opened where the socket put them and their plaintext copied once, to
//! wherever the lane wants it. Both directions renew their keys with TLS key updates, derived
//! by rustls's key schedule, long before the cipher's confidentiality limit.

use std::io;

use ring::aead::{self, Aad, LessSafeKey, Nonce, UnboundKey};
use rustls::ConnectionTrafficSecrets;
use rustls::kernel::KernelConnection;
use tokio::net::TcpStream;

/// A record's header: content type, legacy version, length.
const HEADER_BYTES: usize = 5;
/// The AEAD tag that ends every sealed record.
const TAG_BYTES: usize = 16;
/// The most plaintext one record carries.
const MAX_PLAINTEXT_BYTES: usize = 1 << 14;
/// The longest sealed body a record may announce.
const MAX_SEALED_BODY_BYTES: usize = MAX_PLAINTEXT_BYTES + 256;
/// A sealed record beyond its plaintext: header, inner content type, tag.
const RECORD_OVERHEAD_BYTES: usize = HEADER_BYTES + 1 + TAG_BYTES;
/// A key update's record: a five-byte handshake message and the overhead.
const KEY_UPDATE_RECORD_BYTES: usize = RECORD_OVERHEAD_BYTES + 5;

const ALERT: u8 = 21;
const HANDSHAKE: u8 = 22;
const APPLICATION_DATA: u8 = 23;
/// TLS 1.3's handshake message type for a key update.
const KEY_UPDATE: u8 = 24;
/// An alert's bytes for close_notify (level warning, description 0).
const CLOSE_NOTIFY: [u8; 2] = [1, 0];

/// Sealed bytes a TLS lane holds back for the socket before it takes more plaintext: the
/// socket is handed up to this much in one system call.
const SEALED_BACKLOG_BYTES: usize = 1 << 20;

/// Sealed bytes a TLS lane reads from the socket at once.
const SEALED_READ_BYTES: usize = 256 << 10;

/// Records sealed under one key before it is renewed: a quarter of AES-128-GCM's limit in
/// TLS 1.3 (2^24 records) and half of AES-256-GCM's, about 64 GiB of a lane's traffic.
pub(super) const RECORDS_PER_KEY: u64 = 1 << 22;

/// Where a lane's next traffic keys come from: rustls's key schedule, kept past the handshake.
pub(super) trait KeySchedule: Send + Sync {
    /// The next key for sealing, after this side sent a key update.
    fn next_sealing(&mut self) -> Result<(u64, ConnectionTrafficSecrets), rustls::Error>;
    /// The next key for opening, after the peer sent a key update.
    fn next_opening(&mut self) -> Result<(u64, ConnectionTrafficSecrets), rustls::Error>;
}

impl<Side> KeySchedule for KernelConnection<Side>
where
    KernelConnection<Side>: Send + Sync,
{
    fn next_sealing(&mut self) -> Result<(u64, ConnectionTrafficSecrets), rustls::Error> {
        self.update_tx_secret()
    }

    fn next_opening(&mut self) -> Result<(u64, ConnectionTrafficSecrets), rustls::Error> {
        self.update_rx_secret()
    }
}

/// One direction's AEAD key, its IV and the sequence number of its next record.
struct TrafficKey {
    key: LessSafeKey,
    iv: [u8; 12],
    sequence: u64,
}

impl TrafficKey {
    fn new((sequence, secrets): (u64, ConnectionTrafficSecrets)) -> io::Result<Self> {
        let (algorithm, key, iv) = match &secrets {
            ConnectionTrafficSecrets::Aes128Gcm { key, iv } => (&aead::AES_128_GCM, key, iv),
            ConnectionTrafficSecrets::Aes256Gcm { key, iv } => (&aead::AES_256_GCM, key, iv),
            ConnectionTrafficSecrets::Chacha20Poly1305 { key, iv } => {
                (&aead::CHACHA20_POLY1305, key, iv)
            }
            _ => {
                return Err(io::Error::other(
                    "the lane negotiated a cipher it cannot run",
                ));
            }
        };
        let key = UnboundKey::new(algorithm, key.as_ref())
            .map_err(|_| io::Error::other("rustls handed over a key of the wrong length"))?;
        let iv = iv
            .as_ref()
            .try_into()
            .map_err(|_| io::Error::other("rustls handed over an IV of the wrong length"))?;
        Ok(Self {
            key: LessSafeKey::new(key),
            iv,
            sequence,
        })
    }

    /// The next record's nonce (the IV with the sequence number folded into its low bytes),
    /// counting the record.
    fn next_nonce(&mut self) -> Nonce {
        let mut nonce = self.iv;
        for (byte, counter) in nonce[4..].iter_mut().zip(self.sequence.to_be_bytes()) {
            *byte ^= counter;
        }
        self.sequence += 1;
        Nonce::assume_unique_for_key(nonce)
    }
}

fn invalid(reason: impl Into<String>) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, reason.into())
}

/// A TCP connection carrying TLS 1.3 records under keys from a finished handshake.
pub(super) struct TlsCarrier {
    pub(super) tcp: TcpStream,
    schedule: Box<dyn KeySchedule>,
    sealing: TrafficKey,
    opening: TrafficKey,
    /// Records sealed under the sealing key before it is renewed.
    records_per_key: u64,
    /// The peer asked for this side's key to be renewed.
    renewal_asked: bool,
    /// Sealed records not yet taken by the socket: `sealed[sent..filled]`.
    sealed: Vec<u8>,
    sent: usize,
    filled: usize,
    /// Bytes from the socket: records not yet opened at `received[parsed..read]`, plaintext
    /// not yet delivered at `received[plain..plain_end]`.
    received: Vec<u8>,
    parsed: usize,
    read: usize,
    plain: usize,
    plain_end: usize,
    /// The peer closed the session with close_notify.
    peer_closed: bool,
}

impl TlsCarrier {
    /// Records over `tcp` from the traffic keys `secrets` of a finished handshake, renewed
    /// through `schedule`.
    pub(super) fn new(
        tcp: TcpStream,
        secrets: rustls::ExtractedSecrets,
        schedule: Box<dyn KeySchedule>,
    ) -> io::Result<Self> {
        Ok(Self {
            tcp,
            schedule,
            sealing: TrafficKey::new(secrets.tx)?,
            opening: TrafficKey::new(secrets.rx)?,
            records_per_key: RECORDS_PER_KEY,
            renewal_asked: false,
            sealed: vec![0; SEALED_BACKLOG_BYTES],
            sent: 0,
            filled: 0,
            received: vec![0; SEALED_READ_BYTES],
            parsed: 0,
            read: 0,
            plain: 0,
            plain_end: 0,
            peer_closed: false,
        })
    }

    /// The same carrier renewing its key every `records` records (tests reach a key update
    /// in a few records instead of millions).
    #[cfg(test)]
    pub(super) fn renewing_every(mut self, records: u64) -> Self {
        self.records_per_key = records;
        self
    }

    /// Seals as much of `bytes` as the backlog takes and hands the socket what it will take;
    /// `WouldBlock` when nothing could be taken.
    pub(super) fn try_write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        self.send_sealed()?;
        let mut taken = 0;
        while taken < bytes.len() {
            let room = self.room();
            if room <= RECORD_OVERHEAD_BYTES + KEY_UPDATE_RECORD_BYTES {
                break;
            }
            let length = (bytes.len() - taken)
                .min(MAX_PLAINTEXT_BYTES)
                .min(room - RECORD_OVERHEAD_BYTES - KEY_UPDATE_RECORD_BYTES);
            self.seal(&bytes[taken..taken + length])?;
            taken += length;
        }
        self.send_sealed()?;
        if taken == 0 && !bytes.is_empty() {
            return Err(io::ErrorKind::WouldBlock.into());
        }
        Ok(taken)
    }

    /// Room left in the backlog, moving what the socket has not taken to its front when the
    /// front half has gone.
    fn room(&mut self) -> usize {
        if self.sent == self.filled {
            (self.sent, self.filled) = (0, 0);
        } else if self.sent >= SEALED_BACKLOG_BYTES / 2 {
            self.sealed.copy_within(self.sent..self.filled, 0);
            (self.sent, self.filled) = (0, self.filled - self.sent);
        }
        SEALED_BACKLOG_BYTES - self.filled
    }

    /// Seals `plain` as one application-data record, renewing the key first when it is due.
    fn seal(&mut self, plain: &[u8]) -> io::Result<()> {
        if self.renewal_asked || self.sealing.sequence >= self.records_per_key {
            // The key update goes under the old key; the peer renews its opening key on it.
            self.seal_record(HANDSHAKE, &[KEY_UPDATE, 0, 0, 1, 0])?;
            let next = self.schedule.next_sealing().map_err(io::Error::other)?;
            self.sealing = TrafficKey::new(next)?;
            self.renewal_asked = false;
        }
        self.seal_record(APPLICATION_DATA, plain)
    }

    /// Seals one record of content type `kind` at the end of the backlog (which has room).
    fn seal_record(&mut self, kind: u8, plain: &[u8]) -> io::Result<()> {
        let body = plain.len() + 1 + TAG_BYTES;
        let record = &mut self.sealed[self.filled..self.filled + HEADER_BYTES + body];
        let (header, rest) = record.split_at_mut(HEADER_BYTES);
        let length = (body as u16).to_be_bytes();
        header.copy_from_slice(&[APPLICATION_DATA, 3, 3, length[0], length[1]]);
        let (inner, tag_space) = rest.split_at_mut(plain.len() + 1);
        inner[..plain.len()].copy_from_slice(plain);
        inner[plain.len()] = kind;
        let nonce = self.sealing.next_nonce();
        let tag = self
            .sealing
            .key
            .seal_in_place_separate_tag(nonce, Aad::from(&*header), inner)
            .map_err(|_| io::Error::other("sealing a TLS record failed"))?;
        tag_space.copy_from_slice(tag.as_ref());
        self.filled += HEADER_BYTES + body;
        Ok(())
    }

    /// Hands the socket sealed records until it is full or none are left; whether any went.
    pub(super) fn send_sealed(&mut self) -> io::Result<bool> {
        let mut went = false;
        while self.sent < self.filled {
            match self.tcp.try_write(&self.sealed[self.sent..self.filled]) {
                Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
                Ok(sent) => {
                    self.sent += sent;
                    went = true;
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
        }
        Ok(went)
    }

    /// Whether every sealed record has gone to the socket.
    pub(super) fn flushed(&self) -> bool {
        self.sent == self.filled
    }

    /// Reads plaintext into `into` without waiting: `Ok(0)` once the peer closed,
    /// `WouldBlock` when no whole record has come.
    pub(super) fn try_read(&mut self, into: &mut [u8]) -> io::Result<usize> {
        loop {
            if self.plain < self.plain_end {
                let length = into.len().min(self.plain_end - self.plain);
                into[..length].copy_from_slice(&self.received[self.plain..self.plain + length]);
                self.plain += length;
                return Ok(length);
            }
            if self.peer_closed {
                return Ok(0);
            }
            if !self.open_next()? && !self.receive()? {
                return if self.parsed == self.read {
                    Ok(0)
                } else {
                    Err(io::Error::new(
                        io::ErrorKind::UnexpectedEof,
                        "the connection closed inside a TLS record",
                    ))
                };
            }
        }
    }

    /// Reads what the socket has after the records not yet opened; `false` when the peer
    /// closed the connection.
    fn receive(&mut self) -> io::Result<bool> {
        if self.received.len() - self.parsed < HEADER_BYTES + MAX_SEALED_BODY_BYTES {
            self.received.copy_within(self.parsed..self.read, 0);
            (self.parsed, self.read) = (0, self.read - self.parsed);
        }
        let read = self.tcp.try_read(&mut self.received[self.read..])?;
        self.read += read;
        Ok(read > 0)
    }

    /// Opens the next whole record in place; whether there was one.
    fn open_next(&mut self) -> io::Result<bool> {
        let waiting = &self.received[self.parsed..self.read];
        if waiting.len() < HEADER_BYTES {
            return Ok(false);
        }
        let body = u16::from_be_bytes([waiting[3], waiting[4]]) as usize;
        if waiting[..3] != [APPLICATION_DATA, 3, 3]
            || !(1 + TAG_BYTES..=MAX_SEALED_BODY_BYTES).contains(&body)
        {
            return Err(invalid(
                "the peer sent something other than a TLS 1.3 record",
            ));
        }
        if waiting.len() < HEADER_BYTES + body {
            return Ok(false);
        }
        let start = self.parsed;
        self.parsed += HEADER_BYTES + body;
        let nonce = self.opening.next_nonce();
        let (header, sealed) =
            self.received[start..start + HEADER_BYTES + body].split_at_mut(HEADER_BYTES);
        let inner = self
            .opening
            .key
            .open_in_place(nonce, Aad::from(&*header), sealed)
            .map_err(|_| invalid("a TLS record failed authentication"))?;
        let Some(end) = inner.iter().rposition(|&byte| byte != 0) else {
            return Err(invalid("a TLS record without a content type"));
        };
        match inner[end] {
            APPLICATION_DATA => {
                self.plain = start + HEADER_BYTES;
                self.plain_end = self.plain + end;
            }
            HANDSHAKE => match inner[..end] {
                [KEY_UPDATE, 0, 0, 1, asked @ (0 | 1)] => {
                    self.renewal_asked |= asked == 1;
                    let next = self.schedule.next_opening().map_err(io::Error::other)?;
                    self.opening = TrafficKey::new(next)?;
                }
                _ => {
                    return Err(invalid(
                        "an unexpected TLS handshake message after the handshake",
                    ));
                }
            },
            ALERT if inner[..end] == CLOSE_NOTIFY => self.peer_closed = true,
            ALERT => {
                return Err(invalid(format!(
                    "the peer sent TLS alert {:?}",
                    &inner[..end]
                )));
            }
            other => return Err(invalid(format!("a TLS record of content type {other}"))),
        }
        Ok(true)
    }
}
