//! What a lane's bytes travel on once its opening is done: the TCP connection itself, or a
//! rustls session over it (a job with `tls:`).
//!
//! The lane's loop (`lane.rs`) writes and reads without waiting and waits only when neither
//! direction can move, so the session is driven by hand rather than through an async stream:
//! plaintext written goes into the session, which seals it into records of up to 16 KiB, and
//! the sealed records go to the socket as far as it takes them; records read from the socket
//! are opened in the session and their plaintext copied out. Encryption and decryption are
//! the only passes over the bytes besides the kernel's copies, so a TLS lane costs what the
//! cipher costs and no more.

use std::io::{self, Read, Write};

use tokio::net::TcpStream;

/// Sealed bytes a TLS carrier holds back for the socket before it takes more plaintext.
const SEALED_BACKLOG_BYTES: usize = 1 << 20;

/// Sealed bytes a TLS carrier reads from the socket at once: the session takes records a few
/// KiB at a time, so it is fed from this buffer rather than from one system call each.
const SEALED_READ_BYTES: usize = 256 << 10;

/// A lane's connection, ready for chunks.
pub(super) enum Carrier {
    /// Bytes as they are.
    Plain(TcpStream),
    /// Bytes through a TLS session whose handshake is done.
    Tls(Box<TlsCarrier>),
}

/// A TCP connection and the TLS session over it.
pub(super) struct TlsCarrier {
    tcp: TcpStream,
    session: rustls::Connection,
    /// Sealed bytes read from the socket and not yet taken by the session:
    /// `sealed[taken..filled]` (allocated at the first read).
    sealed: Vec<u8>,
    taken: usize,
    filled: usize,
}

impl Carrier {
    /// The session `session` over `tcp`, whose handshake is done (plaintext it already
    /// opened stays in it and is read first).
    pub(super) fn tls(tcp: TcpStream, session: impl Into<rustls::Connection>) -> Self {
        let mut session = session.into();
        session.set_buffer_limit(Some(SEALED_BACKLOG_BYTES));
        Self::Tls(Box::new(TlsCarrier {
            tcp,
            session,
            sealed: Vec::new(),
            taken: 0,
            filled: 0,
        }))
    }

    /// The TCP connection underneath.
    fn tcp(&self) -> &TcpStream {
        match self {
            Self::Plain(tcp) => tcp,
            Self::Tls(carrier) => &carrier.tcp,
        }
    }

    /// The same carrier with its connection registered with `runtime` (a lane runs on a
    /// runtime of its own).
    pub(super) fn moved_onto(self, runtime: &tokio::runtime::Runtime) -> io::Result<Self> {
        let rehome = |tcp: TcpStream| -> io::Result<TcpStream> {
            let tcp = tcp.into_std()?;
            let _entered = runtime.enter();
            TcpStream::from_std(tcp)
        };
        Ok(match self {
            Self::Plain(tcp) => Self::Plain(rehome(tcp)?),
            Self::Tls(carrier) => {
                let TlsCarrier {
                    tcp,
                    session,
                    sealed,
                    taken,
                    filled,
                } = *carrier;
                Self::Tls(Box::new(TlsCarrier {
                    tcp: rehome(tcp)?,
                    session,
                    sealed,
                    taken,
                    filled,
                }))
            }
        })
    }

    /// Writes some of `bytes` without waiting; `WouldBlock` when none could be taken.
    pub(super) fn try_write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        match self {
            Self::Plain(tcp) => tcp.try_write(bytes),
            Self::Tls(carrier) => carrier.try_write(bytes),
        }
    }

    /// Reads some bytes into `into` without waiting: `Ok(0)` when the peer closed,
    /// `WouldBlock` when nothing has come.
    pub(super) fn try_read(&mut self, into: &mut [u8]) -> io::Result<usize> {
        match self {
            Self::Plain(tcp) => tcp.try_read(into),
            Self::Tls(carrier) => carrier.try_read(into),
        }
    }

    /// Sends what the carrier still holds back, as far as the socket takes it; whether
    /// anything went.
    pub(super) fn flush_some(&mut self) -> io::Result<bool> {
        match self {
            Self::Plain(_) => Ok(false),
            Self::Tls(carrier) => carrier.send_sealed(),
        }
    }

    /// Whether everything written has gone to the socket.
    pub(super) fn flushed(&self) -> bool {
        match self {
            Self::Plain(_) => true,
            Self::Tls(carrier) => !carrier.session.wants_write(),
        }
    }

    /// Waits until a write can make progress.
    pub(super) async fn writable(&self) -> io::Result<()> {
        match self {
            Self::Tls(carrier) if !carrier.session.wants_write() => Ok(()),
            _ => self.tcp().writable().await,
        }
    }

    /// Waits until a read can make progress.
    pub(super) async fn readable(&self) -> io::Result<()> {
        self.tcp().readable().await
    }
}

impl TlsCarrier {
    fn try_write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        self.send_sealed()?;
        // Sealed into the session's backlog, up to its limit.
        let taken = self.session.writer().write(bytes)?;
        self.send_sealed()?;
        if taken == 0 && !bytes.is_empty() {
            return Err(io::ErrorKind::WouldBlock.into());
        }
        Ok(taken)
    }

    /// Writes sealed records to the socket until it is full or none are left.
    fn send_sealed(&mut self) -> io::Result<bool> {
        let mut sent = false;
        while self.session.wants_write() {
            match self.session.write_tls(&mut Unwaiting(&self.tcp)) {
                Ok(0) => break,
                Ok(_) => sent = true,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
        }
        Ok(sent)
    }

    fn try_read(&mut self, into: &mut [u8]) -> io::Result<usize> {
        loop {
            match self.session.reader().read(into) {
                Ok(read) => return Ok(read),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                Err(e) => return Err(e),
            }
            // No plaintext left: open what was read from the socket, reading more first when
            // nothing is left of it.
            if self.taken == self.filled {
                self.sealed.resize(SEALED_READ_BYTES, 0);
                (self.taken, self.filled) = (0, 0);
                let read = self.tcp.try_read(&mut self.sealed)?;
                self.filled = read;
                if read == 0 {
                    // The peer closed: what the session makes of it (a clean close, or a
                    // truncation) is what the reader says next.
                    self.session.read_tls(&mut io::empty())?;
                    self.process()?;
                    return self.session.reader().read(into);
                }
            }
            self.taken += self
                .session
                .read_tls(&mut &self.sealed[self.taken..self.filled])?;
            self.process()?;
        }
    }

    fn process(&mut self) -> io::Result<()> {
        self.session
            .process_new_packets()
            .map(|_| ())
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))
    }
}

/// The socket seen as a blocking writer that never blocks: `WouldBlock` instead.
struct Unwaiting<'a>(&'a TcpStream);

impl Write for Unwaiting<'_> {
    fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        self.0.try_write(bytes)
    }

    /// The session hands over every sealed record it holds at once: one system call.
    fn write_vectored(&mut self, records: &[io::IoSlice<'_>]) -> io::Result<usize> {
        self.0.try_write_vectored(records)
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}
