//! The books of one finished step: what the coordinator is told ([`StepAccount::report`]) and
//! what `/metrics` shows ([`StepAccount::record`]). Pure figures in, messages and gauges out,
//! so the arithmetic (rates, which step a report names, when a checksum is due) is tested
//! without a trainer.

use proto::v1::{LossTerms, StepReport};
use settings::{DeviceInUse, Phase};
use telemetry::Registry;

use crate::datapath::StepFigures;
use crate::metrics;

/// Everything known about one step once it is applied.
#[derive(Debug, Clone)]
pub struct StepAccount {
    /// The step's own figures.
    pub figures: StepFigures,
    /// Samples this worker trained in it.
    pub samples: usize,
    /// Its wall time.
    pub seconds: f64,
    /// Seconds it waited on the data loader.
    pub data_wait_s: f64,
    /// Undecodable frames skipped so far in this generation.
    pub skipped_frames: u64,
    /// Examples of them (sent only while there are some).
    pub skipped_examples: Vec<String>,
    /// Micro-batches the loader has ready.
    pub loader_queue: usize,
}

/// Who reports: the worker's registration and the generation it is in.
#[derive(Debug, Clone)]
pub struct Reporter {
    /// The worker's id.
    pub worker_id: u64,
    /// Its registration's secret.
    pub session: String,
    /// The generation.
    pub generation: u64,
    /// The stage it trains.
    pub stage: Phase,
    /// The device it trains on.
    pub device: Option<DeviceInUse>,
}

impl StepAccount {
    /// Samples per second of this worker in the step.
    pub fn samples_per_s(&self) -> f64 {
        self.samples as f64 / self.seconds.max(1e-9)
    }

    /// The report for the coordinator. It names the step as it was before the update
    /// (counted from 0), as the coordinator's records do.
    pub fn report(&self, reporter: &Reporter) -> StepReport {
        let metrics = &self.figures.metrics;
        StepReport {
            worker_id: reporter.worker_id,
            session: reporter.session.clone(),
            generation: reporter.generation,
            phase: proto::convert::phase_to_wire(reporter.stage) as i32,
            step: metrics.step,
            loss: Some(LossTerms {
                total: metrics.loss,
                learning_rate: metrics.learning_rate,
                grad_norm: metrics.grad_norm,
                applied: metrics.applied,
                l1: self.figures.l1,
                lpips: self.figures.lpips,
            }),
            parameter_checksum: self.figures.checksum.unwrap_or(0),
            checksum_computed: self.figures.checksum.is_some(),
            samples_per_s: self.samples_per_s(),
            allreduce_s: self.figures.allreduce_s,
            skipped_frames: self.skipped_frames,
            step_s: self.seconds,
            data_wait_s: self.data_wait_s,
            device: reporter
                .device
                .as_ref()
                .map(proto::convert::device_in_use_to_wire),
            skipped_examples: if self.skipped_frames > 0 {
                self.skipped_examples.clone()
            } else {
                Vec::new()
            },
        }
    }

    /// Sets this worker's gauges and adds to its histograms.
    pub fn record(&self, registry: &Registry) {
        let metrics = &self.figures.metrics;
        registry.set(&metrics::STEP, &[], (metrics.step + 1) as f64);
        registry.set(&metrics::LOSS, &[], f64::from(metrics.loss));
        registry.set(&metrics::LEARNING_RATE, &[], metrics.learning_rate);
        registry.set(&metrics::GRAD_NORM, &[], metrics.grad_norm);
        registry.set(&metrics::STEP_SECONDS, &[], self.seconds);
        registry.set(&metrics::SAMPLES_PER_SECOND, &[], self.samples_per_s());
        registry.set(&metrics::ALLREDUCE_SECONDS, &[], self.figures.allreduce_s);
        registry.observe(&metrics::STEP_DURATION, &[], self.seconds);
        registry.observe(&metrics::ALLREDUCE_DURATION, &[], self.figures.allreduce_s);
        registry.observe(&metrics::DATA_WAIT, &[], self.data_wait_s);
        if self.figures.allreduce_s > 0.0 {
            let bandwidth = self.figures.reduced_bytes as f64 / self.figures.allreduce_s;
            registry.set(&metrics::ALLREDUCE_BANDWIDTH, &[], bandwidth);
        }
        registry.set(&metrics::LOADER_QUEUE, &[], self.loader_queue as f64);
        registry.raise_to(&metrics::SKIPPED_FRAMES, &[], self.skipped_frames as f64);
    }
}

#[cfg(test)]
mod tests {
    use trainer_core::trainer::StepMetrics;

    use super::*;
    use crate::datapath::PhaseTimes;

    fn account(skipped_frames: u64, checksum: Option<u32>) -> StepAccount {
        StepAccount {
            figures: StepFigures {
                metrics: StepMetrics {
                    step: 6,
                    loss: 0.5,
                    learning_rate: 1e-3,
                    grad_norm: 2.0,
                    applied: true,
                },
                l1: 0.4,
                lpips: 0.2,
                allreduce_s: 0.5,
                reduced_bytes: 4000,
                checksum,
                phases: PhaseTimes::default(),
            },
            samples: 8,
            seconds: 2.0,
            data_wait_s: 0.25,
            skipped_frames,
            skipped_examples: vec!["scene-3/frame-0007.png".into()],
            loader_queue: 2,
        }
    }

    fn reporter() -> Reporter {
        Reporter {
            worker_id: 4,
            session: "secret".into(),
            generation: 9,
            stage: Phase::Stage2,
            device: Some(DeviceInUse {
                backend: settings::Backend::Cpu,
                name: "cpu".into(),
                replicas: 2,
            }),
        }
    }

    #[test]
    fn a_report_names_the_step_before_its_update_and_carries_every_figure() {
        let report = account(0, Some(77)).report(&reporter());
        assert_eq!(
            (report.worker_id, report.generation, report.step),
            (4, 9, 6)
        );
        assert_eq!(report.session, "secret");
        let device = report.device.as_ref().expect("the step names its device");
        assert_eq!(
            (device.backend, device.replicas),
            (proto::v1::Device::Cpu as i32, 2)
        );
        assert_eq!(report.phase, proto::v1::Phase::Stage2 as i32);
        let loss = report.loss.unwrap();
        assert_eq!((loss.total, loss.l1, loss.lpips), (0.5, 0.4, 0.2));
        assert_eq!(
            (loss.learning_rate, loss.grad_norm, loss.applied),
            (1e-3, 2.0, true)
        );
        assert_eq!(
            (report.parameter_checksum, report.checksum_computed),
            (77, true)
        );
        assert_eq!(report.samples_per_s, 4.0);
        assert_eq!(
            (report.step_s, report.allreduce_s, report.data_wait_s),
            (2.0, 0.5, 0.25)
        );
    }

    #[test]
    fn skipped_examples_travel_only_while_frames_are_skipped() {
        assert!(
            account(0, None)
                .report(&reporter())
                .skipped_examples
                .is_empty()
        );
        let skipping = account(3, None).report(&reporter());
        assert_eq!(skipping.skipped_frames, 3);
        assert_eq!(skipping.skipped_examples, ["scene-3/frame-0007.png"]);
        assert!(!skipping.checksum_computed);
    }

    #[test]
    fn metrics_show_the_steps_done_and_the_bandwidth() {
        let registry = Registry::new();
        account(0, None).record(&registry);
        let text = registry.render();
        assert!(text.contains("xfactor_step 7"), "{text}");
        assert!(
            text.contains("xfactor_allreduce_bytes_per_second 8000"),
            "{text}"
        );
    }
}
