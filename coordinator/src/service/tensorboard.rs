//! TensorBoard event files under the checkpoint URI, one run directory per phase:
//! `tensorboard/stage1/`, `tensorboard/stage2/`, `tensorboard/evaluate/`, so
//! `tensorboard --logdir <checkpoint.uri>/tensorboard` shows the stages side by side.
//!
//! Per step: the loss and its terms, learning rate, gradient norm, skipped updates, step,
//! all-reduce and data-wait times, the communication share, pairs per second and the world
//! size. Per stage: the resolved configuration as text. Per evaluation: every number of its
//! `report.json` (trained and untrained) as scalars and its figures as images.
//!
//! Object stores cannot append, so each run's newest event file is rewritten as it grows and
//! a new one is started every [`SEGMENT_EVENTS`] events; file names carry this coordinator's
//! start time, so a restarted coordinator's files sort after its predecessor's.

use std::collections::HashMap;
use std::time::{SystemTime, UNIX_EPOCH};

use data::store::{DataRoot, StoreError};
use serde_json::Value;
use settings::Phase;
use telemetry::tensorboard::{EventSegment, event_file_name};

use crate::config::AuthConfig;
use crate::job::StepRecord;
use crate::plan::Plan;

/// Events per file: a rewrite stays below about 300 KB of scalars.
pub const SEGMENT_EVENTS: usize = 4000;

/// Where the runs go under the checkpoint URI.
pub const PREFIX: &str = "tensorboard";

/// The job's configuration as TensorBoard shows it: the cluster YAML as resolved (an inline
/// token replaced) and the plan `--dry-run` prints.
pub fn resolved_config(plan: &Plan) -> String {
    let mut config = plan.config.clone();
    if let AuthConfig::Token(token) = &mut config.auth {
        token.0 = "<redacted>".into();
    }
    let yaml = serde_norway::to_string(&config)
        .unwrap_or_else(|error| format!("(the configuration could not be written: {error})"));
    format!(
        "Cluster YAML, resolved:\n\n```yaml\n{yaml}```\n\nPlan:\n\n```\n{}```\n",
        plan.describe()
    )
}

/// Seconds since the epoch.
fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// One run directory's file being filled.
struct Run {
    sequence: u64,
    segment: EventSegment,
    unwritten: bool,
    /// Updates skipped for an exploding gradient so far in this run.
    skipped: u64,
}

/// The event files of every phase of the job.
pub struct TensorBoard {
    root: DataRoot,
    started: u64,
    runs: HashMap<Phase, Run>,
}

impl TensorBoard {
    /// Event files under `root` (the checkpoint URI), named after the current time.
    pub fn new(root: DataRoot) -> Self {
        Self {
            root,
            started: now() as u64,
            runs: HashMap::new(),
        }
    }

    fn run(&mut self, phase: Phase) -> &mut Run {
        self.runs.entry(phase).or_insert_with(|| Run {
            sequence: 0,
            segment: EventSegment::new(now()),
            unwritten: true,
            skipped: 0,
        })
    }

    /// The resolved job configuration, as text in `phase`'s run at step 0.
    pub fn record_config(&mut self, phase: Phase, text: &str) {
        let run = self.run(phase);
        run.segment.text(now(), 0, "config", text);
        run.unwritten = true;
    }

    /// One scalar of each measure per finished step.
    pub fn record_steps(&mut self, records: &[StepRecord]) {
        let wall_time = now();
        for record in records {
            let run = self.run(record.phase);
            if !record.applied {
                run.skipped += 1;
            }
            let communication_share = if record.step_s > 0.0 {
                record.allreduce_s / record.step_s
            } else {
                0.0
            };
            let mut scalars = vec![
                ("loss/total", f64::from(record.loss)),
                ("loss/l1", f64::from(record.l1)),
                ("optimizer/learning_rate", record.learning_rate),
                ("optimizer/grad_norm", record.grad_norm),
                ("optimizer/skipped_steps", run.skipped as f64),
                ("time/step_s", record.step_s),
                ("time/allreduce_s", record.allreduce_s),
                ("time/data_wait_s", record.data_wait_s),
                ("time/communication_share", communication_share),
                ("throughput/pairs_per_s", record.samples_per_s),
                ("cluster/world_size", record.world_size as f64),
            ];
            if let Some(lpips) = record.lpips {
                scalars.push(("loss/lpips", f64::from(lpips)));
            }
            for (tag, value) in scalars {
                run.segment.scalar(wall_time, record.step, tag, value);
            }
            run.unwritten = true;
        }
    }

