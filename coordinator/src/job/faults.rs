//! The job's answers to faults: members stuck in their step while a peer waits, the back-off
//! a blamed worker sits out, and the job-wide limit on skipped frames.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use settings::Phase;
use settings::work::{Activity, StepReport};

use super::members::StepProgress;

use super::{GenerationEnd, JobState, SKIPPED_EXAMPLES, records};

/// The longest wait between groups while the object store keeps failing.
pub const STORE_BACKOFF_MAX: Duration = Duration::from_secs(8);

/// The object store's back-off: consecutive generations that failed on it, and until when the
/// next group waits.
#[derive(Debug, Clone, Default)]
pub(super) struct StoreRetry {
    failures: u32,
    until: Option<Instant>,
    /// The first failure of the current outage.
    since: Option<Instant>,
    /// The job's next step when the store last failed it: the step being computed, or the
    /// commit after the step before it.
    failed_at_step: u64,
}

impl StoreRetry {
    /// Counts one more failure at `now`, while the job was at `next_step`; returns the wait
    /// it imposes.
    fn fail(&mut self, now: Instant, next_step: u64) -> Duration {
        let backoff = Duration::from_secs(1 << self.failures.min(8)).min(STORE_BACKOFF_MAX);
        self.failures += 1;
        self.until = Some(now + backoff);
        self.since.get_or_insert(now);
        self.failed_at_step = next_step;
        backoff
    }

    /// A group formed after the failure trained up to `next_step`. Once that is past the step
    /// where the store failed, the store has answered what it refused and the outage is
    /// over, though the back-off stays until a commit proves uploads work too. Steps re-trained
    /// before a refused upload prove only that reads work, so they leave the outage showing.
    pub(super) fn progressed(&mut self, next_step: u64) {
        if next_step > self.failed_at_step {
            self.since = None;
        }
    }

    /// How long the store has been failing at `now`, while it is.
    pub(super) fn failing_for(&self, now: Instant) -> Option<Duration> {
        self.since.map(|since| now.saturating_duration_since(since))
    }

    /// Whether a group may form at `now`.
    pub(super) fn allows(&self, now: Instant) -> bool {
        self.until.is_none_or(|until| now >= until)
    }
}

impl JobState {
    /// Removes the members of the running group that have not moved on from computing a step
    /// for `stall_timeout` while a peer waits for them in that step's all-reduce: a worker
    /// stuck (in a data read, say) whose heartbeats still arrive. Each is blamed and sits out
    /// a back-off. Returns whether any was removed.
    pub(super) fn remove_stalled(&mut self, now: Instant) -> bool {
        let Some(group) = &self.group else {
            return false;
        };
        let stuck_for = |progress: &StepProgress| {
            now.duration_since(progress.since) > self.timing.stall_timeout
        };
        let waited_on = |step: u64| {
            group.members.iter().any(|m| {
                let progress = self.members.get(m).and_then(|peer| peer.state.progress());
                progress.is_some_and(|peer| {
                    (peer.activity, peer.step) == (Activity::Allreduce, step) && stuck_for(peer)
                })
            })
        };
        let stalled: Vec<u64> = group
            .members
            .iter()
            .copied()
            .filter(|m| {
                let progress = self
                    .members
                    .get(m)
                    .and_then(|member| member.state.progress());
                progress.is_some_and(|member| {
                    matches!(member.activity, Activity::Computing | Activity::Idle)
                        && stuck_for(member)
                        && waited_on(member.step)
                })
            })
            .collect();
        for worker in &stalled {
            let (name, step) = match self.members.get(worker) {
                Some(member) => (
                    member.name.clone(),
                    member.state.progress().map_or(0, |p| p.step),
                ),
                None => continue,
            };
            tracing::warn!(
                worker,
                %name,
                step,
                stall_timeout_s = self.timing.stall_timeout.as_secs_f64(),
                "worker removed: no progress in its step while its peers waited in the all-reduce"
            );
            self.blame(*worker, now);
        }
        !stalled.is_empty()
    }

