//! Preparing one training assignment: the device, the trainer (resumed from the last commit,
//! started from another checkpoint's weights, or fresh), this rank's data stream, and its
//! place in the ring. What it returns is everything the step loop needs.

use std::path::{Path, PathBuf};

use anyhow::Context;
use data::prefetch::{Prefetched, Schedule};
use data::spec::{RankSource, rank_slice};
use settings::work::{TrainStart, TrainWork};
use tokio::runtime::Runtime;
use trainer_core::Device;
use trainer_core::XFactor;
use trainer_core::backend::{BackendDevices, default_shards};
use trainer_core::lpips::Lpips;
use trainer_core::trainer::Trainer;

use crate::checkpoints;
use crate::collective::{Ring, RingKeys};
use crate::context::WorkerContext;
use crate::datapath::Replica;
use crate::device;

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

/// Builds or resumes one trainer per device of this worker, opens the rank's data and joins
/// the ring of `generation`.
pub fn prepare(
    runtime: &Runtime,
    context: &WorkerContext<'_>,
    generation: u64,
    work: &TrainWork,
) -> anyhow::Result<Prepared> {
    let mut train = work.train.clone();
    let choice = context.options.device.unwrap_or(work.device);
    let resolved = device::resolve(choice, &context.progress.metrics)?;
    let backend = resolved.backend;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    train.shards = context
        .options
        .threads
        .or((train.shards > 0).then_some(train.shards))
        .unwrap_or_else(|| default_shards(backend, cores));
    let devices = backend.devices(context.options.devices.as_ref().unwrap_or(&work.devices))?;
    context.progress.device.set(&resolved, devices.len());
    let start = fetch_start(runtime, context, work)?;
    let (first, count) = rank_slice(work.train.global_batch, work.world_size(), work.rank);
    let micro_batch = work.train.micro_batch.max(1);
    let slices = replica_slices(first, count, micro_batch, devices.len());
    let mut replicas = Vec::with_capacity(devices.len());
    for (index, (device, (first, count))) in devices.into_iter().zip(slices).enumerate() {
        let device = if context.options.activation_checkpointing {
            device.autodiff().gradient_checkpointing()
        } else {
            device.autodiff()
        };
        let trainer = build_trainer(work, train.clone(), start.as_ref(), &device)?;
        replicas.push(Replica {
            trainer,
            index,
            first,
            count,
        });
    }
    let start_step = replicas.first().map_or(0, |r| r.trainer.step());
    tracing::info!(
        backend = backend.name(),
        replicas = replicas.len(),
        threads = train.shards,
        start_step,
        total_steps = work.total_steps,
        "training"
    );
    let rank_source =
        runtime.block_on(RankSource::open(&work.data, work.world_size(), work.rank))?;
    let shard = rank_source.shard_at(start_step);
    if !shard.is_empty() {
        tracing::info!(sequences = shard.len(), "data shard of this epoch");
    }
    let schedule = Schedule {
        start_step,
        first_sample: first,
        global_batch: count,
        micro_batch,
    };
    let source = Prefetched::new(rank_source, schedule, 2 * count.div_ceil(micro_batch), 1);
    let ring = runtime.block_on(join_ring(context, generation, work))?;
    Ok(Prepared {
        replicas,
        source,
        ring,
        samples_per_step: count,
    })
}

/// The rank's samples `first .. first + count` cut into one slice per replica along
/// micro-batch boundaries, the first replicas taking one micro-batch more when they do not
/// divide evenly; so the replicas read the prefetched micro-batches in order, and together
/// they compute exactly the rank's share.
pub fn replica_slices(
    first: u64,
    count: usize,
    micro_batch: usize,
    replicas: usize,
) -> Vec<(u64, usize)> {
    let micro_batches = count.div_ceil(micro_batch.max(1));
    let replicas = replicas.max(1);
    let mut slices = Vec::with_capacity(replicas);
    let mut start = 0;
    for replica in 0..replicas {
        let own = micro_batches / replicas + usize::from(replica < micro_batches % replicas);
        let end = (start + own * micro_batch).min(count);
        slices.push((first + start as u64, end - start));
        start = end;
    }
    slices
}

/// The checkpoint the assignment starts from, downloaded once for every replica; `None`
/// for a fresh start from the seed.
fn fetch_start(
    runtime: &Runtime,
    context: &WorkerContext<'_>,
    work: &TrainWork,
) -> anyhow::Result<Option<PathBuf>> {
    let (location, folder) = match &work.start {
        TrainStart::Resume(location) => (location, "resume"),
        TrainStart::InitWeights(location) => (location, "init"),
        TrainStart::Fresh => return Ok(None),
    };
    let dir = context.scratch().join(folder);
    checkpoints::clear(&dir)?;
    runtime.block_on(checkpoints::download(location, &dir))?;
    Ok(Some(dir))
}

/// One trainer on `device`, started where `start` says.
fn build_trainer(
    work: &TrainWork,
    train: settings::train::TrainConfig,
    start: Option<&PathBuf>,
    device: &Device,
) -> anyhow::Result<Trainer> {
    let lpips = match &work.lpips_weights {
        Some(weights) => Some(
            Lpips::from_file(Path::new(weights), device)
                .with_context(|| format!("LPIPS weights {weights}"))?,
        ),
        None => None,
    };
    match (&work.start, start) {
        (TrainStart::Resume(location), Some(dir)) => Trainer::resume(train, dir, lpips, device)
            .with_context(|| format!("resuming from {location}")),
        (TrainStart::InitWeights(location), Some(dir)) => {
            let trainer = Trainer::from_weights(train, dir, lpips, device)
                .with_context(|| format!("initial weights from {location}"))?;
            anyhow::ensure!(
                *trainer.model_config() == work.model,
                "initial weights at {location} are a different model ({:?}) from the job's ({:?})",
                trainer.model_config(),
                work.model
            );
            Ok(trainer)
        }
        _ => {
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
    let link = crate::collective::Link {
        lanes: work.lanes,
        ..context.link.clone()
    };
    Ok(Ring::connect(
        context.mailbox,
        work.rank,
        &work.peers,
        generation,
        &keys,
        &link,
        context.progress.generation_token(),
    )
    .await?
    .with_wire(work.wire))
}

#[cfg(test)]
mod tests {
    use super::replica_slices;

    #[test]
    fn replicas_split_the_rank_slice_along_micro_batches() {
        assert_eq!(replica_slices(8, 8, 2, 1), [(8, 8)]);
        assert_eq!(replica_slices(8, 8, 2, 2), [(8, 4), (12, 4)]);
        assert_eq!(replica_slices(0, 10, 2, 3), [(0, 4), (4, 4), (8, 2)]);
        assert_eq!(replica_slices(0, 5, 2, 2), [(0, 4), (4, 1)]);
        assert_eq!(replica_slices(0, 2, 2, 2), [(0, 2), (2, 0)]);
    }
}
