//! Whether a worker goes on after a failed generation, decided by whose fault it was.
//!
//! A worker may end itself only for its own faults (its device, its disk, its data), after
//! [`MAX_OWN_FAILURES`] of them in a row. A failure that names someone else (a peer, the object
//! store, a corrupt commit) never ends it: however long the store is down, the worker waits and
//! asks for work again, with a back-off that doubles up to [`MAX_BACKOFF`] and a jitter, so a
//! healthy cluster is still there when the store comes back. A generation the coordinator
//! ended under the worker (to re-form the group) is nobody's failure: it asks again at once.
//! A generation that finishes resets every streak.

use std::time::Duration;

use settings::work::FailureCause;

/// Own failures in a row after which the worker gives up: a device or local file that failed
/// this often will not heal by itself.
pub const MAX_OWN_FAILURES: u32 = 8;

/// The longest pause between two tries after failures that were not this worker's: the
/// coordinator's own store back-off stops at 8 s too, so a returned store is found within
/// seconds (with a 30 s cap, stage 1 committed 11.1 s after a minute's outage, 0.9 s with 8 s).
pub const MAX_BACKOFF: Duration = Duration::from_secs(8);

/// The first pause after a failure that was not this worker's.
const FIRST_BACKOFF: Duration = Duration::from_secs(1);

/// Whose fault a failed generation was, as far as going on is concerned.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Blame {
    /// This worker's own.
    Own,
    /// A peer's.
    Peer,
    /// The object store's.
    Store,
    /// A committed checkpoint that does not verify.
    CorruptCheckpoint,
    /// The coordinator ended the generation (it re-forms the group): nothing to wait for.
    Coordinator,
}

impl Blame {
    /// The blame of a failure's typed cause.
    pub fn of(cause: &FailureCause) -> Self {
        match cause {
            FailureCause::Worker => Self::Own,
            FailureCause::Peer { .. } => Self::Peer,
            FailureCause::Store => Self::Store,
            FailureCause::CorruptCheckpoint { .. } => Self::CorruptCheckpoint,
        }
    }

    /// The label of `xfactor_worker_waiting{cause}` and of the logs.
    pub fn name(self) -> &'static str {
        match self {
            Self::Own => "own",
            Self::Peer => "peer",
            Self::Store => "store",
            Self::CorruptCheckpoint => "corrupt_checkpoint",
            Self::Coordinator => "coordinator",
        }
    }
}

/// What the worker does after a failed generation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AfterFailure {
    /// Ask for work again after `pause`.
    Retry {
        /// How long to wait first (zero after an own failure, whose exclusion the coordinator
        /// already times, and after a generation the coordinator ended).
        pause: Duration,
        /// Whose fault the failure was.
        blame: Blame,
        /// Failures of this blame in a row, this one included.
        in_a_row: u32,
    },
    /// Give up: this worker failed [`MAX_OWN_FAILURES`] generations in a row itself.
    GiveUp {
        /// Its own failures in a row.
        own_in_a_row: u32,
    },
}

/// Consecutive failures by blame since the last generation that finished.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FailureStreaks {
    own: u32,
    others: u32,
}

impl FailureStreaks {
    /// Failures of any blame since the last generation that finished.
    pub fn in_a_row(&self) -> u32 {
        self.own + self.others
    }

    /// A generation finished: every streak starts again.
    pub fn succeeded(&mut self) {
        *self = Self::default();
    }

    /// Records a failure that `blame` is to blame for; `jitter` in `[0, 1)` spreads the pauses
    /// of workers that failed together (a fraction of up to a quarter of the pause is added).
    pub fn failed(&mut self, blame: Blame, jitter: f64) -> AfterFailure {
        if blame == Blame::Coordinator {
            return AfterFailure::Retry {
                pause: Duration::ZERO,
                blame,
                in_a_row: self.in_a_row() + 1,
            };
        }
        if blame == Blame::Own {
            self.own += 1;
            if self.own >= MAX_OWN_FAILURES {
                return AfterFailure::GiveUp {
                    own_in_a_row: self.own,
                };
            }
            return AfterFailure::Retry {
                pause: Duration::ZERO,
                blame,
                in_a_row: self.own,
            };
        }
        self.others += 1;
        AfterFailure::Retry {
            pause: backoff(self.others, jitter),
            blame,
            in_a_row: self.others,
        }
    }
}

/// The pause before try `attempt + 1`: 1 s doubled per failure, at most [`MAX_BACKOFF`], plus
/// up to a quarter of it by `jitter` (clamped to `[0, 1)`, NaN as 0).
fn backoff(attempt: u32, jitter: f64) -> Duration {
    let doublings = attempt.saturating_sub(1).min(16);
    let base = FIRST_BACKOFF
        .saturating_mul(1 << doublings)
        .min(MAX_BACKOFF);
    let jitter = if jitter.is_finite() {
        jitter.clamp(0.0, 0.999)
    } else {
        0.0
    };
    base + base.mul_f64(jitter / 4.0)
}

