//! One rank's part of a training generation, from its prepared state to the stage's end: per
//! step, a stop check, the step itself (`step`), its books sent to the coordinator
//! (`accounting`), and on rank 0 the commits the schedule asks for (`commits`), uploaded in the
//! background while the next steps train.

use std::time::Instant;

use anyhow::{Context, bail};
use proto::v1::{Activity, StepAck};
use settings::work::TrainWork;
use tokio::runtime::Runtime;
use trainer_core::backend::MemoryFigures;

use crate::accounting::{Reporter, StepAccount};
use crate::checkpoints;
use crate::commits::{CommitDecision, CommitRequest, CommitSchedule, InFlightCommit};
use crate::context::{Ending, GenerationEnded, WorkerContext};
use crate::datapath::{ChecksumPlan, DataPath};
use crate::generation::{self, Prepared};
use crate::metrics::{self, Timed};
use crate::session::Client;

/// Trains the assigned stage from its resume point to its end as one rank of the group.
pub fn train_generation(
    runtime: &Runtime,
    client: &mut Client,
    context: &WorkerContext<'_>,
    generation: u64,
    work: &TrainWork,
) -> anyhow::Result<Ending> {
    let Prepared {
        mut replicas,
        source,
        ring,
        samples_per_step,
    } = generation::prepare(runtime, context, generation, work)?;
    let registry = &context.progress.metrics;
    registry.set(&metrics::STAGE, &[], f64::from(work.stage.number()));
    registry.set(&metrics::RANK, &[], work.rank as f64);
    registry.set(&metrics::GENERATION, &[], generation as f64);
    let timed = Timed::new(&source);
    let checksums = ChecksumPlan {
        every: work.checksum_every,
        commit_every: work.checkpoint_every,
        total_steps: work.total_steps,
    };
    let mut path = DataPath::new(ring, checksums, context.options.drill_diverge_from_step);
    let mut run = StageRun {
        runtime,
        client,
        context,
        work,
        generation,
        in_flight: None,
    };
    loop {
        let Some(replica) = replicas.first() else {
            bail!("no replica to train");
        };
        let step = replica.trainer.step();
        if step >= work.total_steps {
            return Ok(Ending::Done);
        }
        let _span = tracing::info_span!("step", step).entered();
        if let Some(ending) = run.stop_before(step)? {
            return Ok(ending);
        }
        let started = Instant::now();
        let figures = path.step(runtime, &mut replicas, &timed, context.progress)?;
        let done = figures.metrics.step + 1;
        context
            .progress
            .step
            .store(done, std::sync::atomic::Ordering::SeqCst);
        context.progress.doing(Activity::Idle);
        metrics::record_device_memory(registry, &MemoryFigures::read(replica_device(&replicas)?));
        let account = StepAccount {
            figures,
            samples: samples_per_step,
            seconds: started.elapsed().as_secs_f64(),
            data_wait_s: timed.take_seconds(),
            skipped_frames: source.inner().skipped_frames(),
            skipped_examples: source.inner().skipped_examples(),
            loader_queue: source.queued(),
        };
        let ack = run.report(&account)?;
        if ack.checksum_next {
            path.checksum_next_step();
        }
        if let Some(ending) =
            run.after_ack(&ack, done, |dir| replicas[0].trainer.save_checkpoint(dir))?
        {
            return Ok(ending);
        }
    }
}

/// The device of the first replica, whose memory the metrics show.
fn replica_device(replicas: &[crate::datapath::Replica]) -> anyhow::Result<&trainer_core::Device> {
    let replica = replicas.first().context("no replica to train")?;
    Ok(replica.trainer.device())
}

/// The state of a stage's step loop beyond the replicas: who to tell, and the commit in
/// flight (rank 0's last checkpoint while it uploads; aborted if the generation ends in error).
struct StageRun<'a> {
    runtime: &'a Runtime,
    client: &'a mut Client,
    context: &'a WorkerContext<'a>,
    work: &'a TrainWork,
    generation: u64,
    in_flight: Option<InFlightCommit>,
}

