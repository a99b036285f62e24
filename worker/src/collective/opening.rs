//! A lane connection's opening: the magic, TLS when the ring runs it, the hello, the mutual
//! proof of the ring's secret (`handshake.rs`) and the listener's answer, each message framed
//! by its length. The dialler and the listener sides of it, so that `lane.rs` starts from a
//! carrier ready for chunks.
//!
//! The magic is the only thing sent in the clear on a TLS lane: the hello, the proofs and the
//! answer travel inside the session, so a proof is bound to the session whose listener showed
//! a certificate the ring's CA signed, and nobody in between can relay it into a session of
//! their own.

use std::sync::Arc;

use prost::Message;
use proto::v1::{LaneAnswer, LaneChallenge, LaneHello, LaneProof};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;

use super::carrier::Carrier;
use super::core::Attempt;
use super::handshake::{self, Role};
use super::tls_handshake::{self, TlsHandshakeError};

/// The first bytes of a plain lane connection (a gRPC connection opens with HTTP/2's preface
/// or a TLS hello, never with these).
pub const LANE_MAGIC: &[u8; 8] = b"XFLANE01";

/// The first bytes of a TLS lane connection, followed by the TLS handshake.
pub const TLS_LANE_MAGIC: &[u8; 8] = b"XFLANE1S";

/// Longest handshake message either side reads: a hello, a challenge or a proof is a few dozen
/// bytes, so a stranger cannot make a rank hold more than this for a connection.
pub(super) const MAX_HANDSHAKE_BYTES: usize = 1024;

/// `message` preceded by its length as a little-endian u32.
pub(super) fn framed(message: &impl Message) -> Vec<u8> {
    let body = message.encode_to_vec();
    let mut framed = Vec::with_capacity(4 + body.len());
    framed.extend_from_slice(&(body.len() as u32).to_le_bytes());
    framed.extend_from_slice(&body);
    framed
}

/// Writes `message` framed and pushes it out (through the TLS session too, when there is one).
async fn send<S: AsyncWrite + Unpin>(
    stream: &mut S,
    message: &impl Message,
) -> std::io::Result<()> {
    stream.write_all(&framed(message)).await?;
    stream.flush().await
}

/// How a ring's lanes dial their right neighbour over TLS: whom they trust, and the name
/// the neighbour's certificate must carry.
#[derive(Clone)]
pub(super) struct LaneTlsClient {
    /// Trust in the ring's CA.
    pub(super) config: Arc<rustls::ClientConfig>,
    /// The neighbour's name.
    pub(super) name: rustls::pki_types::ServerName<'static>,
}

