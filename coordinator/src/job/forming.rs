//! Forming a generation: deciding when enough eligible workers wait, picking them, and handing
//! each its rank's assignment. The first group waits for `expected` workers (or `minimum` once
//! the quorum timeout passes); later groups re-form from whoever is left once every survivor
//! waits and the regroup grace has let a replacement register.

use std::time::Instant;

use settings::Phase;
use settings::work::{Assignment, TrainStart, Work};

use super::{GenerationStart, Group, JobState, Member, assignments};

impl JobState {
    /// Forms the next generation when the waiting workers allow one, and the object store's
    /// back-off after a failure on it has passed; returns whether it did.
    pub(super) fn try_form(&mut self, now: Instant) -> bool {
        if !self.store_retry.allows(now) {
            return false;
        }
        let Some(waiting) = self.ready_to_form(now) else {
            return false;
        };
        let phase = self.durable.phase;
        let size = if phase.is_training() {
            self.plan.config.workers.expected.0 as usize
        } else {
            1
        };
        let members: Vec<u64> = waiting.into_iter().take(size).collect();
        // The generation advances only once its group has its work.
        let generation = self.generation + 1;
        let Some(assignments) = self.group_assignments(phase, &members, generation) else {
            return false;
        };
        self.generation = generation;
        tracing::info!(
            generation,
            %phase,
            world_size = members.len(),
            resume = ?self.durable.last_commit.as_ref().map(|c| c.step),
            "group formed"
        );
        for (rank, (&worker, assignment)) in members.iter().zip(assignments).enumerate() {
            if rank == 0 {
                self.record_generation_start(phase, members.len(), &assignment);
            }
            self.assignments.insert(worker, assignment);
            self.restart_progress(worker, now);
        }
        self.group = Some(Group {
            generation: self.generation,
            members,
            phase,
        });
        true
    }

    /// The eligible workers waiting for an assignment, in id order, when there are enough of
    /// them to form a group now; `None` while the job should keep waiting.
    fn ready_to_form(&self, now: Instant) -> Option<Vec<u64>> {
        let eligible = |m: &Member| !m.state.is_lost() && !self.excluded(&m.address, now);
        let alive = self.members.values().filter(|m| eligible(m)).count();
        let waiting: Vec<u64> = self
            .members
            .iter()
            .filter(|(_, m)| eligible(m) && m.state.waiting_after().is_some())
            .map(|(&id, _)| id)
            .collect();
        let ready = if self.generation == self.first_generation {
            self.first_group_ready(waiting.len(), now)
        } else {
            self.regroup_ready(waiting.len(), alive, now)
        };
        ready.then_some(waiting)
    }

    /// The first group starts with `expected` workers, or with `minimum` once the quorum
    /// timeout since the first registration has passed (a job should not wait forever for a
    /// worker that never comes).
    fn first_group_ready(&self, waiting: usize, now: Instant) -> bool {
        let settings = &self.plan.config.workers;
        let quorum_over = self
            .first_registration
            .is_some_and(|t| now.duration_since(t) >= self.timing.quorum_timeout);
        waiting >= settings.expected.0 as usize
            || (waiting >= settings.minimum.0 as usize && quorum_over)
    }

    /// A later group re-forms once at least `minimum` workers wait and every eligible one is
    /// among them (or `expected` are); short of `expected`, it also waits out the regroup grace
    /// after a loss so that a replacement can take the lost worker's place.
    fn regroup_ready(&self, waiting: usize, alive: usize, now: Instant) -> bool {
        let settings = &self.plan.config.workers;
        let (expected, minimum) = (settings.expected.0 as usize, settings.minimum.0 as usize);
        let all_in = waiting == alive || waiting >= expected;
        let grace_over = self
            .lost_at
            .is_none_or(|t| now.duration_since(t) >= self.timing.regroup_grace);
        waiting >= minimum && all_in && (grace_over || waiting >= expected)
    }

    /// Each member's assignment in rank order for `generation`: a rank of the training ring,
    /// or the single evaluator's task. `None` when the job has no evaluation section.
    fn group_assignments(
        &self,
        phase: Phase,
        members: &[u64],
        generation: u64,
    ) -> Option<Vec<Assignment>> {
        if !phase.is_training() {
            let evaluation = assignments::evaluate(&self.plan, &self.durable, generation)?;
            return Some(vec![evaluation; members.len()]);
        }
        let peers: Vec<String> = members
            .iter()
            .map(|m| self.members[m].address.clone())
            .collect();
        let trains = (0..members.len()).map(|rank| {
            assignments::train(&self.plan, &self.durable, generation, phase, rank, &peers)
        });
        Some(trains.collect())
    }

    /// Records in the report where the new generation starts from, as rank 0's assignment
    /// says: the checkpoint it resumes, and the weights it initialises or evaluates.
    fn record_generation_start(&mut self, phase: Phase, world_size: usize, rank0: &Assignment) {
        let (resume_from, init_weights_from) = match &rank0.work {
            Work::Train(train) => match &train.start {
                TrainStart::Resume(location) => (location.clone(), String::new()),
                TrainStart::InitWeights(location) => (String::new(), location.clone()),
                TrainStart::Fresh => (String::new(), String::new()),
            },
            Work::Evaluate(evaluate) => {
                let weights: Vec<&str> = evaluate
                    .checkpoints
                    .iter()
                    .map(|c| c.weights.as_str())
                    .collect();
                (String::new(), weights.join(" "))
            }
            Work::Finish => (String::new(), String::new()),
        };
        self.report.generations.push(GenerationStart {
            generation: self.generation,
            phase,
            world_size,
            resume_from,
            init_weights_from,
        });
    }

    /// A member of a new group has finished no step of it yet and is idle until it starts,
    /// so stall detection measures from the group's formation.
    fn restart_progress(&mut self, worker: u64, now: Instant) {
        if let Some(member) = self.members.get_mut(&worker) {
            member.state.joins_group(now);
        }
    }
}
