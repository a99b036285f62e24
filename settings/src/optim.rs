//! The learning-rate schedule and AdamW's hyper-parameters. The optimiser itself is
//! trainer-core's; the schedule is plain arithmetic, so it lives with its settings.

use serde::{Deserialize, Serialize};

/// Linear warm-up then cosine decay, as `optax.warmup_cosine_decay_schedule`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Schedule {
    /// Learning rate at step 0.
    pub initial_lr: f64,
    /// Learning rate at the end of warm-up.
    pub peak_lr: f64,
    /// Learning rate from `total_steps` on.
    pub final_lr: f64,
    /// Steps of linear warm-up.
    pub warmup_steps: u64,
    /// Step at which the cosine reaches `final_lr` (warm-up included).
    pub total_steps: u64,
}

impl Default for Schedule {
    /// The paper's: `1e-12 -> 4e-4` over 4000 steps, cosine to `1e-4` at step 100000.
    fn default() -> Self {
        Self {
            initial_lr: 1e-12,
            peak_lr: 4e-4,
            final_lr: 1e-4,
            warmup_steps: 4000,
            total_steps: 100_000,
        }
    }
}

impl Schedule {
    /// The learning rate used for the update of `step` (counted from 0), computed as the
    /// release's optax schedule computes it under XLA: in `f32`, the warm-up in optax's
    /// polynomial form `(init - peak) * (1 - step / warmup) + peak` with the multiply-add fused
    /// (XLA contracts it), the decay as `peak * ((1 - alpha) * cosine + alpha)`. Rounding the
    /// same way matters early in warm-up, where the `f32` difference of two numbers near the
    /// peak is all that is left: at step 2 the release's rate is `2.0000934e-7`, not the
    /// `2.00001e-7` of exact arithmetic (a 4e-5 relative difference in every update). One
    /// consequence: the `1e-12` initial rate rounds away and step 0's rate is `0`, as in the
    /// release.
    pub fn learning_rate(&self, step: u64) -> f64 {
        let peak = self.peak_lr as f32;
        if step < self.warmup_steps {
            let remaining = 1.0f32 - step as f32 / self.warmup_steps as f32;
            let span = (self.initial_lr - self.peak_lr) as f32;
            return f64::from(span.mul_add(remaining, peak));
        }
        let decay_steps = self.total_steps.saturating_sub(self.warmup_steps).max(1);
        let count = (step - self.warmup_steps).min(decay_steps) as f32;
        let cosine = 0.5f32 * (1.0 + (std::f32::consts::PI * count / decay_steps as f32).cos());
        let alpha = self.final_lr / self.peak_lr;
        let decayed = ((1.0 - alpha) as f32).mul_add(cosine, alpha as f32);
        f64::from(peak * decayed)
    }
}

/// AdamW hyper-parameters (defaults: the paper's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdamWConfig {
    /// First-moment decay.
    pub beta1: f64,
    /// Second-moment decay.
    pub beta2: f64,
    /// Added to the root of the second moment.
    pub epsilon: f64,
    /// Decoupled weight decay, multiplied by the learning rate.
    pub weight_decay: f64,
    /// Clip gradients to this global norm (over all parameters together).
    pub clip_norm: Option<f64>,
    /// Skip the whole update when the pre-clip global norm exceeds this or is NaN (E-RayZer
    /// uses 5.0).
    pub skip_norm_above: Option<f64>,
}

impl Default for AdamWConfig {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.95,
            epsilon: 1e-8,
            weight_decay: 5e-3,
            clip_norm: Some(1.0),
            skip_norm_above: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_matches_the_paper_at_its_landmarks() {
        let schedule = Schedule::default();
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * b.abs();
        assert!(close(schedule.learning_rate(2000), 2e-4));
        assert!(close(schedule.learning_rate(4000), 4e-4));
        assert!(close(schedule.learning_rate(52_000), 2.5e-4));
        assert!(close(schedule.learning_rate(100_000), 1e-4));
        assert!(close(schedule.learning_rate(150_000), 1e-4));
    }

    #[test]
    fn early_warm_up_rounds_as_the_release_in_f32() {
        let schedule = Schedule::default();
        // What optax under XLA computes for the paper's schedule (the clu-checkpoint fixture's
        // third update shows it): the fused f32 multiply-add, not exact arithmetic.
        assert_eq!(schedule.learning_rate(2) as f32, 2.000_093_4e-7_f32);
        assert_eq!(schedule.learning_rate(0), 0.0);
        assert!(schedule.learning_rate(1) > 0.0);
    }
}