impl StageRun<'_> {
    /// Whether to stop before `step`: on SIGTERM (cleanly, nothing of it applied), or with an
    /// error when the coordinator abandoned the generation.
    fn stop_before(&self, step: u64) -> anyhow::Result<Option<Ending>> {
        if self.context.shutdown.is_cancelled() {
            tracing::info!(step, "stopping before this step; nothing of it was applied");
            return Ok(Some(Ending::Stopping));
        }
        if self.context.progress.generation_token().is_cancelled() {
            return Err(GenerationEnded {
                generation: self.generation,
            }
            .into());
        }
        Ok(None)
    }

    /// Logs the step, records its metrics and reports it; the coordinator's answer says
    /// whether the generation is still current and whether the job is being suspended.
    fn report(&mut self, account: &StepAccount) -> anyhow::Result<StepAck> {
        let metrics = &account.figures.metrics;
        tracing::info!(
            loss = metrics.loss,
            lr = metrics.learning_rate,
            grad_norm = metrics.grad_norm,
            step_s = account.seconds,
            allreduce_s = account.figures.allreduce_s,
            compute_s = account.figures.phases.compute_s,
            copy_s = account.figures.phases.copy_s,
            apply_s = account.figures.phases.apply_s,
            checksum_s = account.figures.phases.checksum_s,
            "step done"
        );
        let progress = self.context.progress;
        account.record(&progress.metrics);
        let reporter = Reporter {
            worker_id: progress.worker_id(),
            session: progress.session(),
            generation: self.generation,
            stage: self.work.stage,
            device: progress.device.get(),
        };
        let ack = self
            .runtime
            .block_on(self.client.report_step(account.report(&reporter)))
            .map_err(|status| anyhow::anyhow!("step report refused: {}", status.message()))?
            .into_inner();
        if !ack.generation_current {
            return Err(GenerationEnded {
                generation: self.generation,
            }
            .into());
        }
        Ok(ack)
    }

    /// After step `done` was acknowledged: surfaces a finished upload's error, ends a
    /// suspended non-zero rank, and on rank 0 commits what the schedule asks for (`save`
    /// writes the checkpoint directory).
    fn after_ack(
        &mut self,
        ack: &StepAck,
        done: u64,
        save: impl FnOnce(&std::path::Path) -> Result<(), trainer_core::trainer::TrainError>,
    ) -> anyhow::Result<Option<Ending>> {
        if let Some(finished) = self.in_flight.take_if(|commit| commit.is_finished()) {
            finished.wait(self.runtime)?;
        }
        let schedule = CommitSchedule {
            every: self.work.checkpoint_every,
            total_steps: self.work.total_steps,
        };
        let decision = schedule.decide(self.work.rank, done, ack.suspend, self.in_flight.is_some());
        match decision {
            CommitDecision::Nothing if ack.suspend => Ok(Some(Ending::Suspended)),
            CommitDecision::Nothing => Ok(None),
            CommitDecision::SkipWhilePreviousUploads => {
                if let Some(previous) = &self.in_flight {
                    tracing::warn!(
                        previous = previous.step,
                        location = %previous.location,
                        "checkpoint of this step skipped: the previous one is still uploading"
                    );
                }
                Ok(None)
            }
            CommitDecision::Commit {
                wait_previous,
                wait_this,
            } => {
                let _span = tracing::info_span!("checkpoint", step = done).entered();
                if wait_previous && let Some(previous) = self.in_flight.take() {
                    self.context.progress.doing(Activity::Committing);
                    previous.wait(self.runtime)?;
                }
                self.commit(done, wait_this, save)?;
                Ok(ack.suspend.then_some(Ending::Suspended))
            }
        }
    }

    /// Saves the state after step `done` and starts its commit; waits for it when `wait`.
    fn commit(
        &mut self,
        done: u64,
        wait: bool,
        save: impl FnOnce(&std::path::Path) -> Result<(), trainer_core::trainer::TrainError>,
    ) -> anyhow::Result<()> {
        let dir = self.context.scratch().join("save");
        checkpoints::clear(&dir)?;
        save(&dir)?;
        let request = CommitRequest {
            dir: &dir,
            location: format!(
                "{}/step-{done:08}-g{}",
                self.work.checkpoint_prefix, self.generation
            ),
            phase: self.work.stage,
            step: done,
            generation: self.generation,
        };
        let progress = self.context.progress;
        let commit = InFlightCommit::start(self.runtime, self.client, progress, request)?;
        if wait {
            progress.doing(Activity::Committing);
            commit.wait(self.runtime)?;
        } else {
            self.in_flight = Some(commit);
        }
        Ok(())
    }
}
