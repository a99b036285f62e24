//! The cluster YAML a local job writes: the same file an operator would, sized by
//! [`LocalJob`]'s fields.

use std::fmt::Write as _;

use settings::work::WireFormat;

use super::LocalJob;

impl LocalJob {
    /// The cluster YAML of this job, its data at `data`.
    pub(super) fn yaml(&self, data: &str) -> String {
        let mut yaml = String::new();
        let _ = writeln!(yaml, "job: local-demo");
        let _ = writeln!(yaml, "seed: {}", self.seed);
        let _ = writeln!(yaml, "listen: {}:{}", self.listen_host, self.port);
        let _ = writeln!(yaml, "auth:\n  token: {}", self.token());
        if let Some(viewing) = &self.viewing_token {
            let _ = writeln!(yaml, "viewing:\n  token: {viewing}");
        }
        let _ = writeln!(
            yaml,
            "model:\n  preset: {}\n  image_size: {}",
            self.preset, self.image_size
        );
        if let Some(pose_dim) = self.pose_dim {
            let _ = writeln!(yaml, "  pose_dim: {pose_dim}");
        }
        if self.in_memory {
            let _ = writeln!(
                yaml,
                "data:\n  generated:\n    scenes: {}\n    trajectories: {}\n    frames: {}",
                self.scenes, self.trajectories, self.frames
            );
        } else {
            let window = self.frames as u64;
            let stage2_begin = self
                .stage2_views_keeping_render
                .map_or(6, |views| views.max(3));
            let _ = writeln!(
                yaml,
                "data:\n  datasets:\n    - kind: re10k\n      uri: {data}\n      stage1: {{weight: 1, window_begin: 2, window_end: {window}}}\n      stage2: {{weight: 1, window_begin: {stage2_begin}, window_end: {window}}}"
            );
        }
        for (stage, steps, span, peak_lr) in [
            (
                1,
                self.stage1_steps,
                self.stage1_schedule(),
                self.stage1_peak_lr,
            ),
            (2, self.stage2_steps, self.stage2_steps, 1e-3),
        ] {
            let warmup = (span / 200).clamp(2, 20);
            let _ = writeln!(
                yaml,
                "stage{stage}:\n  steps: {steps}\n  global_batch: {}\n  micro_batch: {}\n  lpips_weight: 0\n  curriculum_steps: {span}\n  schedule: {{initial_lr: 1.0e-4, peak_lr: {}, final_lr: 1.0e-4, warmup_steps: {warmup}, total_steps: {span}}}",
                self.global_batch, self.micro_batch, peak_lr
            );
            let mut objective = Vec::new();
            if let Some(variant) = self
                .objective_variant
                .filter(|v| stage == 1 || !v.stage1_only())
            {
                let name = serde_json::to_string(&variant).unwrap_or_default();
                objective.push(format!("variant: {}", name.trim_matches('"')));
            }
            if let (2, Some(views)) = (stage, self.stage2_views_keeping_render) {
                objective.push(format!("views: {views}, render_from_stage1: true"));
            }
            if !objective.is_empty() {
                let _ = writeln!(yaml, "  objective: {{{}}}", objective.join(", "));
            }
        }
        if self.stage1_only {
            let _ = writeln!(yaml, "stop_after: stage1");
        }
        let _ = writeln!(
            yaml,
            "checkpoint:\n  uri: {}\n  every: {}",
            self.checkpoint_location(),
            self.checkpoint_every
        );
        if self.evaluate {
            self.evaluation
                .write_yaml(self.seed, &self.departures(), &mut yaml);
        }
        self.write_workers_and_tls(&mut yaml);
        yaml
    }

    /// The YAML's `workers:` section, and `tls:` when the job runs it.
    fn write_workers_and_tls(&self, yaml: &mut String) {
        let _ = writeln!(
            yaml,
            "workers:\n  expected: {}\n  minimum: {}\n  device: {}\n  threads: 1\n  heartbeat_interval_s: 0.25\n  heartbeat_timeout_s: 3\n  regroup_grace_s: 1\n  quorum_timeout_s: 120\n  stall_timeout_s: {}",
            self.workers, self.minimum, self.device, self.stall_timeout_s
        );
        if self.allreduce_wire != WireFormat::F32 {
            let _ = writeln!(yaml, "  allreduce_wire: {}", self.allreduce_wire.name());
        }
        if let Some(every) = self.checksum_every {
            let _ = writeln!(yaml, "  checksum_every: {every}");
        }
        if let Some(tls) = &self.tls {
            let _ = writeln!(
                yaml,
                "tls:\n  cert: {}\n  key: {}",
                tls.join("server.pem").display(),
                tls.join("server.key").display()
            );
        }
    }
}
