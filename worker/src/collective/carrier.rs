//! What a lane's bytes travel on: the TCP connection itself, or TLS 1.3 records over it (a
//! job with `tls:`, `records.rs`). The same carrier serves the lane's opening, as an async
//! stream, and its chunks, written and read without waiting by the lane's loop (`lane.rs`),
//! which waits only when neither direction can move.

use std::io;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;

use super::records::TlsCarrier;

/// A lane's connection.
pub(super) enum Carrier {
    /// Bytes as they are.
    Plain(TcpStream),
    /// Bytes sealed into TLS records, the handshake done.
    Tls(Box<TlsCarrier>),
}

impl Carrier {
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
                let mut carrier = *carrier;
                carrier.tcp = rehome(carrier.tcp)?;
                Self::Tls(Box::new(carrier))
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
            Self::Tls(carrier) => carrier.flushed(),
        }
    }

    /// Waits until a write can make progress.
    pub(super) async fn writable(&self) -> io::Result<()> {
        match self {
            Self::Tls(carrier) if carrier.flushed() => Ok(()),
            _ => self.tcp().writable().await,
        }
    }

    /// Waits until a read can make progress.
    pub(super) async fn readable(&self) -> io::Result<()> {
        self.tcp().readable().await
    }
}

impl AsyncRead for Carrier {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Plain(tcp) => Pin::new(tcp).poll_read(cx, buf),
            Self::Tls(carrier) => loop {
                match carrier.try_read(buf.initialize_unfilled()) {
                    Ok(read) => {
                        buf.advance(read);
                        return Poll::Ready(Ok(()));
                    }
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                        ready!(carrier.tcp.poll_read_ready(cx))?;
                    }
                    Err(e) => return Poll::Ready(Err(e)),
                }
            },
        }
    }
}

impl AsyncWrite for Carrier {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bytes: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Self::Plain(tcp) => Pin::new(tcp).poll_write(cx, bytes),
            Self::Tls(carrier) => loop {
                match carrier.try_write(bytes) {
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                        ready!(carrier.tcp.poll_write_ready(cx))?;
                    }
                    written => return Poll::Ready(written),
                }
            },
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Plain(tcp) => Pin::new(tcp).poll_flush(cx),
            Self::Tls(carrier) => {
                while !carrier.flushed() {
                    if !carrier.send_sealed()? {
                        ready!(carrier.tcp.poll_write_ready(cx))?;
                    }
                }
                Poll::Ready(Ok(()))
            }
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        ready!(self.as_mut().poll_flush(cx))?;
        match self.get_mut() {
            Self::Plain(tcp) => Pin::new(tcp).poll_shutdown(cx),
            Self::Tls(carrier) => Pin::new(&mut carrier.tcp).poll_shutdown(cx),
        }
    }
}
