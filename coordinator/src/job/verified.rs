//! A commit holds parameters every replica agreed on, or it is not taken.
//!
//! Rank 0 uploads its own parameters; whether the other replicas hold the same is known only
//! from the step's parameter checksums. A commit of a step that no full set of checksums covers
//! could hold a replica that diverged since the last check: committed, the divergence would be
//! restored on every rank by the next rollback, and from then on every checksum would agree on
//! it. So a training commit is taken only when every member of its generation sent a checksum
//! for the committed step and all are equal. Workers hash their parameters at every step the
//! commit schedule commits (`worker/src/datapath`), and a suspension gives a step's notice so
//! that its step is hashed too (`suspension.rs`).

use std::collections::BTreeMap;
use std::time::Instant;

use super::{Commit, JobState, Refusal};

/// What the step records say of a commit's step.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum Verification {
    /// Every member sent a checksum and all are equal.
    Verified,
    /// These ranks' checksums have not arrived (yet): the commit may wait for them.
    Missing(Vec<u32>),
    /// The checksums disagree: the commit is refused and the group rolls back.
    Differ(BTreeMap<u32, u32>),
}

impl JobState {
    /// Whether the checksums of the step `commit` saves, sent by the `world_size` ranks of
    /// `generation`, are all in and equal. Only training commits hold parameters to verify.
    fn verification(&self, commit: &Commit, generation: u64, world_size: usize) -> Verification {
        if !commit.phase.is_training() {
            return Verification::Verified;
        }
        let checksums = commit
            .step
            .checked_sub(1)
            .and_then(|index| self.steps.get(commit.phase, index, generation))
            .map(|record| record.checksums.clone())
            .unwrap_or_default();
        verify_checksums(&checksums, world_size)
    }

    /// The refusal for a commit whose verification failed, if it did.
    pub(super) fn check_verified(
        &self,
        commit: &Commit,
        generation: u64,
        world_size: usize,
    ) -> Result<(), Refusal> {
        match self.verification(commit, generation, world_size) {
            Verification::Verified => Ok(()),
            Verification::Missing(ranks) => Err(Refusal::Unverified {
                phase: commit.phase,
                step: commit.step,
                missing: ranks,
            }),
            Verification::Differ(checksums) => Err(Refusal::ChecksumsDiffer {
                phase: commit.phase,
                step: commit.step,
                checksums,
            }),
        }
    }
}

impl JobState {
    /// Ends `generation` at once when a training commit of it was refused for its checksums
    /// (missing after the wait, or differing), rolling back to the last commit as for a
    /// mismatch: before rank 0 hears the refusal, so its report of the failed commit finds
    /// the generation over and blames no one. The odd replica, where a majority named one,
    /// was recorded when its checksum arrived. Returns whether the generation ended.
    pub fn roll_back_refused(&mut self, refusal: &Refusal, generation: u64, now: Instant) -> bool {
        if !matches!(
            refusal,
            Refusal::Unverified { .. } | Refusal::ChecksumsDiffer { .. }
        ) {
            return false;
        }
        if self
            .divergence
            .as_ref()
            .is_none_or(|(g, _)| *g != generation)
        {
            self.divergence = Some((generation, Vec::new()));
        }
        self.roll_back_divergence(now)
    }
}

/// The verdict on one step's checksums by rank, from a generation of `world_size` ranks.
fn verify_checksums(checksums: &BTreeMap<u32, u32>, world_size: usize) -> Verification {
    let missing: Vec<u32> = (0..world_size as u32)
        .filter(|rank| !checksums.contains_key(rank))
        .collect();
    let mut values = checksums.values();
    let first = values.next();
    if first.is_some_and(|first| values.any(|other| other != first)) {
        return Verification::Differ(checksums.clone());
    }
    if missing.is_empty() {
        Verification::Verified
    } else {
        Verification::Missing(missing)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checksums(pairs: &[(u32, u32)]) -> BTreeMap<u32, u32> {
        pairs.iter().copied().collect()
    }

    #[test]
    fn every_rank_equal_is_verified() {
        let all = checksums(&[(0, 7), (1, 7), (2, 7)]);
        assert_eq!(verify_checksums(&all, 3), Verification::Verified);
    }

    #[test]
    fn a_missing_rank_is_named_and_none_at_all_names_every_rank() {
        let partial = checksums(&[(0, 7), (2, 7)]);
        assert_eq!(
            verify_checksums(&partial, 3),
            Verification::Missing(vec![1])
        );
        assert_eq!(
            verify_checksums(&BTreeMap::new(), 2),
            Verification::Missing(vec![0, 1])
        );
    }

    #[test]
    fn a_disagreement_refuses_even_before_every_rank_is_in() {
        let odd = checksums(&[(0, 7), (1, 8)]);
        assert_eq!(verify_checksums(&odd, 3), Verification::Differ(odd.clone()));
    }
}
