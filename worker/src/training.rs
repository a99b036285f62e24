//! One rank's part of a training generation: build or resume the trainer, then per step
//! gradients of the rank's slice -> ring all-reduce -> apply -> report, and (rank 0) the
//! commits, uploaded in the background while the next steps train.

use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::{Context, anyhow, bail};
use data::prefetch::{Prefetched, Schedule};
use data::spec::{RankSource, rank_slice};
use proto::convert::{ConvertError, device_from_wire, phase_from_wire};
use proto::v1::{Activity, LossTerms, StepReport, TrainAssignment};
use settings::XFactorConfig;
use settings::data::DataSpec;
use settings::train::TrainConfig;
use tokio::runtime::Runtime;
use trainer_core::XFactor;
use trainer_core::flat::{flatten_gradients, parameter_checksum, unflatten_gradients};
use trainer_core::lpips::Lpips;
use trainer_core::trainer::Trainer;

use crate::checkpoints::{self, CommitRequest, InFlightCommit};
use crate::collective::{Ring, RingKeys};
use crate::daemon::{Ending, Group};
use crate::session::Client;
use crate::{device, metrics};

/// Trains the assigned stage from its resume point to its end as one rank of the group.
pub fn train_generation(
    runtime: &Runtime,
    client: &mut Client,
    group: &Group<'_>,
    generation: u64,
    assignment: &TrainAssignment,
) -> anyhow::Result<Ending> {
    let Group {
        options,
        link,
        mailbox,
        progress,
        shutdown,
    } = *group;
    let rank = assignment.rank as usize;
    let world = assignment.world_size as usize;
    let phase = phase_from_wire(assignment.phase, "train.phase")?;
    let model_config = XFactorConfig::from(
        assignment
            .model
            .as_ref()
            .ok_or(ConvertError::Missing("train.model"))?,
    );
    let mut train = TrainConfig::try_from(
        assignment
            .train
            .as_ref()
            .ok_or(ConvertError::Missing("train.train"))?,
    )?;
    let data = DataSpec::try_from(
        assignment
            .data
            .as_ref()
            .ok_or(ConvertError::Missing("train.data"))?,
    )?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    train.shards = options
        .threads
        .or((train.shards > 0).then_some(train.shards))
        .unwrap_or(cores);
    let backend = device::backend(match options.device {
        Some(device) => device,
        None => device_from_wire(assignment.device, "train.device")?,
    });
    let device = backend.device().autodiff();
    let scratch = options
        .scratch
        .join(format!("worker-{}", progress.worker_id()));
    let lpips = if assignment.lpips_weights.is_empty() {
        None
    } else {
        Some(
            Lpips::from_file(Path::new(&assignment.lpips_weights), &device)
                .with_context(|| format!("LPIPS weights {}", assignment.lpips_weights))?,
        )
    };
    let mut trainer = if !assignment.resume_from.is_empty() {
        let dir = scratch.join("resume");
        let _ = std::fs::remove_dir_all(&dir);
        runtime.block_on(checkpoints::download(&assignment.resume_from, &dir))?;
        Trainer::resume(train.clone(), &dir, lpips, &device)
            .with_context(|| format!("resuming from {}", assignment.resume_from))?
    } else if !assignment.init_weights_from.is_empty() {
        let dir = scratch.join("init");
        let _ = std::fs::remove_dir_all(&dir);
        runtime.block_on(checkpoints::download(&assignment.init_weights_from, &dir))?;
        let trainer = Trainer::from_weights(train.clone(), &dir, lpips, &device)
            .with_context(|| format!("initial weights from {}", assignment.init_weights_from))?;
        anyhow::ensure!(
            *trainer.model_config() == model_config,
            "initial weights at {} are a different model ({:?}) from the job's ({:?})",
            assignment.init_weights_from,
            trainer.model_config(),
            model_config
        );
        trainer
    } else {
        let model = XFactor::new(&model_config, train.seed, &device)?;
        Trainer::new(train.clone(), model_config, model, lpips, &device)?
    };
    tracing::info!(
        backend = backend.name(),
        threads = train.shards,
        start_step = trainer.step(),
        total_steps = assignment.total_steps,
        "training"
    );
    let (first, count) = rank_slice(train.global_batch, world, rank);
    let rank_source = runtime.block_on(RankSource::open(&data, world, rank))?;
    let shard = rank_source.shard_at(trainer.step());
    if !shard.is_empty() {
        tracing::info!(sequences = shard.len(), "data shard of this epoch");
    }
    let schedule = Schedule {
        start_step: trainer.step(),
        first_sample: first,
        global_batch: count,
        micro_batch: train.micro_batch,
    };
    let micro_batches_per_step = count.div_ceil(train.micro_batch.max(1));
    let source = Prefetched::new(rank_source, schedule, 2 * micro_batches_per_step, 1);
    let timed = metrics::Timed::new(&source);
    let mut ring = runtime.block_on(Ring::connect(
        mailbox,
        rank,
        &assignment.peers,
        generation,
        &RingKeys {
            own: assignment.ring_secret.clone(),
            left: assignment.left_ring_secret.clone(),
        },
        link,
        progress.cancel.subscribe(),
    ))?;
    let registry = &progress.metrics;
    registry.set(&metrics::STAGE, &[], f64::from(phase.number()));
    registry.set(&metrics::RANK, &[], f64::from(assignment.rank));
    registry.set(&metrics::GENERATION, &[], generation as f64);
    // Rank 0's last checkpoint while it uploads; aborted if this generation ends in error.
    let mut in_flight: Option<InFlightCommit> = None;
    while trainer.step() < assignment.total_steps {
        let step = trainer.step();
        let _span = tracing::info_span!("step", step).entered();
        if shutdown.is_cancelled() {
            tracing::info!(step, "stopping before this step; nothing of it was applied");
            return Ok(Ending::Stopping);
        }
        if *progress.cancel.borrow() {
            bail!("the coordinator abandoned generation {generation}");
        }
        let started = Instant::now();
        progress.doing(Activity::Computing);
        let (slice_loss, grads) = trainer
            .slice_gradients(&timed, first, count)
            .with_context(|| format!("gradients of step {step}"))?;
        let mut flat = flatten_gradients(trainer.model(), &grads);
        flat.extend([slice_loss.total, slice_loss.l1, slice_loss.lpips]);
        progress.doing(Activity::Allreduce);
        let (returned, mut flat, reduce) = ring
            .all_reduce_on(runtime, flat)
            .with_context(|| format!("all-reduce of step {step}"))?;
        ring = returned;
        let lpips = flat.pop().unwrap_or(f32::NAN);
        let l1 = flat.pop().unwrap_or(f32::NAN);
        let loss = flat.pop().unwrap_or(f32::NAN);
        if options
            .drill_diverge_from_step
            .is_some_and(|from| step >= from)
            && let Some(first) = flat.first_mut()
        {
            *first += 1.0;
            tracing::warn!(
                step,
                "fault drill: this replica's reduced gradients perturbed"
            );
        }
        let grads = unflatten_gradients(trainer.model(), &flat)?;
        let outcome = trainer.apply_gradients(&grads, loss);
        let done = trainer.step();
        progress.step.store(done, Ordering::SeqCst);
        progress.doing(Activity::Idle);
        let checksum_due =
            done.is_multiple_of(assignment.checksum_every.max(1)) || done == assignment.total_steps;
        let checksum = checksum_due.then(|| parameter_checksum(trainer.model()));
        let elapsed = started.elapsed().as_secs_f64();
        tracing::info!(
            loss = outcome.loss,
            lr = outcome.learning_rate,
            grad_norm = outcome.grad_norm,
            step_s = elapsed,
            allreduce_s = reduce.seconds,
            "step done"
        );
        let skipped_frames = source.inner().skipped_frames();
        registry.set(&metrics::STEP, &[], done as f64);
        registry.set(&metrics::LOSS, &[], f64::from(outcome.loss));
        registry.set(&metrics::LEARNING_RATE, &[], outcome.learning_rate);
        registry.set(&metrics::GRAD_NORM, &[], outcome.grad_norm);
        registry.set(&metrics::STEP_SECONDS, &[], elapsed);
        registry.set(
            &metrics::SAMPLES_PER_SECOND,
            &[],
            count as f64 / elapsed.max(1e-9),
        );
        registry.set(&metrics::ALLREDUCE_SECONDS, &[], reduce.seconds);
        registry.observe(&metrics::STEP_DURATION, &[], elapsed);
        registry.observe(&metrics::ALLREDUCE_DURATION, &[], reduce.seconds);
        let data_wait_s = timed.take_seconds();
        registry.observe(&metrics::DATA_WAIT, &[], data_wait_s);
        if reduce.seconds > 0.0 {
            let bytes = (flat.len() * std::mem::size_of::<f32>()) as f64;
            registry.set(&metrics::ALLREDUCE_BANDWIDTH, &[], bytes / reduce.seconds);
        }
        registry.set(&metrics::LOADER_QUEUE, &[], source.queued() as f64);
        registry.raise_to(&metrics::SKIPPED_FRAMES, &[], skipped_frames as f64);
        let report = StepReport {
            worker_id: progress.worker_id(),
            session: progress.session(),
            generation,
            phase: assignment.phase,
            step,
            loss: Some(LossTerms {
                total: outcome.loss,
                learning_rate: outcome.learning_rate,
                grad_norm: outcome.grad_norm,
                applied: outcome.applied,
                l1,
                lpips,
            }),
            parameter_checksum: checksum.unwrap_or(0),
            checksum_computed: checksum.is_some(),
            samples_per_s: count as f64 / elapsed.max(1e-9),
            allreduce_s: reduce.seconds,
            skipped_frames,
            step_s: elapsed,
            data_wait_s,
            skipped_examples: if skipped_frames > 0 {
                source.inner().skipped_examples()
            } else {
                Vec::new()
            },
        };
        let ack = runtime
            .block_on(client.report_step(report))
            .map_err(|s| anyhow!("step report refused: {}", s.message()))?
            .into_inner();
        if !ack.generation_current {
            bail!("generation {generation} is no longer current");
        }
        if let Some(finished) = in_flight.take_if(|commit| commit.is_finished()) {
            finished.wait(runtime)?;
        }
        if ack.suspend && rank != 0 {
            return Ok(Ending::Suspended);
        }
        let commit_due = done.is_multiple_of(assignment.checkpoint_every.max(1))
            || done == assignment.total_steps
            || ack.suspend;
        if rank == 0 && commit_due {
            let _span = tracing::info_span!("checkpoint", step = done).entered();
            let last = done == assignment.total_steps || ack.suspend;
            if let Some(previous) = in_flight.take() {
                if !last {
                    tracing::warn!(
                        previous = previous.step,
                        location = %previous.location,
                        "checkpoint of this step skipped: the previous one is still uploading"
                    );
                    in_flight = Some(previous);
                    continue;
                }
                progress.doing(Activity::Committing);
                previous.wait(runtime)?;
            }
            let dir = scratch.join("save");
            let _ = std::fs::remove_dir_all(&dir);
            trainer.save_checkpoint(&dir)?;
            let request = CommitRequest {
                dir: &dir,
                location: format!(
                    "{}/step-{done:08}-g{generation}",
                    assignment.checkpoint_prefix
                ),
                phase,
                step: done,
                generation,
            };
            let commit = InFlightCommit::start(runtime, client, progress, request)?;
            if last {
                progress.doing(Activity::Committing);
                commit.wait(runtime)?;
                if ack.suspend {
                    return Ok(Ending::Suspended);
                }
            } else {
                in_flight = Some(commit);
            }
        }
    }
    Ok(Ending::Done)
}