    /// The evaluation under `location` (its `report.json` and PNG figures) in the `evaluate`
    /// run at `step`. A figure that is no PNG is skipped with a warning.
    pub async fn record_evaluation(
        &mut self,
        location: &DataRoot,
        step: u64,
    ) -> Result<(), StoreError> {
        let report = location.read("report.json").await?;
        let wall_time = now();
        let parsed: Value = serde_json::from_slice(&report).unwrap_or(Value::Null);
        let mut scalars = Vec::new();
        for stage in parsed["stages"].as_array().into_iter().flatten() {
            let label = stage["checkpoint"]["label"]
                .as_str()
                .unwrap_or("checkpoint");
            for part in ["trained", "untrained", "baselines"] {
                flatten(&format!("{label}/{part}"), &stage[part], &mut scalars);
            }
        }
        let figures: Vec<String> = location
            .list()
            .await?
            .into_iter()
            .map(|object| object.path)
            .filter(|path| path.ends_with(".png"))
            .collect();
        let mut images = Vec::new();
        for figure in figures {
            images.push((figure.clone(), location.read(&figure).await?));
        }
        let run = self.run(Phase::Evaluate);
        for (tag, value) in scalars {
            run.segment.scalar(wall_time, step, &tag, value);
        }
        for (figure, png) in images {
            let tag = format!("figures/{}", figure.trim_end_matches(".png"));
            if let Err(error) = run.segment.image(wall_time, step, &tag, png) {
                tracing::warn!(%error, "evaluation figure left out of TensorBoard");
            }
        }
        run.unwritten = true;
        Ok(())
    }

    /// Writes every run's file that changed, starting new files for full ones. On a failed
    /// write the events stay and go with the next call.
    pub async fn flush(&mut self) -> Result<(), StoreError> {
        for (phase, run) in &mut self.runs {
            if !run.unwritten {
                continue;
            }
            let path = format!(
                "{PREFIX}/{phase}/{}",
                event_file_name(self.started, "xfactor-coordinator", run.sequence)
            );
            self.root.write(&path, run.segment.bytes().to_vec()).await?;
            run.unwritten = false;
            if run.segment.events() >= SEGMENT_EVENTS {
                run.sequence += 1;
                run.segment = EventSegment::new(now());
            }
        }
        Ok(())
    }
}

/// Every number under `value` as `(prefix/key/..., value)`; entries of an array that carry a
/// `threshold` are named by it (`.../thresholds/30/auc`), others by position.
fn flatten(prefix: &str, value: &Value, out: &mut Vec<(String, f64)>) {
    match value {
        Value::Number(number) => {
            if let Some(number) = number.as_f64() {
                out.push((prefix.to_string(), number));
            }
        }
        Value::Object(fields) => {
            for (key, field) in fields {
                flatten(&format!("{prefix}/{key}"), field, out);
            }
        }
        Value::Array(items) => {
            for (index, item) in items.iter().enumerate() {
                let name = item
                    .get("threshold")
                    .and_then(Value::as_f64)
                    .map_or(index.to_string(), |t| format!("{t}"));
                flatten(&format!("{prefix}/{name}"), item, out);
            }
        }
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reports_flatten_to_named_numbers() {
        let report = serde_json::json!({
            "reconstruction": {"psnr": 21.5, "lpips": null},
            "probe": {"metrics": {"thresholds": [{"threshold": 30, "auc": 0.5}]}},
        });
        let mut out = Vec::new();
        flatten("trained", &report, &mut out);
        out.sort_by(|a, b| a.0.cmp(&b.0));
        assert_eq!(
            out,
            [
                ("trained/probe/metrics/thresholds/30/auc".to_string(), 0.5),
                (
                    "trained/probe/metrics/thresholds/30/threshold".to_string(),
                    30.0
                ),
                ("trained/reconstruction/psnr".to_string(), 21.5),
            ]
        );
    }

    #[tokio::test]
    async fn each_phase_gets_its_own_run_and_full_files_roll_over() {
        let root = DataRoot::in_memory("tensorboard");
        let mut board = TensorBoard::new(root.clone());
        board.record_config(Phase::Stage1, "job: x");
        let records: Vec<StepRecord> = (0..SEGMENT_EVENTS as u64 / 11 + 1)
            .map(|step| StepRecord::new(Phase::Stage1, step, 1))
            .collect();
        board.record_steps(&records);
        board.record_steps(&[StepRecord::new(Phase::Stage2, 0, 2)]);
        board.flush().await.unwrap();
        board.record_steps(&[StepRecord::new(Phase::Stage1, 999, 1)]);
        board.flush().await.unwrap();
        let paths: Vec<String> = root
            .list()
            .await
            .unwrap()
            .into_iter()
            .map(|o| o.path)
            .collect();
        assert_eq!(paths.len(), 3, "{paths:?}");
        assert!(paths[0].starts_with("tensorboard/stage1/events.out.tfevents."));
        assert!(paths[0].ends_with(".000000") && paths[1].ends_with(".000001"));
        assert!(paths[2].starts_with("tensorboard/stage2/"));
    }
}