/// A jitter in `[0, 1)` derived from the worker and the failure count, so each worker's pauses
/// differ from its peers' and a rerun waits the same.
pub fn jitter(worker_id: u64, failures: u32) -> f64 {
    let mut stream = data::rng::Stream::new(&[worker_id, u64::from(failures)]);
    stream.uniform_in(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn own_failures_end_the_worker_after_the_bound() {
        let mut streaks = FailureStreaks::default();
        for in_a_row in 1..MAX_OWN_FAILURES {
            let after = streaks.failed(Blame::Own, 0.5);
            assert_eq!(
                after,
                AfterFailure::Retry {
                    pause: Duration::ZERO,
                    blame: Blame::Own,
                    in_a_row
                }
            );
        }
        assert_eq!(
            streaks.failed(Blame::Own, 0.5),
            AfterFailure::GiveUp {
                own_in_a_row: MAX_OWN_FAILURES
            }
        );
    }

    #[test]
    fn a_store_outage_of_any_length_never_ends_the_worker() {
        let mut streaks = FailureStreaks::default();
        for attempt in 1..=10_000 {
            match streaks.failed(Blame::Store, 0.0) {
                AfterFailure::Retry { pause, blame, .. } => {
                    assert_eq!(blame, Blame::Store);
                    assert!(pause <= MAX_BACKOFF, "{attempt}: {pause:?}");
                }
                AfterFailure::GiveUp { .. } => panic!("gave up at failure {attempt}"),
            }
        }
    }

    #[test]
    fn peers_and_corrupt_commits_are_not_counted_against_the_worker() {
        let mut streaks = FailureStreaks::default();
        for _ in 0..MAX_OWN_FAILURES - 1 {
            streaks.failed(Blame::Own, 0.0);
        }
        for cause in [
            FailureCause::Peer { rank: 1 },
            FailureCause::CorruptCheckpoint {
                location: "stage1/000010".into(),
            },
            FailureCause::Store,
        ] {
            assert!(matches!(
                streaks.failed(Blame::of(&cause), 0.0),
                AfterFailure::Retry { .. }
            ));
        }
        assert!(matches!(
            streaks.failed(Blame::Own, 0.0),
            AfterFailure::GiveUp { own_in_a_row: 8 }
        ));
    }

    #[test]
    fn generations_the_coordinator_ended_never_count_against_the_worker() {
        let mut streaks = FailureStreaks::default();
        for _ in 0..100 {
            assert!(matches!(
                streaks.failed(Blame::Coordinator, 0.0),
                AfterFailure::Retry {
                    pause: Duration::ZERO,
                    blame: Blame::Coordinator,
                    ..
                }
            ));
        }
        assert!(matches!(
            streaks.failed(Blame::Own, 0.0),
            AfterFailure::Retry { in_a_row: 1, .. }
        ));
    }

    #[test]
    fn a_finished_generation_resets_every_streak() {
        let mut streaks = FailureStreaks::default();
        for _ in 0..MAX_OWN_FAILURES - 1 {
            streaks.failed(Blame::Own, 0.0);
        }
        streaks.failed(Blame::Store, 0.0);
        streaks.succeeded();
        assert_eq!(streaks, FailureStreaks::default());
        assert!(matches!(
            streaks.failed(Blame::Own, 0.0),
            AfterFailure::Retry { in_a_row: 1, .. }
        ));
    }

    #[test]
    fn the_backoff_doubles_to_its_cap_with_at_most_a_quarter_of_jitter() {
        assert_eq!(backoff(1, 0.0), Duration::from_secs(1));
        assert_eq!(backoff(2, 0.0), Duration::from_secs(2));
        assert_eq!(backoff(4, 0.0), Duration::from_secs(8));
        assert_eq!(backoff(5, 0.0), MAX_BACKOFF);
        assert_eq!(backoff(u32::MAX, 0.0), MAX_BACKOFF);
        assert_eq!(backoff(1, 0.5), Duration::from_millis(1125));
        for bad in [f64::NAN, f64::INFINITY, -3.0] {
            assert_eq!(backoff(1, bad), Duration::from_secs(1), "{bad}");
        }
        assert!(backoff(6, 1.0) < MAX_BACKOFF.mul_f64(1.25));
    }

    #[test]
    fn jitter_depends_on_the_worker_and_the_failure_only() {
        let value = jitter(3, 1);
        assert!((0.0..1.0).contains(&value));
        assert_eq!(jitter(3, 1), value);
        assert_ne!(jitter(4, 1), value);
        assert_ne!(jitter(3, 2), value);
    }
}
