//! A TLS lane's handshake: rustls's unbuffered connection driven over the lane's TCP
//! connection one record at a time, then turned into its traffic keys and key schedule for
//! the lane's own record layer (`records.rs`).
//!
//! Reading whole records, and never past the one rustls is waiting for, is what makes the
//! hand-over safe: the first byte after the handshake (the dialler's hello) is still in the
//! socket when rustls lets go, so no record is opened by rustls and lost with it.

use std::sync::Arc;

use rustls::client::{ClientConnectionData, UnbufferedClientConnection};
use rustls::kernel::KernelConnection;
use rustls::server::{ServerConnectionData, UnbufferedServerConnection};
use rustls::unbuffered::{ConnectionState, EncodeError, UnbufferedStatus};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::records::{KeySchedule, TlsCarrier};

/// The longest record the handshake reads: TLS 1.3's limit for a sealed record.
const MAX_HANDSHAKE_RECORD_BYTES: usize = (1 << 14) + 256;

/// Why a lane's TLS handshake failed.
#[derive(Debug, thiserror::Error)]
pub(super) enum TlsHandshakeError {
    /// The connection failed or closed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The peer's handshake was refused (a certificate, a protocol error).
    #[error("{0}")]
    Refused(#[from] rustls::Error),
    /// The peer sent something other than a TLS record, or application data mid-handshake.
    #[error("the peer broke the TLS handshake: {0}")]
    Broken(String),
}

/// The dialler's side: a TLS client of `name` under `config`.
pub(super) async fn as_client(
    tcp: TcpStream,
    config: Arc<rustls::ClientConfig>,
    name: rustls::pki_types::ServerName<'static>,
) -> Result<TlsCarrier, TlsHandshakeError> {
    drive(tcp, UnbufferedClientConnection::new(config, name)?).await
}

/// The listener's side: a TLS server under `config`.
pub(super) async fn as_server(
    tcp: TcpStream,
    config: Arc<rustls::ServerConfig>,
) -> Result<TlsCarrier, TlsHandshakeError> {
    drive(tcp, UnbufferedServerConnection::new(config)?).await
}

/// What both sides of rustls's unbuffered connection offer.
trait Unbuffered: Sized {
    type Side: 'static;
    fn process<'c, 'i>(
        &'c mut self,
        incoming: &'i mut [u8],
    ) -> UnbufferedStatus<'c, 'i, Self::Side>;
    fn handshaking(&self) -> bool;
    fn into_keys(
        self,
    ) -> Result<(rustls::ExtractedSecrets, KernelConnection<Self::Side>), rustls::Error>;
}

/// The two sides offer the same methods on different types; one implementation for both.
macro_rules! unbuffered {
    ($connection:ty, $side:ty) => {
        impl Unbuffered for $connection {
            type Side = $side;
            fn process<'c, 'i>(
                &'c mut self,
                incoming: &'i mut [u8],
            ) -> UnbufferedStatus<'c, 'i, Self::Side> {
                self.process_tls_records(incoming)
            }
            fn handshaking(&self) -> bool {
                self.is_handshaking()
            }
            fn into_keys(
                self,
            ) -> Result<(rustls::ExtractedSecrets, KernelConnection<Self::Side>), rustls::Error>
            {
                self.dangerous_into_kernel_connection()
            }
        }
    };
}

unbuffered!(UnbufferedClientConnection, ClientConnectionData);
unbuffered!(UnbufferedServerConnection, ServerConnectionData);

/// What the handshake needs next.
enum Next {
    /// Another turn of rustls.
    Process,
    /// A record from the peer.
    Record,
    /// Nothing: the handshake is done once this side no longer handshakes.
    Traffic,
}

/// Runs `connection`'s handshake over `tcp` and hands its keys to a carrier.
async fn drive<C: Unbuffered>(
    mut tcp: TcpStream,
    mut connection: C,
) -> Result<TlsCarrier, TlsHandshakeError>
where
    KernelConnection<C::Side>: KeySchedule + 'static,
{
    let mut incoming = Vec::new();
    let mut outgoing = Vec::new();
    loop {
        let UnbufferedStatus { discard, state } = connection.process(&mut incoming);
        let next = match state? {
            ConnectionState::EncodeTlsData(mut data) => {
                let mut encoded = data.encode(&mut []);
                if let Err(EncodeError::InsufficientSize(size)) = encoded {
                    let at = outgoing.len();
                    outgoing.resize(at + size.required_size, 0);
                    encoded = data.encode(&mut outgoing[at..]);
                }
                encoded.map_err(|e| TlsHandshakeError::Broken(e.to_string()))?;
                Next::Process
            }
            ConnectionState::TransmitTlsData(data) => {
                tcp.write_all(&outgoing).await?;
                outgoing.clear();
                data.done();
                Next::Process
            }
            ConnectionState::BlockedHandshake => Next::Record,
            ConnectionState::WriteTraffic(_) => Next::Traffic,
            other => {
                return Err(TlsHandshakeError::Broken(format!(
                    "{other:?} during the handshake"
                )));
            }
        };
        incoming.drain(..discard);
        match next {
            Next::Process => {}
            Next::Traffic if !connection.handshaking() => break,
            Next::Record | Next::Traffic => read_record(&mut tcp, &mut incoming).await?,
        }
    }
    let (secrets, schedule) = connection.into_keys()?;
    Ok(TlsCarrier::new(tcp, secrets, Box::new(schedule))?)
}

/// Appends exactly one record from `tcp` to `incoming`.
async fn read_record(tcp: &mut TcpStream, incoming: &mut Vec<u8>) -> Result<(), TlsHandshakeError> {
    let mut header = [0u8; 5];
    tcp.read_exact(&mut header).await?;
    let length = u16::from_be_bytes([header[3], header[4]]) as usize;
    if !(20..=23).contains(&header[0]) || length > MAX_HANDSHAKE_RECORD_BYTES {
        return Err(TlsHandshakeError::Broken(format!(
            "a {length}-byte record of type {}",
            header[0]
        )));
    }
    let at = incoming.len();
    incoming.extend_from_slice(&header);
    incoming.resize(at + 5 + length, 0);
    tcp.read_exact(&mut incoming[at + 5..]).await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio::net::{TcpListener, TcpStream};

    use super::super::carrier::Carrier;
    use super::*;

    /// A dialler's and a listener's carrier over loopback, each renewing its key every
    /// `records` records.
    async fn pair(records: u64) -> (Carrier, Carrier) {
        let certificates = Path::new(env!("CARGO_MANIFEST_DIR")).join("../proto/testdata/tls");
        let server_config = proto::tls::lane_server_config(
            &certificates.join("server.pem"),
            &certificates.join("server.key"),
        )
        .unwrap();
        let client_config = proto::tls::lane_client_config(&certificates.join("ca.pem")).unwrap();
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        let server = tokio::spawn(async move {
            let (tcp, _) = listener.accept().await.unwrap();
            as_server(tcp, server_config).await.unwrap()
        });
        let name = rustls::pki_types::ServerName::try_from("localhost").unwrap();
        let client = as_client(
            TcpStream::connect(address).await.unwrap(),
            client_config,
            name,
        )
        .await
        .unwrap();
        let server = server.await.unwrap();
        (
            Carrier::Tls(Box::new(client.renewing_every(records))),
            Carrier::Tls(Box::new(server.renewing_every(records))),
        )
    }

    fn pattern(length: usize, seed: u8) -> Vec<u8> {
        (0..length)
            .map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed) ^ (i >> 11) as u8)
            .collect()
    }

    /// Sends `bytes` one way and reads them back on the other side.
    async fn through(from: &mut Carrier, to: &mut Carrier, bytes: &[u8]) -> Vec<u8> {
        let mut got = vec![0; bytes.len()];
        let (sent, read) = tokio::join!(
            async {
                from.write_all(bytes).await?;
                from.flush().await
            },
            to.read_exact(&mut got)
        );
        sent.unwrap();
        read.unwrap();
        got
    }

    #[tokio::test]
    async fn records_carry_every_byte_both_ways_across_key_updates() {
        // Three records a key: a 3 MB message crosses about 60 key updates each way.
        let (mut dialler, mut listener) = pair(3).await;
        let first = pattern(3 << 20, 1);
        assert!(through(&mut dialler, &mut listener, &first).await == first);
        let back = pattern((3 << 20) + 12345, 7);
        assert!(through(&mut listener, &mut dialler, &back).await == back);
        let small = pattern(5, 9);
        assert_eq!(through(&mut dialler, &mut listener, &small).await, small);
    }

    #[tokio::test]
    async fn a_forged_record_fails_authentication_instead_of_reading_as_data() {
        let (mut dialler, mut listener) = pair(super::super::records::RECORDS_PER_KEY).await;
        let Carrier::Tls(records) = &mut dialler else {
            unreachable!("the pair is TLS")
        };
        let mut forged = vec![23, 3, 3, 0, 40];
        forged.extend(pattern(40, 3));
        records.tcp.write_all(&forged).await.unwrap();
        let mut got = [0u8; 16];
        let error = listener.read(&mut got).await.unwrap_err();
        assert_eq!(error.kind(), std::io::ErrorKind::InvalidData);
        assert!(error.to_string().contains("authentication"), "{error}");
    }

    #[tokio::test]
    async fn a_record_that_is_not_tls_is_refused() {
        let (mut dialler, mut listener) = pair(super::super::records::RECORDS_PER_KEY).await;
        let Carrier::Tls(records) = &mut dialler else {
            unreachable!("the pair is TLS")
        };
        records
            .tcp
            .write_all(b"GET / HTTP/1.1\r\n\r\n")
            .await
            .unwrap();
        let error = listener.read(&mut [0u8; 16]).await.unwrap_err();
        assert!(error.to_string().contains("TLS 1.3 record"), "{error}");
    }
}
