//! A registered worker and where it stands. Its state is one enum, [`MemberState`], whose
//! transitions are the methods below: every rule about what a heartbeat, a request for work,
//! an assignment, a step report or a loss does to a member lives here, tested on its own.

use std::time::Instant;

use settings::work::Activity;
use settings::{DeviceInUse, Phase};

/// A registered worker.
#[derive(Debug, Clone)]
pub(super) struct Member {
    pub(super) name: String,
    pub(super) address: String,
    pub(super) last_seen: Instant,
    pub(super) samples_per_s: f64,
    /// The device it said it trains on, once a generation resolved it.
    pub(super) device: Option<DeviceInUse>,
    pub(super) state: MemberState,
}

impl Member {
    /// A worker that just registered at `now`.
    pub(super) fn new(name: String, address: String, now: Instant) -> Self {
        Self {
            name,
            address,
            last_seen: now,
            samples_per_s: 0.0,
            device: None,
            state: MemberState::Working(StepProgress::idle(now)),
        }
    }
}

/// What a member is doing within its generation, as its heartbeats and reports say.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct StepProgress {
    /// What it last said it was doing.
    pub(super) activity: Activity,
    /// At which step.
    pub(super) step: u64,
    /// Since when it has been doing that.
    pub(super) since: Instant,
    /// The last step it reported finished in this generation.
    pub(super) finished: Option<(Phase, u64)>,
}

impl StepProgress {
    fn idle(now: Instant) -> Self {
        Self {
            activity: Activity::Idle,
            step: 0,
            since: now,
            finished: None,
        }
    }
}

/// Where a member stands.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum MemberState {
    /// Registered, assigned or between steps, and not asking for work.
    Working(StepProgress),
    /// Asking for its next assignment after generation `after`.
    Waiting {
        /// The newest generation it has had.
        after: u64,
        /// How far it got in that generation.
        progress: StepProgress,
    },
    /// Silent past the heartbeat timeout, left, or blamed: in no group again under this id.
    Lost,
}

impl MemberState {
    /// Whether it is lost.
    pub(super) fn is_lost(&self) -> bool {
        matches!(self, Self::Lost)
    }

    /// The generation it asks for work after, while it asks.
    pub(super) fn waiting_after(&self) -> Option<u64> {
        match self {
            Self::Waiting { after, .. } => Some(*after),
            _ => None,
        }
    }

    /// How far it is in its generation, unless lost.
    pub(super) fn progress(&self) -> Option<&StepProgress> {
        match self {
            Self::Working(progress) | Self::Waiting { progress, .. } => Some(progress),
            Self::Lost => None,
        }
    }

    fn progress_mut(&mut self) -> Option<&mut StepProgress> {
        match self {
            Self::Working(progress) | Self::Waiting { progress, .. } => Some(progress),
            Self::Lost => None,
        }
    }

    /// A heartbeat says it does `activity` at `step`: the clock of that activity starts at
    /// `now` when it changed.
    pub(super) fn heard(&mut self, activity: Activity, step: u64, now: Instant) {
        if let Some(progress) = self.progress_mut()
            && (progress.activity, progress.step) != (activity, step)
        {
            (progress.activity, progress.step, progress.since) = (activity, step, now);
        }
    }

    /// It asks for work after generation `after`.
    pub(super) fn asks_after(&mut self, after: u64) {
        if let Some(&progress) = self.progress() {
            *self = Self::Waiting { after, progress };
        }
    }

    /// It was handed its assignment.
    pub(super) fn assigned(&mut self) {
        if let Self::Waiting { progress, .. } = *self {
            *self = Self::Working(progress);
        }
    }

    /// It joins a new group at `now`: it has finished no step of it and is idle until it
    /// starts, so stall detection measures from the group's formation.
    pub(super) fn joins_group(&mut self, now: Instant) {
        if let Some(progress) = self.progress_mut() {
            *progress = StepProgress::idle(now);
        }
    }

    /// It reports `step` of `phase` finished.
    pub(super) fn finished(&mut self, phase: Phase, step: u64) {
        if let Some(progress) = self.progress_mut() {
            progress.finished = Some((phase, step));
        }
    }

    /// Whether it asks for more work after `generation` without having finished `last` of
    /// it: its part of that generation went wrong.
    pub(super) fn gave_up(&self, generation: u64, last: (Phase, u64)) -> bool {
        match self {
            Self::Waiting { after, progress } => {
                *after == generation && progress.finished != Some(last)
            }
            _ => false,
        }
    }

    /// It is lost; returns whether it was not already.
    pub(super) fn lose(&mut self) -> bool {
        !std::mem::replace(self, Self::Lost).is_lost()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_member_moves_from_work_to_waiting_and_back_and_is_lost_once() {
        let start = Instant::now();
        let mut state = Member::new("w".into(), "a:1".into(), start).state;
        assert_eq!(state.waiting_after(), None);
        state.asks_after(0);
        assert_eq!(state.waiting_after(), Some(0));
        state.assigned();
        state.joins_group(start);
        assert_eq!(state.waiting_after(), None);

        let later = start + Duration::from_secs(5);
        state.heard(Activity::Computing, 3, later);
        state.heard(Activity::Computing, 3, later + Duration::from_secs(1));
        let progress = *state.progress().unwrap();
        assert_eq!(
            (progress.activity, progress.step, progress.since),
            (Activity::Computing, 3, later)
        );

        state.finished(Phase::Stage1, 3);
        state.asks_after(7);
        assert!(
            !state.gave_up(7, (Phase::Stage1, 3)),
            "it finished the stage"
        );
        assert!(state.gave_up(7, (Phase::Stage1, 9)), "it stopped short");
        assert!(
            !state.gave_up(6, (Phase::Stage1, 9)),
            "about another generation"
        );
        state.joins_group(later);
        assert_eq!(state.progress().unwrap().finished, None);

        assert!(state.lose());
        assert!(!state.lose(), "lost once");
        state.asks_after(8);
        state.heard(Activity::Allreduce, 1, later);
        assert_eq!(
            state,
            MemberState::Lost,
            "nothing brings a lost member back"
        );
        assert_eq!(state.progress(), None);
    }
}
