//! Secrets beyond the job token. The token admits a process to the job; a session secret
//! proves which worker it is: every request that names a worker id must carry the secret its
//! registration was given, so a holder of the token cannot leave, report or commit as another
//! worker. Ring secrets prove which rank a chunk stream comes from: each rank of a generation
//! gets its own, and its right neighbour gets it too, to demand of the stream. Secrets live
//! only in this coordinator's memory: after a restart every worker is unknown and registers
//! again.

use std::collections::btree_map::Entry;
use std::collections::{BTreeMap, HashMap};
use std::sync::Mutex;

use proto::v1::Assignment;
use proto::v1::assignment::Work;
use tonic::Status;

/// Random bytes per secret (128 bits), sent as 32 hex digits.
const SECRET_BYTES: usize = 16;

/// The secret of every registered worker.
#[derive(Default)]
pub struct Sessions {
    secrets: Mutex<HashMap<u64, String>>,
}

impl Sessions {
    /// A fresh secret for `worker`.
    pub fn issue(&self, worker: u64) -> Result<String, Status> {
        let secret = random_secret()?;
        self.lock().insert(worker, secret.clone());
        Ok(secret)
    }

    /// Refuses a request naming `worker` unless it carries that worker's secret: not found
    /// for an id this coordinator never issued (register again), permission denied for a
    /// wrong secret.
    pub fn check(&self, worker: u64, presented: &str) -> Result<(), Status> {
        let secrets = self.lock();
        let Some(expected) = secrets.get(&worker) else {
            return Err(Status::not_found(format!(
                "unknown worker {worker}: register first"
            )));
        };
        if proto::constant_time_equal(presented.as_bytes(), expected.as_bytes()) {
            Ok(())
        } else {
            tracing::warn!(worker, "request with a wrong session secret refused");
            Err(Status::permission_denied(format!(
                "worker {worker}: the session secret does not match its registration"
            )))
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u64, String>> {
        // A panic while holding this lock leaves the map itself consistent.
        self.secrets
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// 128 bits from the operating system's random source, as hex.
fn random_secret() -> Result<String, Status> {
    let mut bytes = [0u8; SECRET_BYTES];
    getrandom::fill(&mut bytes)
        .map_err(|e| Status::internal(format!("no randomness for a secret: {e}")))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Generations whose ring secrets are kept (a late member of an old generation is refused by
/// the job state anyway).
const RING_GENERATIONS_KEPT: usize = 4;

/// Each generation's ring secrets, one per rank.
#[derive(Default)]
pub struct RingSecrets {
    generations: Mutex<BTreeMap<u64, Vec<String>>>,
}

impl RingSecrets {
    /// Puts the rank's own and its left neighbour's secret into a training assignment of a
    /// group of two or more; other assignments are left as they are.
    pub fn fill(&self, assignment: &mut Assignment) -> Result<(), Status> {
        let generation = assignment.generation;
        let Some(Work::Train(train)) = assignment.work.as_mut() else {
            return Ok(());
        };
        let (rank, world) = (train.rank as usize, train.world_size as usize);
        if world < 2 || rank >= world {
            return Ok(());
        }
        let mut generations = self
            .generations
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let secrets = match generations.entry(generation) {
            Entry::Occupied(known) => known.get().clone(),
            Entry::Vacant(new) => new
                .insert(
                    (0..world)
                        .map(|_| random_secret())
                        .collect::<Result<_, _>>()?,
                )
                .clone(),
        };
        while generations.len() > RING_GENERATIONS_KEPT {
            generations.pop_first();
        }
        train.ring_secret = secrets[rank].clone();
        train.left_ring_secret = secrets[(rank + world - 1) % world].clone();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_issued_secret_speaks_for_its_worker() {
        let sessions = Sessions::default();
        let first = sessions.issue(1).unwrap();
        let second = sessions.issue(2).unwrap();
        assert_eq!(first.len(), 2 * SECRET_BYTES);
        assert_ne!(first, second);
        assert!(sessions.check(1, &first).is_ok());
        let forged = sessions.check(1, &second).unwrap_err();
        assert_eq!(forged.code(), tonic::Code::PermissionDenied);
        assert_eq!(
            sessions.check(1, "").unwrap_err().code(),
            tonic::Code::PermissionDenied
        );
        assert_eq!(
            sessions.check(3, &first).unwrap_err().code(),
            tonic::Code::NotFound
        );
    }

    #[test]
    fn each_rank_holds_its_own_and_its_left_neighbours_ring_secret() {
        let secrets = RingSecrets::default();
        let assignment = |rank: u32| {
            let mut assignment = Assignment {
                generation: 9,
                work: Some(Work::Train(proto::v1::TrainAssignment {
                    rank,
                    world_size: 3,
                    ..Default::default()
                })),
            };
            secrets.fill(&mut assignment).unwrap();
            match assignment.work {
                Some(Work::Train(train)) => (train.ring_secret, train.left_ring_secret),
                _ => unreachable!(),
            }
        };
        let ranks: Vec<(String, String)> = (0..3).map(assignment).collect();
        for rank in 0..3 {
            assert_eq!(ranks[rank].1, ranks[(rank + 2) % 3].0, "rank {rank}");
            assert_eq!(ranks[rank].0.len(), 2 * SECRET_BYTES);
        }
        assert_ne!(ranks[0].0, ranks[1].0);
        assert_eq!(assignment(1), ranks[1], "asked again, the same secrets");
    }
}
