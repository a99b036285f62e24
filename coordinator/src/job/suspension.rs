//! Suspending the job at one step that every rank of the group hears.
//!
//! A worker learns of a suspension from the answer to a step report. Were each answer to say
//! "suspend" from the moment it was asked for, ranks that reported the same step on either side
//! of that moment would part: one would exit while the other waited in the next step's
//! all-reduce for it, and would be left behind once the coordinator stopped. So the suspension
//! takes effect at one step, the same for every rank, and the coordinator stops only once
//! every rank has heard it.
//!
//! Why two steps after the first report answered is safe: a worker reports each step and waits
//! for the answer before its next step, and a step's all-reduce needs every rank. So when the
//! coordinator answers a report of step `s`, no rank has reported step `s + 1` yet: every rank
//! is still to report `s + 1`, and each of those answers gives notice of the point at `s + 2`,
//! and every answer to `s + 2` says "suspend".
//!
//! The notice is why the point is two steps off, not one: rank 0 commits the suspension's step,
//! and the coordinator commits only a step whose parameter checksums every rank sent and all
//! agree (`JobState::commit`). With a step's notice, every rank hashes its parameters after the
//! suspension's step whatever the checksum interval.

use std::collections::BTreeSet;

use super::JobState;

/// The step of one generation at which the ranks suspend.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct SuspendPoint {
    /// The group's generation.
    pub generation: u64,
    /// Reports of this step and later are answered "suspend".
    pub step: u64,
}

/// What the answer to a step report says of a suspension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SuspendAnswer {
    /// Train on.
    Continue,
    /// The next step is the suspension's: hash the parameters after it, for its commit.
    ChecksumNext,
    /// Suspend now: rank 0 commits the step just done, every rank exits.
    Suspend,
}

/// A requested suspension: where it takes effect and who has heard it.
#[derive(Debug, Default)]
pub(super) struct Suspension {
    requested: bool,
    point: Option<SuspendPoint>,
    told: BTreeSet<u64>,
}

impl Suspension {
    /// From now on, reports fix the suspension's step and hear it.
    pub fn request(&mut self) {
        self.requested = true;
    }

    /// What the answer to `worker`'s accepted report of `step` in `generation` says. The
    /// first report after the request fixes the point two steps after it (one step of notice);
    /// a newer generation (the group re-formed) fixes it afresh, and an older one never
    /// suspends (its group is gone and its members hear so anyway).
    pub fn answer(&mut self, worker: u64, generation: u64, step: u64) -> SuspendAnswer {
        if !self.requested {
            return SuspendAnswer::Continue;
        }
        let point = match self.point {
            Some(point) if point.generation == generation => point,
            Some(point) if point.generation > generation => return SuspendAnswer::Continue,
            _ => {
                self.told.clear();
                *self.point.insert(SuspendPoint {
                    generation,
                    step: step + 2,
                })
            }
        };
        if step >= point.step {
            self.told.insert(worker);
            SuspendAnswer::Suspend
        } else if step + 1 == point.step {
            SuspendAnswer::ChecksumNext
        } else {
            SuspendAnswer::Continue
        }
    }

    /// The point fixed so far, if any.
    pub fn point(&self) -> Option<SuspendPoint> {
        self.point
    }

    /// Whether every one of `members` of `generation` has been told to suspend.
    pub fn heard_by(&self, generation: u64, members: &[u64]) -> bool {
        self.point.is_some_and(|p| p.generation == generation)
            && members.iter().all(|m| self.told.contains(m))
    }
}

impl JobState {
    /// Suspends the job: the group's ranks hear it two steps after the next report (see the
    /// module's doc), rank 0 commits that step, and every rank exits.
    pub fn request_suspension(&mut self) {
        self.suspension.request();
    }

    /// What the answer to `worker`'s report of `step` in `generation`, which
    /// [`JobState::report_step`] accepted, says of a suspension.
    pub fn suspends(&mut self, worker: u64, generation: u64, step: u64) -> SuspendAnswer {
        self.suspension.answer(worker, generation, step)
    }

    /// Whether the requested suspension is done with the running group: every member has
    /// heard it and rank 0's commit of the suspension's step is in. No group running counts
    /// as done: there is nothing left to commit or to tell.
    pub fn suspension_complete(&self) -> bool {
        let Some(group) = &self.group else {
            return true;
        };
        let Some(point) = self.suspension.point() else {
            return false;
        };
        let committed = self
            .durable
            .last_commit
            .as_ref()
            .is_some_and(|c| c.phase == group.phase && c.step > point.step);
        committed && self.suspension.heard_by(group.generation, &group.members)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use SuspendAnswer::{ChecksumNext, Continue, Suspend};

    #[test]
    fn nothing_suspends_before_the_request() {
        let mut suspension = Suspension::default();
        assert_eq!(suspension.answer(1, 7, 3), Continue);
        assert_eq!(suspension.point(), None);
    }

    #[test]
    fn ranks_on_either_side_of_the_request_all_get_notice_then_suspend_at_one_step() {
        let mut suspension = Suspension::default();
        assert_eq!(
            suspension.answer(1, 7, 3),
            Continue,
            "rank 0 reported before the request"
        );
        suspension.request();
        assert_eq!(
            suspension.answer(2, 7, 3),
            Continue,
            "rank 1's report of the same step"
        );
        assert_eq!(
            suspension.point(),
            Some(SuspendPoint {
                generation: 7,
                step: 5
            })
        );
        assert_eq!(suspension.answer(2, 7, 4), ChecksumNext);
        assert_eq!(suspension.answer(1, 7, 4), ChecksumNext);
        assert!(!suspension.heard_by(7, &[1, 2]));
        assert_eq!(suspension.answer(2, 7, 5), Suspend);
        assert!(!suspension.heard_by(7, &[1, 2]), "rank 0 has not heard yet");
        assert_eq!(suspension.answer(1, 7, 5), Suspend);
        assert!(suspension.heard_by(7, &[1, 2]));
    }

    #[test]
    fn a_reformed_group_fixes_its_own_point_and_a_stale_generation_never_suspends() {
        let mut suspension = Suspension::default();
        suspension.request();
        assert_eq!(suspension.answer(1, 7, 10), Continue);
        assert_eq!(suspension.answer(1, 7, 11), ChecksumNext);
        assert_eq!(suspension.answer(1, 7, 12), Suspend);
        assert_eq!(
            suspension.answer(1, 8, 2),
            Continue,
            "the new group's first report"
        );
        assert!(
            !suspension.heard_by(8, &[1]),
            "what generation 7 heard does not count"
        );
        assert_eq!(suspension.answer(2, 7, 13), Continue, "a stale report");
        assert_eq!(suspension.answer(1, 8, 3), ChecksumNext);
        assert_eq!(suspension.answer(1, 8, 4), Suspend);
        assert!(suspension.heard_by(8, &[1]));
        assert!(!suspension.heard_by(7, &[1]));
    }
}
