//! The `--dry-run` description of a plan: what the job will train, how each stage's batch
//! splits over the expected ranks, how the first epoch's sequences shard, and where the
//! checkpoints and the evaluation report go, so an operator can check a file before a
//! cluster is booked.

use std::fmt::Write as _;

use data::spec::{rank_slice, shard_ids, steps_per_epoch};
use settings::Phase;
use settings::data::{DataSource, StoredDataset};

use super::{Plan, StagePlan};

/// Sequence ids shown per rank before the list is cut with `...`.
const SHARD_PREVIEW: usize = 4;

// Writing to a `String` cannot fail, so the `fmt::Result` of each `writeln!` is dropped.
impl Plan {
    /// Human-readable plan for `--dry-run`: ranks, shards of the first epoch, steps.
    pub fn describe(&self) -> String {
        let mut out = String::new();
        self.describe_job(&mut out);
        for stage in &self.stages {
            self.describe_stage(&mut out, stage);
        }
        match &self.stages[0].data.source {
            DataSource::Generated {
                scenes,
                trajectories,
                frames,
            } => {
                let _ = writeln!(
                    out,
                    "data: generated, {scenes} scenes x {trajectories} trajectories x {frames} frames, drawn by global sample index (not sharded)"
                );
            }
            DataSource::Stored(datasets) => self.describe_stored(&mut out, datasets),
        }
        self.describe_outputs(&mut out);
        out
    }

    /// The ranks the plan is laid out for: the workers the job waits for.
    fn world(&self) -> usize {
        self.config.workers.expected.0 as usize
    }

    /// Name, seed, address, model dimensions and group size.
    fn describe_job(&self, out: &mut String) {
        let config = &self.config;
        let _ = writeln!(out, "job: {}", config.job.0);
        let _ = writeln!(out, "seed: {}", config.seed);
        let _ = writeln!(out, "listen: {}", config.listen.0);
        let _ = writeln!(
            out,
            "model: {:?} image_size={} width={} heads={} pose_layers={} render_layers={}",
            config.model.preset,
            self.model.image_size,
            self.model.width,
            self.model.num_heads,
            self.model.pose_layers,
            self.model.render_layers
        );
        let _ = writeln!(
            out,
            "workers: expected={} minimum={} device={:?}",
            self.world(),
            config.workers.minimum.0,
            config.workers.device
        );
    }

    /// One stage's length, batch, schedule and LPIPS weight, and each rank's share of a step.
    fn describe_stage(&self, out: &mut String, stage: &StagePlan) {
        if !self.trains(stage.phase) {
            let _ = writeln!(out, "{}: not trained (stop_after: stage1)", stage.phase);
            return;
        }
        let train = &stage.train;
        let _ = writeln!(
            out,
            "{}: steps={} global_batch={} micro_batch={} lr {}→{}→{} warmup={} lpips_weight={} frames_per_sample={}",
            stage.phase,
            stage.steps,
            train.global_batch,
            train.micro_batch,
            train.schedule.initial_lr,
            train.schedule.peak_lr,
            train.schedule.final_lr,
            train.schedule.warmup_steps,
            train.objective.lpips_weight(),
            stage.data.sampler.frames,
        );
        let world = self.world();
        for rank in 0..world {
            let (first, count) = rank_slice(train.global_batch, world, rank);
            let _ = writeln!(
                out,
                "  rank {rank}: samples {first}..{} of each step ({} micro-batches)",
                first + count as u64,
                count.div_ceil(train.micro_batch.max(1))
            );
        }
    }

    /// Each stored dataset's train sequences and frames, the epoch length, and the first
    /// sequences of each rank's shard of epoch 0.
    fn describe_stored(&self, out: &mut String, datasets: &[StoredDataset]) {
        for (dataset, (_, _, manifest)) in datasets.iter().zip(&self.manifests) {
            let _ = writeln!(
                out,
                "data: {} at {}: {} train sequences, {} frames",
                dataset.kind.name(),
                dataset.uri,
                manifest.sequences.len(),
                manifest.frame_counts().iter().sum::<usize>()
            );
        }
        let sequences: usize = self
            .manifests
            .iter()
            .map(|(_, _, m)| m.sequences.len())
            .sum();
        let epoch_steps = steps_per_epoch(sequences, self.stages[0].train.global_batch);
        let _ = writeln!(out, "epoch: {epoch_steps} steps; shards of epoch 0:");
        let world = self.world();
        for rank in 0..world {
            let ids = shard_ids(&self.manifests, world, rank, self.config.seed, 0);
            let preview: Vec<&str> = ids.iter().take(SHARD_PREVIEW).map(String::as_str).collect();
            let _ = writeln!(
                out,
                "  rank {rank}: {} sequences ({}{})",
                ids.len(),
                preview.join(", "),
                if ids.len() > SHARD_PREVIEW {
                    ", ..."
                } else {
                    ""
                }
            );
        }
    }

    /// Where checkpoints go and how often, and whether (and on what) stage 3 evaluates.
    fn describe_outputs(&self, out: &mut String) {
        let config = &self.config;
        let _ = writeln!(
            out,
            "checkpoints: {} every {} steps",
            config.checkpoint.uri.0, config.checkpoint.every.0
        );
        match &config.evaluate {
            Some(spec) => {
                let _ = writeln!(
                    out,
                    "stage 3: one worker evaluates the final weights of {} ({} scenes x {} trajectories, {} TPS pairs, probe {} steps); report under {}/evaluation/",
                    if self.trains(Phase::Stage2) {
                        "both stages"
                    } else {
                        "stage 1"
                    },
                    spec.scenes,
                    spec.trajectories,
                    spec.tps_pairs,
                    spec.probe.steps,
                    config.checkpoint.uri.0.trim_end_matches('/')
                );
            }
            None => {
                let _ = writeln!(out, "no evaluation stage (add `evaluate: {{}}` for one)");
            }
        }
    }
}