    /// A member says its part of `generation` failed, pointing at the rank the evidence names
    /// (`None`: itself). While that generation runs, it ends now, the suspect is blamed and
    /// sits out a back-off, and the group re-forms from the last commit; a report about an
    /// older generation changes nothing. Returns whether the generation ended.
    pub fn generation_failed(
        &mut self,
        worker: u64,
        generation: u64,
        reason: &str,
        suspect_rank: Option<u32>,
        now: Instant,
    ) -> bool {
        let Some(group) = self.group.as_ref().filter(|g| g.generation == generation) else {
            return false;
        };
        let Some(rank) = group.members.iter().position(|&m| m == worker) else {
            return false;
        };
        let suspect_rank = suspect_rank.map_or(rank, |r| r as usize);
        let Some(&suspect) = group.members.get(suspect_rank) else {
            return false;
        };
        tracing::warn!(
            generation,
            reporter = worker,
            suspect,
            suspect_rank,
            %reason,
            "generation failed; the suspect sits out and the group re-forms from the last commit"
        );
        self.blame(suspect, now);
        let name = self.members.get(&suspect).map_or("?", |m| m.name.as_str());
        let ended = format!("rank {suspect_rank} ({name}) failed: {reason}");
        self.end_generation(now, ended);
        true
    }

    /// A member says its part of `generation` failed because the object store did: the
    /// generation ends and the group re-forms from the last commit, but no worker is blamed.
    /// The next group waits out the store's own back-off instead (1 s, doubling to
    /// [`STORE_BACKOFF_MAX`], reset by the next commit that lands), so a store that is down
    /// is retried often enough to go on within seconds of its return. Returns whether the
    /// generation ended.
    pub fn store_failed(
        &mut self,
        worker: u64,
        generation: u64,
        reason: &str,
        now: Instant,
    ) -> bool {
        if !self.in_running_group(worker, generation) {
            return false;
        }
        let backoff = self.store_retry.fail(now, self.current_step);
        tracing::warn!(
            generation,
            reporter = worker,
            %reason,
            retry_in_s = backoff.as_secs_f64(),
            "generation failed on the object store; no worker is blamed, the group re-forms after the store's back-off"
        );
        self.end_generation(now, format!("the object store failed: {reason}"));
        true
    }

    /// Ends the running generation at `now` as a restart, for `reason` (kept in the report and
    /// shown on the status page): the next group re-forms from the last commit.
    pub(super) fn end_generation(&mut self, now: Instant, reason: String) {
        if let Some(group) = self.group.take() {
            self.report.generation_ends.push(GenerationEnd {
                generation: group.generation,
                phase: group.phase,
                step: self.current_step,
                reason,
            });
        }
        self.report.restarts += 1;
        self.lost_at = Some(now);
    }

    /// Whether `worker` is a member of `generation` and that generation still runs: a report
    /// about any other generation changes nothing.
    fn in_running_group(&self, worker: u64, generation: u64) -> bool {
        self.group
            .as_ref()
            .is_some_and(|g| g.generation == generation && g.members.contains(&worker))
    }

    /// A member of `generation` found the committed checkpoint at `location` corrupt. When it
    /// is the phase's newest commit, the phase falls back to the commit before it (or to the
    /// phase's start), no one is blamed, and the group re-forms from there. Returns whether
    /// the generation ended.
    pub fn checkpoint_corrupt(
        &mut self,
        worker: u64,
        generation: u64,
        location: &str,
        now: Instant,
    ) -> bool {
        if !self.in_running_group(worker, generation) {
            return false;
        }
        if self
            .durable
            .last_commit
            .as_ref()
            .is_some_and(|c| c.location == location)
        {
            self.durable.fall_back();
            tracing::error!(
                %location,
                fallback = ?self.durable.last_commit.as_ref().map(|c| &c.location),
                "the newest commit is corrupt; the phase falls back to the one before it"
            );
            self.report.fallbacks.push(location.to_string());
        } else {
            tracing::error!(%location, "a checkpoint the group starts from is corrupt; nothing to fall back to");
        }
        self.end_generation(now, format!("checkpoint {location} is corrupt"));
        true
    }

    /// Ends a generation whose replicas' parameter checksums disagreed: the group re-forms
    /// from the last commit, where every replica is identical again. A member whose checksum
    /// was the odd one out twice (across registrations) is blamed and sits out a back-off.
    /// Returns whether a generation ended.
    pub(super) fn roll_back_divergence(&mut self, now: Instant) -> bool {
        let Some((generation, odd)) = self.divergence.take() else {
            return false;
        };
        if self
            .group
            .as_ref()
            .is_none_or(|g| g.generation != generation)
        {
            return false;
        }
        tracing::error!(
            generation,
            ?odd,
            "replicas diverged; the group rolls back to the last commit"
        );
        for worker in odd {
            let Some(address) = self.members.get(&worker).map(|m| m.address.clone()) else {
                continue;
            };
            let penalty = self.penalties.entry(address).or_default();
            penalty.divergences += 1;
            if penalty.divergences >= 2 {
                self.blame(worker, now);
            }
        }
        self.end_generation(
            now,
            "the replicas' parameter checksums disagreed: rolled back to the last commit".into(),
        );
        true
    }

