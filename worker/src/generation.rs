//! Preparing one training assignment: the device, the trainer (resumed from the last commit,
//! started from another checkpoint's weights, or fresh), this rank's data stream, and its
//! place in the ring. What it returns is everything the step loop needs.

use std::path::Path;

use anyhow::Context;
use data::prefetch::{Prefetched, Schedule};
use data::spec::{RankSource, rank_slice};
use settings::work::{TrainStart, TrainWork};
use tokio::runtime::Runtime;
use trainer_core::XFactor;
use trainer_core::backend::BackendChoice;
use trainer_core::lpips::Lpips;
use trainer_core::trainer::Trainer;

use crate::checkpoints;
use crate::collective::{Ring, RingKeys};
use crate::context::WorkerContext;
use crate::device;
use crate::step::Replica;

/// A prepared assignment: the replicas of this worker, the data they read and the ring.
pub struct Prepared {
    /// One replica per device of this worker, each with its slice of the rank's samples.
    pub replicas: Vec<Replica>,
    /// This rank's samples, prefetched.
    pub source: Prefetched<RankSource>,
    /// This rank's place in the ring of the generation.
    pub ring: Ring,
    /// Samples this rank trains per step.
    pub samples_per_step: usize,
}

/// Builds or resumes the trainer, opens the rank's data and joins the ring of `generation`.
pub fn prepare(
    runtime: &Runtime,
    context: &WorkerContext<'_>,
    generation: u64,
    work: &TrainWork,
) -> anyhow::Result<Prepared> {
    let mut train = work.train.clone();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    train.shards = context
        .options
        .threads
        .or((train.shards > 0).then_some(train.shards))
        .unwrap_or(cores);
    let backend = device::backend(context.options.device.unwrap_or(work.device));
    let threads = train.shards;
    let trainer = build_trainer(runtime, context, work, train, backend)?;
    tracing::info!(
        backend = backend.name(),
        threads,
        start_step = trainer.step(),
        total_steps = work.total_steps,
        "training"
    );
    let (first, count) = rank_slice(work.train.global_batch, work.world_size(), work.rank);
    let rank_source =
        runtime.block_on(RankSource::open(&work.data, work.world_size(), work.rank))?;
    let shard = rank_source.shard_at(trainer.step());
    if !shard.is_empty() {
        tracing::info!(sequences = shard.len(), "data shard of this epoch");
    }
    let micro_batch = work.train.micro_batch.max(1);
    let schedule = Schedule {
        start_step: trainer.step(),
        first_sample: first,
        global_batch: count,
        micro_batch,
    };
    let source = Prefetched::new(rank_source, schedule, 2 * count.div_ceil(micro_batch), 1);
    let ring = runtime.block_on(join_ring(context, generation, work))?;
    Ok(Prepared {
        replicas: vec![Replica {
            trainer,
            first,
            count,
        }],
        source,
        ring,
        samples_per_step: count,
    })
}

/// The trainer where the assignment says it starts: a commit of this stage to resume, another
/// checkpoint's weights, or the seed.
fn build_trainer(
    runtime: &Runtime,
    context: &WorkerContext<'_>,
    work: &TrainWork,
    train: settings::train::TrainConfig,
    backend: BackendChoice,
) -> anyhow::Result<Trainer> {
    let device = &backend.device().autodiff();
    let lpips = match &work.lpips_weights {
        Some(weights) => Some(
            Lpips::from_file(Path::new(weights), device)
                .with_context(|| format!("LPIPS weights {weights}"))?,
        ),
        None => None,
    };
    let scratch = context.scratch();
    match &work.start {
        TrainStart::Resume(location) => {
            let dir = scratch.join("resume");
            checkpoints::clear(&dir)?;
            runtime.block_on(checkpoints::download(location, &dir))?;
            Trainer::resume(train, &dir, lpips, device)
                .with_context(|| format!("resuming from {location}"))
        }
        TrainStart::InitWeights(location) => {
            let dir = scratch.join("init");
            checkpoints::clear(&dir)?;
            runtime.block_on(checkpoints::download(location, &dir))?;
            let trainer = Trainer::from_weights(train, &dir, lpips, device)
                .with_context(|| format!("initial weights from {location}"))?;
            anyhow::ensure!(
                *trainer.model_config() == work.model,
                "initial weights at {location} are a different model ({:?}) from the job's ({:?})",
                trainer.model_config(),
                work.model
            );
            Ok(trainer)
        }
        TrainStart::Fresh => {
            let model = XFactor::new(&work.model, train.seed, device)?;
            Ok(Trainer::new(
                train,
                work.model.clone(),
                model,
                lpips,
                device,
            )?)
        }
    }
}

/// Joins the ring of `generation` with the assignment's secrets (none in a group of one).
async fn join_ring(
    context: &WorkerContext<'_>,
    generation: u64,
    work: &TrainWork,
) -> anyhow::Result<Ring> {
    let keys = work
        .ring
        .as_ref()
        .map(|ring| RingKeys {
            own: ring.own.clone(),
            left: ring.left.clone(),
        })
        .unwrap_or_default();
    Ok(Ring::connect(
        context.mailbox,
        work.rank,
        &work.peers,
        generation,
        &keys,
        context.link,
        context.progress.cancel.subscribe(),
    )
    .await?)
}
