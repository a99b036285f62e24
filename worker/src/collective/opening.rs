//! A lane connection's opening: the magic, the hello, the mutual proof of the ring's secret
//! (`handshake.rs`) and the listener's answer, each message framed by its length. The dialler
//! and the listener sides of it, so that `lane.rs` starts from a connection ready for chunks.

use prost::Message;
use proto::v1::{LaneAnswer, LaneChallenge, LaneHello, LaneProof};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::core::Attempt;
use super::handshake::{self, Role};

/// The first bytes of a lane connection (a gRPC connection opens with HTTP/2's preface or a
/// TLS hello, never with these).
pub const LANE_MAGIC: &[u8; 8] = b"XFLANE01";

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
pub(super) async fn read_framed<M: Message + Default>(
    stream: &mut TcpStream,
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

/// Opens lane `hello.lane` to `address` as the holder of the ring secret `secret`: the magic
/// and the hello (with a fresh nonce), the listener's proof checked before anything of the
/// dialler's own is sent, the dialler's proof, and the listener's answer. Returns the
/// connection ready for chunks, or why it was refused.
pub(super) async fn dial(
    address: &str,
    hello: &LaneHello,
    secret: &str,
) -> Result<TcpStream, Attempt> {
    let unreachable = |e: &dyn std::fmt::Display| Attempt::Again(e.to_string());
    let nonce = handshake::fresh_nonce().map_err(|e| Attempt::Refused(e.to_string()))?;
    let hello = LaneHello {
        nonce,
        ..hello.clone()
    };
    let mut stream = TcpStream::connect(address)
        .await
        .map_err(|e| unreachable(&e))?;
    stream.set_nodelay(true).map_err(|e| unreachable(&e))?;
    let mut opening = LANE_MAGIC.to_vec();
    opening.extend_from_slice(&framed(&hello));
    stream
        .write_all(&opening)
        .await
        .map_err(|e| unreachable(&e))?;
    let challenge: LaneChallenge = read_framed(&mut stream, MAX_HANDSHAKE_BYTES)
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
    stream
        .write_all(&framed(&proof))
        .await
        .map_err(|e| unreachable(&e))?;
    let answer: LaneAnswer = read_framed(&mut stream, MAX_HANDSHAKE_BYTES)
        .await
        .map_err(|e| unreachable(&e))?;
    if answer.refusal.is_empty() {
        Ok(stream)
    } else {
        Err(Attempt::Refused(answer.refusal))
    }
}

/// Reads a lane's hello, after its magic, from a connection the listener accepted.
pub(super) async fn read_hello(stream: &mut TcpStream) -> Result<LaneHello, HandshakeError> {
    let mut magic = [0u8; LANE_MAGIC.len()];
    stream.read_exact(&mut magic).await?;
    read_framed(stream, MAX_HANDSHAKE_BYTES).await
}

/// Refuses a lane at its challenge, saying why.
pub(super) async fn refuse(stream: &mut TcpStream, refusal: &str) -> std::io::Result<()> {
    let challenge = LaneChallenge {
        refusal: refusal.to_string(),
        ..LaneChallenge::default()
    };
    stream.write_all(&framed(&challenge)).await
}

/// The listener's side of the mutual proof for `hello` under the ring secret `secret`: sends
/// its proof and a fresh nonce, reads the dialler's proof. Returns whether the dialler proved
/// that it holds the secret (refusing it on the connection when it did not).
pub(super) async fn challenge(
    stream: &mut TcpStream,
    hello: &LaneHello,
    secret: &str,
) -> Result<bool, HandshakeError> {
    let nonce = handshake::fresh_nonce().map_err(std::io::Error::other)?;
    let challenge = LaneChallenge {
        refusal: String::new(),
        proof: handshake::prove(Role::Listener, secret, &hello.nonce, hello),
        nonce: nonce.clone(),
    };
    stream.write_all(&framed(&challenge)).await?;
    let proof: LaneProof = read_framed(stream, MAX_HANDSHAKE_BYTES).await?;
    let proven = handshake::verify(Role::Dialler, secret, &nonce, hello, &proof.proof);
    if !proven {
        answer(stream, "wrong proof of the ring's secret").await?;
    }
    Ok(proven)
}

/// Answers a proven lane: an empty refusal admits it (sent once its ring has taken it).
pub(super) async fn answer(stream: &mut TcpStream, refusal: &str) -> std::io::Result<()> {
    let answer = LaneAnswer {
        refusal: refusal.to_string(),
    };
    stream.write_all(&framed(&answer)).await
}
