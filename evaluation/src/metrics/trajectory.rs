//! The release's two trajectory errors of camera centres (`inv(T_cw)[:3, 3]`): the mean
//! absolute difference after scaling the prediction by `<t, p> / <p, p>` (scale-invariant, the
//! scale clamped below at `1e-8` in the denominator), and without scaling.

use data::scenes::CameraPose;
use serde::{Deserialize, Serialize};

/// Both errors of one trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryError {
    /// Mean `|c_ref - s * c_eval|` with the least-squares scale `s`.
    pub scale_invariant: f64,
    /// Mean `|c_ref - c_eval|`.
    pub unscaled: f64,
}

/// The errors between two trajectories of world-to-camera poses (the shorter length is used).
pub fn trajectory_error(reference: &[CameraPose], evaluated: &[CameraPose]) -> TrajectoryError {
    let frames = reference.len().min(evaluated.len());
    let target: Vec<[f64; 3]> = reference[..frames].iter().map(CameraPose::center).collect();
    let pred: Vec<[f64; 3]> = evaluated[..frames].iter().map(CameraPose::center).collect();
    let dot = |a: &[[f64; 3]], b: &[[f64; 3]]| -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| x[0] * y[0] + x[1] * y[1] + x[2] * y[2])
            .sum()
    };
    let scale = dot(&target, &pred) / dot(&pred, &pred).max(1e-8);
    let mean_abs = |s: f64| -> f64 {
        let count = (frames * 3).max(1) as f64;
        target
            .iter()
            .zip(&pred)
            .flat_map(|(t, p)| (0..3).map(move |i| (t[i] - s * p[i]).abs()))
            .sum::<f64>()
            / count
    };
    TrajectoryError {
        scale_invariant: mean_abs(scale),
        unscaled: mean_abs(1.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(center: [f64; 3]) -> CameraPose {
        CameraPose::look_at(center, [center[0], center[1], center[2] + 1.0])
    }

    #[test]
    fn a_scaled_copy_has_no_scale_invariant_error() {
        let reference = [
            at([0.0, 0.0, 0.0]),
            at([1.0, 0.0, 0.0]),
            at([2.0, 1.0, 0.0]),
        ];
        let half: Vec<CameraPose> = reference
            .iter()
            .map(|p| {
                let c = p.center();
                at([c[0] / 2.0, c[1] / 2.0, c[2] / 2.0])
            })
            .collect();
        let error = trajectory_error(&reference, &half);
        assert!(error.scale_invariant < 1e-12, "{error:?}");
        // Unscaled: |0| + |0.5| + |1| + |0.5| over 9 coordinates.
        assert!((error.unscaled - 2.0 / 9.0).abs() < 1e-12, "{error:?}");
    }
}
