//! The series both the coordinator and the workers export with the same meaning, named once so
//! a dashboard can put a worker's page next to the coordinator's.

use crate::Metric;

/// Stage being trained (1 or 2; 3 evaluates).
pub const STAGE: Metric = Metric::gauge("xfactor_stage", "Stage being trained (3: evaluation).");
/// Steps done in the current stage.
pub const STEP: Metric =
    Metric::gauge("xfactor_step", "Optimiser steps done in the current stage.");
/// Loss of the last step's global batch.
pub const LOSS: Metric = Metric::gauge("xfactor_loss", "Loss of the last step's global batch.");
/// Learning rate of the last step.
pub const LEARNING_RATE: Metric =
    Metric::gauge("xfactor_learning_rate", "Learning rate of the last step.");
/// Gradient norm before clipping.
pub const GRAD_NORM: Metric = Metric::gauge(
    "xfactor_grad_norm",
    "Global gradient norm of the last step before clipping.",
);
/// Current group generation.
pub const GENERATION: Metric = Metric::gauge(
    "xfactor_generation",
    "Group generation (grows on every re-formation).",
);