    /// After a mid-stage commit, ends a group smaller than `expected` when workers that are
    /// not in it wait for work (late joiners, returned workers): the next group, formed at
    /// once from the commit just made, takes them in, so nothing is redone.
    pub(super) fn grow_at_commit(&mut self, step: u64) {
        let Some(group) = &self.group else {
            return;
        };
        let expected = self.plan.config.workers.expected.0 as usize;
        let excluded = |address: &str| self.last_tick.is_some_and(|t| self.excluded(address, t));
        let joiners = self
            .members
            .iter()
            .filter(|(id, m)| {
                m.state.waiting_after().is_some()
                    && !group.members.contains(id)
                    && !excluded(&m.address)
            })
            .count();
        if joiners == 0 || group.members.len() >= expected {
            return;
        }
        tracing::info!(
            generation = group.generation,
            step,
            joiners,
            "workers waiting to join: the group re-forms at this commit"
        );
        self.group = None;
        self.lost_at = None;
    }

    /// Marks `worker` lost and excludes its address from groups for a back-off that doubles
    /// with each failure it is blamed for.
    fn blame(&mut self, worker: u64, now: Instant) {
        let Some(member) = self.members.get_mut(&worker) else {
            return;
        };
        member.state.lose();
        let penalty = self.penalties.entry(member.address.clone()).or_default();
        penalty.failures += 1;
        let factor = 2u32.saturating_pow(penalty.failures - 1);
        let backoff = self
            .timing
            .exclusion
            .saturating_mul(factor)
            .min(Duration::from_secs(3600));
        penalty.excluded_until = Some(now + backoff);
        self.report.exclusions.push(records::Exclusion {
            worker: member.name.clone(),
            address: member.address.clone(),
            failures: penalty.failures,
            seconds: backoff.as_secs_f64(),
        });
    }

    /// Whether the worker at `address` sits out a back-off at `now`.
    pub(super) fn excluded(&self, address: &str, now: Instant) -> bool {
        self.penalties
            .get(address)
            .and_then(|p| p.excluded_until)
            .is_some_and(|until| now < until)
    }

    /// Adds a report's skipped frames to the job's count; past `max_skipped_frames` the job
    /// stops, naming the datasets and examples.
    pub(super) fn count_skipped(&mut self, worker: u64, report: &StepReport) {
        if report.skipped_frames == 0 {
            return;
        }
        self.skipped
            .insert((report.generation, worker), report.skipped_frames);
        for example in &report.skipped_examples {
            if !self.report.skipped_examples.contains(example) {
                self.report.skipped_examples.push(example.clone());
            }
        }
        let excess = self
            .report
            .skipped_examples
            .len()
            .saturating_sub(SKIPPED_EXAMPLES);
        self.report.skipped_examples.drain(..excess);
        self.report.skipped_frames = self.skipped.values().sum();
        let limit = self.plan.config.max_skipped_frames;
        if self.report.skipped_frames > limit && self.durable.failure.is_none() {
            self.fail(format!(
                "{} frames could not be read or decoded (max_skipped_frames: {limit}); examples: {}",
                self.report.skipped_frames,
                self.report.skipped_examples.join("; ")
            ));
        }
    }

    /// Stops the job: no group forms again, workers are told to finish, and the reason is kept
    /// in `job.json` and the report.
    pub fn fail(&mut self, reason: String) {
        tracing::error!(%reason, "the job stops");
        self.durable.failure = Some(reason);
        self.durable.phase = Phase::Finished;
        self.group = None;
    }

    /// Why the job stopped short, if it did.
    pub fn failure(&self) -> Option<&str> {
        self.durable.failure.as_deref()
    }
}

/// The ranks whose checksum differs from the one most ranks share; empty when no checksum is
/// held by more than half of them (two replicas that disagree: either may be wrong).
pub(super) fn odd_ranks(checksums: &BTreeMap<u32, u32>) -> Vec<u32> {
    let mut counts: BTreeMap<u32, usize> = BTreeMap::new();
    for checksum in checksums.values() {
        *counts.entry(*checksum).or_default() += 1;
    }
    let majority = counts
        .iter()
        .find(|(_, count)| 2 * **count > checksums.len())
        .map(|(&checksum, _)| checksum);
    match majority {
        Some(majority) => checksums
            .iter()
            .filter(|(_, checksum)| **checksum != majority)
            .map(|(&rank, _)| rank)
            .collect(),
        None => Vec::new(),
    }
}
