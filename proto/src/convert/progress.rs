//! What a worker says about its progress, read from the wire into `settings::work`'s domain
//! types: its activity within a step (heartbeats) and its report of a finished step.

use settings::work::{Activity, StepLoss, StepReport};

use super::ConvertError;
use crate::v1;

/// An activity from its wire value; `field` names it in the error.
pub fn activity_from_wire(value: i32, field: &'static str) -> Result<Activity, ConvertError> {
    match v1::Activity::try_from(value) {
        Ok(v1::Activity::Idle) => Ok(Activity::Idle),
        Ok(v1::Activity::Computing) => Ok(Activity::Computing),
        Ok(v1::Activity::Allreduce) => Ok(Activity::Allreduce),
        Ok(v1::Activity::Committing) => Ok(Activity::Committing),
        Err(_) => Err(ConvertError::Unknown { field, value }),
    }
}

impl From<&v1::StepReport> for StepReport {
    /// Every field the wire carries maps to a value (an absent loss stays absent; a NaN LPIPS
    /// is the wire's "no LPIPS term"), so reading a report cannot fail.
    fn from(wire: &v1::StepReport) -> Self {
        Self {
            generation: wire.generation,
            step: wire.step,
            loss: wire.loss.as_ref().map(|loss| StepLoss {
                total: loss.total,
                learning_rate: loss.learning_rate,
                grad_norm: loss.grad_norm,
                applied: loss.applied,
                l1: loss.l1,
                lpips: (!loss.lpips.is_nan()).then_some(loss.lpips),
            }),
            checksum: wire.checksum_computed.then_some(wire.parameter_checksum),
            samples_per_s: wire.samples_per_s,
            allreduce_s: wire.allreduce_s,
            step_s: wire.step_s,
            data_wait_s: wire.data_wait_s,
            skipped_frames: wire.skipped_frames,
            skipped_examples: wire.skipped_examples.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn activities_are_read_from_the_wire_and_unknown_ones_are_named() {
        for (wire, activity) in [
            (v1::Activity::Idle, Activity::Idle),
            (v1::Activity::Computing, Activity::Computing),
            (v1::Activity::Allreduce, Activity::Allreduce),
            (v1::Activity::Committing, Activity::Committing),
        ] {
            assert_eq!(activity_from_wire(wire as i32, "a"), Ok(activity));
        }
        assert_eq!(
            activity_from_wire(42, "heartbeat.activity"),
            Err(ConvertError::Unknown {
                field: "heartbeat.activity",
                value: 42
            })
        );
    }

    #[test]
    fn a_step_report_reads_its_loss_checksum_and_lpips() {
        let wire = v1::StepReport {
            generation: 3,
            step: 9,
            loss: Some(v1::LossTerms {
                total: 0.5,
                lpips: f32::NAN,
                applied: true,
                ..v1::LossTerms::default()
            }),
            parameter_checksum: 77,
            checksum_computed: true,
            skipped_frames: 2,
            ..v1::StepReport::default()
        };
        let report = StepReport::from(&wire);
        assert_eq!((report.generation, report.step), (3, 9));
        let loss = report.loss.expect("a loss");
        assert_eq!((loss.total, loss.lpips, loss.applied), (0.5, None, true));
        assert_eq!(report.checksum, Some(77));
        let unchecked = v1::StepReport {
            parameter_checksum: 77,
            ..v1::StepReport::default()
        };
        assert_eq!(StepReport::from(&unchecked).checksum, None);
        assert_eq!(StepReport::from(&unchecked).loss, None);
    }
}