/// Why a lane's handshake message could not be read.
#[derive(Debug, thiserror::Error)]
pub(super) enum HandshakeError {
    /// The connection failed or closed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The length prefix announced more than a handshake may hold.
    #[error("a {length}-byte message, above the {limit} allowed")]
    TooLong {
        /// The announced length.
        length: usize,
        /// The most allowed.
        limit: usize,
    },
    /// The bytes are not the message.
    #[error("an unreadable message: {0}")]
    Unreadable(#[from] prost::DecodeError),
}

/// Reads one length-prefixed message of at most `limit` bytes.
pub(super) async fn read_framed<M: Message + Default, S: AsyncRead + Unpin>(
    stream: &mut S,
    limit: usize,
) -> Result<M, HandshakeError> {
    let mut length = [0u8; 4];
    stream.read_exact(&mut length).await?;
    let length = u32::from_le_bytes(length) as usize;
    if length > limit {
        return Err(HandshakeError::TooLong { length, limit });
    }
    let mut body = vec![0u8; length];
    stream.read_exact(&mut body).await?;
    Ok(M::decode(body.as_slice())?)
}

/// Opens lane `hello.lane` to `address` as the holder of the ring secret `secret`: the magic,
/// the TLS handshake with `tls`, and the hello (with a fresh nonce), the listener's proof
/// checked before anything of the dialler's own is sent, the dialler's proof, and the
/// listener's answer. Returns the carrier ready for chunks, or why it was refused.
pub(super) async fn dial(
    address: &str,
    hello: &LaneHello,
    secret: &str,
    tls: Option<&LaneTlsClient>,
) -> Result<Carrier, Attempt> {
    let unreachable = |e: &dyn std::fmt::Display| Attempt::Again(e.to_string());
    let mut tcp = TcpStream::connect(address)
        .await
        .map_err(|e| unreachable(&e))?;
    tcp.set_nodelay(true).map_err(|e| unreachable(&e))?;
    let magic = if tls.is_some() {
        TLS_LANE_MAGIC
    } else {
        LANE_MAGIC
    };
    tcp.write_all(magic).await.map_err(|e| unreachable(&e))?;
    let mut carrier = match tls {
        None => Carrier::Plain(tcp),
        Some(tls) => {
            // A certificate refused is final; a connection lost mid-handshake is not.
            let records = tls_handshake::as_client(tcp, tls.config.clone(), tls.name.clone())
                .await
                .map_err(|e| match e {
                    TlsHandshakeError::Io(e) => unreachable(&e),
                    refused => {
                        Attempt::Refused(format!("the lane's TLS handshake failed: {refused}"))
                    }
                })?;
            Carrier::Tls(Box::new(records))
        }
    };
    prove_to_listener(&mut carrier, hello, secret).await?;
    Ok(carrier)
}

/// The dialler's side of the mutual proof on an opened connection: the hello, the listener's
/// proof checked first, then the dialler's own, and the answer.
async fn prove_to_listener(
    stream: &mut Carrier,
    hello: &LaneHello,
    secret: &str,
) -> Result<(), Attempt> {
    let unreachable = |e: &dyn std::fmt::Display| Attempt::Again(e.to_string());
    let nonce = handshake::fresh_nonce().map_err(|e| Attempt::Refused(e.to_string()))?;
    let hello = LaneHello {
        nonce,
        ..hello.clone()
    };
    send(stream, &hello).await.map_err(|e| unreachable(&e))?;
    let challenge: LaneChallenge = read_framed(stream, MAX_HANDSHAKE_BYTES)
        .await
        .map_err(|e| unreachable(&e))?;
    if !challenge.refusal.is_empty() {
        return Err(Attempt::Refused(challenge.refusal));
    }
    if !handshake::verify(
        Role::Listener,
        secret,
        &hello.nonce,
        &hello,
        &challenge.proof,
    ) {
        return Err(Attempt::Refused(
            "the listener could not prove that it holds this ring's secret".into(),
        ));
    }
    let proof = LaneProof {
        proof: handshake::prove(Role::Dialler, secret, &challenge.nonce, &hello),
    };
    send(stream, &proof).await.map_err(|e| unreachable(&e))?;
    let answer: LaneAnswer = read_framed(stream, MAX_HANDSHAKE_BYTES)
        .await
        .map_err(|e| unreachable(&e))?;
    if answer.refusal.is_empty() {
        Ok(())
    } else {
        Err(Attempt::Refused(answer.refusal))
    }
}

/// Reads a lane's magic from a connection the listener accepted: whether it asks for TLS.
pub(super) async fn read_magic(tcp: &mut TcpStream) -> Result<bool, HandshakeError> {
    let mut magic = [0u8; LANE_MAGIC.len()];
    tcp.read_exact(&mut magic).await?;
    Ok(&magic == TLS_LANE_MAGIC)
}

/// Reads a lane's hello, after its magic (and TLS, when the lane runs it).
pub(super) async fn read_hello(stream: &mut Carrier) -> Result<LaneHello, HandshakeError> {
    read_framed(stream, MAX_HANDSHAKE_BYTES).await
}

/// Refuses a lane at its challenge, saying why.
pub(super) async fn refuse<S: AsyncWrite + Unpin>(
    stream: &mut S,
    refusal: &str,
) -> std::io::Result<()> {
    let challenge = LaneChallenge {
        refusal: refusal.to_string(),
        ..LaneChallenge::default()
    };
    send(stream, &challenge).await
}

/// The listener's side of the mutual proof for `hello` under the ring secret `secret`: sends
/// its proof and a fresh nonce, reads the dialler's proof. Returns whether the dialler proved
/// that it holds the secret (refusing it on the connection when it did not).
pub(super) async fn challenge(
    stream: &mut Carrier,
    hello: &LaneHello,
    secret: &str,
) -> Result<bool, HandshakeError> {
    let nonce = handshake::fresh_nonce().map_err(std::io::Error::other)?;
    let challenge = LaneChallenge {
        refusal: String::new(),
        proof: handshake::prove(Role::Listener, secret, &hello.nonce, hello),
        nonce: nonce.clone(),
    };
    send(stream, &challenge).await?;
    let proof: LaneProof = read_framed(stream, MAX_HANDSHAKE_BYTES).await?;
    let proven = handshake::verify(Role::Dialler, secret, &nonce, hello, &proof.proof);
    if !proven {
        answer(stream, "wrong proof of the ring's secret").await?;
    }
    Ok(proven)
}

/// Answers a proven lane: an empty refusal admits it (sent once its ring has taken it).
pub(super) async fn answer(stream: &mut Carrier, refusal: &str) -> std::io::Result<()> {
    let answer = LaneAnswer {
        refusal: refusal.to_string(),
    };
    send(stream, &answer).await
}
