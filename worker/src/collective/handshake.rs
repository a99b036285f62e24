//! The lanes' mutual proof: each side shows that it holds the dialler's ring secret of the
//! generation by an HMAC over a fresh nonce of the other side's, so the secret never crosses
//! the connection and a proof seen once is worth nothing on the next connection.
//!
//! The listener proves itself first, over the dialler's nonce from its hello, so whoever
//! answers at a neighbour's old address learns nothing from a dialler: not the secret, not a
//! proof it could replay. The two roles' proofs carry different labels, so a listener's proof
//! never passes for a dialler's. Both cover the generation, the lane and the ring's lane count,
//! so a proof for one lane does not open another. The nonces are the one place this project
//! draws from the system's randomness instead of its seed: they must not be predictable.

use proto::v1::LaneHello;
use ring::hmac;
use ring::rand::{SecureRandom, SystemRandom};

/// Bytes of a nonce.
pub(super) const NONCE_BYTES: usize = 32;

/// Which side of a lane a proof is from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Role {
    /// The rank that accepted the connection (the dialler's right neighbour).
    Listener,
    /// The rank that opened it.
    Dialler,
}

impl Role {
    fn label(self) -> &'static [u8] {
        match self {
            Role::Listener => b"xfactor-lane-listener",
            Role::Dialler => b"xfactor-lane-dialler",
        }
    }
}

/// The system's random generator could not give a nonce.
#[derive(Debug, thiserror::Error)]
#[error("the system's random number generator failed")]
pub(super) struct NoRandomness;

/// A fresh nonce from the system's random generator.
pub(super) fn fresh_nonce() -> Result<Vec<u8>, NoRandomness> {
    let mut nonce = vec![0u8; NONCE_BYTES];
    SystemRandom::new()
        .fill(&mut nonce)
        .map_err(|_| NoRandomness)?;
    Ok(nonce)
}

/// The bytes a proof covers: the role's label, the other side's nonce, and the lane's place.
fn message(role: Role, nonce: &[u8], hello: &LaneHello) -> Vec<u8> {
    let label = role.label();
    let mut bytes = Vec::with_capacity(label.len() + nonce.len() + 16);
    bytes.extend_from_slice(label);
    bytes.extend_from_slice(nonce);
    bytes.extend_from_slice(&hello.generation.to_le_bytes());
    bytes.extend_from_slice(&hello.lane.to_le_bytes());
    bytes.extend_from_slice(&hello.lanes.to_le_bytes());
    bytes
}

/// `role`'s proof over `nonce` (the other side's) for the lane `hello` opens, keyed with the
/// ring secret `secret`.
pub(super) fn prove(role: Role, secret: &str, nonce: &[u8], hello: &LaneHello) -> Vec<u8> {
    let key = hmac::Key::new(hmac::HMAC_SHA256, secret.as_bytes());
    hmac::sign(&key, &message(role, nonce, hello))
        .as_ref()
        .to_vec()
}

/// Whether `proof` is `role`'s proof over `nonce` for `hello`'s lane under `secret` (compared
/// in constant time). An empty nonce never verifies: it would make a proof replayable.
pub(super) fn verify(
    role: Role,
    secret: &str,
    nonce: &[u8],
    hello: &LaneHello,
    proof: &[u8],
) -> bool {
    if nonce.len() != NONCE_BYTES {
        return false;
    }
    let key = hmac::Key::new(hmac::HMAC_SHA256, secret.as_bytes());
    hmac::verify(&key, &message(role, nonce, hello), proof).is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hello(lane: u32) -> LaneHello {
        LaneHello {
            generation: 9,
            lane,
            lanes: 2,
            nonce: vec![1; NONCE_BYTES],
        }
    }

    #[test]
    fn a_proof_verifies_only_under_its_secret_nonce_role_and_lane() {
        let nonce = fresh_nonce().unwrap();
        let proof = prove(Role::Dialler, "secret", &nonce, &hello(0));
        assert!(verify(Role::Dialler, "secret", &nonce, &hello(0), &proof));
        assert!(!verify(Role::Dialler, "other", &nonce, &hello(0), &proof));
        assert!(!verify(Role::Listener, "secret", &nonce, &hello(0), &proof));
        assert!(!verify(Role::Dialler, "secret", &nonce, &hello(1), &proof));
        let other_nonce = fresh_nonce().unwrap();
        assert!(!verify(
            Role::Dialler,
            "secret",
            &other_nonce,
            &hello(0),
            &proof
        ));
        let other_generation = LaneHello {
            generation: 10,
            ..hello(0)
        };
        assert!(!verify(
            Role::Dialler,
            "secret",
            &nonce,
            &other_generation,
            &proof
        ));
    }

    #[test]
    fn a_proof_is_hmac_sha256_over_label_nonce_and_place() {
        // Python's hmac over b"xfactor-lane-listener" + 32 bytes of 1 + generation 9 (u64),
        // lane 1 and lanes 2 (u32), little-endian, keyed with b"k".
        let expected = "0c72d5e0c43deda791329df92edd4f3dc11d4357f32f2a1fcee698a1d2543b6f";
        let proof = prove(Role::Listener, "k", &[1; NONCE_BYTES], &hello(1));
        let hex: String = proof.iter().map(|byte| format!("{byte:02x}")).collect();
        assert_eq!(hex, expected);
    }

    #[test]
    fn nonces_are_fresh_and_a_short_nonce_never_verifies() {
        assert_ne!(fresh_nonce().unwrap(), fresh_nonce().unwrap());
        let proof = prove(Role::Dialler, "secret", &[], &hello(0));
        assert!(!verify(Role::Dialler, "secret", &[], &hello(0), &proof));
    }
}
