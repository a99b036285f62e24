//! The camera metrics exactly as the spec defines them: for every pair `i < j` of frames the
//! relative pose `T_i * inv(T_j)` of the reference and of the evaluated trajectory, the rotation
//! error (angle of `R_ref^T R_eval`) and the sign-free translation-direction error, then
//! `Rac_t` / `Tac_t` accuracies and the release's AUC@t ([`super::auc`]) of the rotation, the
//! translation and the larger of the two errors, plus the trajectory errors of camera centres.

use data::scenes::CameraPose;
use serde::{Deserialize, Serialize};

use super::spread::bootstrap_spread;

use super::auc::{auc, normalized_histogram};
use super::trajectory::TrajectoryError;
use crate::geometry::{rotation, rotation_angle_degrees, translation};

/// Thresholds (degrees) at which accuracies and AUCs are reported, as in the paper.
pub const THRESHOLDS: [u32; 6] = [3, 5, 10, 15, 20, 30];
/// Translations shorter than this have no direction; their error counts as the worst (90°).
const MIN_DIRECTION: f64 = 1e-12;

/// The errors of one pair of frames, in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PairError {
    /// Angle of `R_ref^T R_eval`, in `[0, 180]`.
    pub rotation: f64,
    /// `acos(|<t_ref, t_eval>|)` of the unit translation directions, in `[0, 90]`.
    pub translation: f64,
}

/// Rotation and sign-free translation-direction errors between two relative poses.
pub fn pair_error(reference: &CameraPose, evaluated: &CameraPose) -> PairError {
    let rotation_error =
        rotation_angle_degrees(&(rotation(reference).transpose() * rotation(evaluated)));
    let (a, b) = (translation(reference), translation(evaluated));
    let translation_error = if a.norm() < MIN_DIRECTION || b.norm() < MIN_DIRECTION {
        90.0
    } else {
        (a.dot(&b).abs() / (a.norm() * b.norm()))
            .clamp(0.0, 1.0)
            .acos()
            .to_degrees()
    };
    PairError {
        rotation: rotation_error,
        translation: translation_error,
    }
}

/// Errors of every pair `i < j` of two trajectories of equal length (world-to-camera poses):
/// the set the spec's metrics are computed over. Extra frames of the longer one are ignored.
pub fn trajectory_errors(reference: &[CameraPose], evaluated: &[CameraPose]) -> Vec<PairError> {
    let frames = reference.len().min(evaluated.len());
    let mut errors = Vec::with_capacity(frames * frames.saturating_sub(1) / 2);
    for i in 0..frames {
        for j in i + 1..frames {
            errors.push(pair_error(
                &reference[i].relative_to(&reference[j]),
                &evaluated[i].relative_to(&evaluated[j]),
            ));
        }
    }
    errors
}

/// Accuracies and AUCs at one threshold.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ThresholdScores {
    /// Threshold in degrees.
    pub threshold: u32,
    /// `Rac_t`: share of pairs whose rotation error is below the threshold.
    pub rotation_accuracy: f64,
    /// `Tac_t`: share of pairs whose translation error is below the threshold.
    pub translation_accuracy: f64,
    /// `SE3_Auc_t`: AUC@t of the `max(rotation, translation)` error.
    pub auc: f64,
    /// `Rot_Auc_t`: AUC@t of the rotation error.
    #[serde(default)]
    pub rotation_auc: f64,
    /// `Trans_Auc_t`: AUC@t of the translation error.
    #[serde(default)]
    pub translation_auc: f64,
}

/// The camera metrics of a set of pairs (possibly pooled over many sequences).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraMetrics {
    /// Pairs the metrics were computed over.
    pub pairs: usize,
    /// Mean rotation error, degrees.
    pub mean_rotation_error: f64,
    /// Mean translation-direction error, degrees.
    pub mean_translation_error: f64,
    /// Scores at each of [`THRESHOLDS`].
    pub thresholds: Vec<ThresholdScores>,
    /// Mean scale-invariant trajectory error of camera centres (`traj_err_scale_invariant`),
    /// when trajectories were given.
    #[serde(default)]
    pub trajectory_error_scale_invariant: Option<f64>,
    /// Mean unscaled trajectory error of camera centres (`traj_err_unscaled`).
    #[serde(default)]
    pub trajectory_error_unscaled: Option<f64>,
    /// Bootstrap spreads of the AUCs over the independent units the errors came from, when
    /// those were given ([`CameraMetrics::from_groups`]).
    #[serde(default)]
    pub spread: Option<CameraSpread>,
}

impl CameraMetrics {
    /// Computes every metric from pooled pair errors; an empty set scores zero everywhere.
    pub fn from_errors(errors: &[PairError]) -> Self {
        let pairs = errors.len();
        let share = |count: usize| {
            if pairs == 0 {
                0.0
            } else {
                count as f64 / pairs as f64
            }
        };
        let mean = |value: fn(&PairError) -> f64| {
            if pairs == 0 {
                0.0
            } else {
                errors.iter().map(value).sum::<f64>() / pairs as f64
            }
        };
        let rotation = normalized_histogram(errors.iter().map(|e| e.rotation), pairs);
        let translation = normalized_histogram(errors.iter().map(|e| e.translation), pairs);
        let worst =
            normalized_histogram(errors.iter().map(|e| e.rotation.max(e.translation)), pairs);
        let thresholds = THRESHOLDS
            .iter()
            .map(|&threshold| {
                let t = f64::from(threshold);
                ThresholdScores {
                    threshold,
                    rotation_accuracy: share(errors.iter().filter(|e| e.rotation < t).count()),
                    translation_accuracy: share(
                        errors.iter().filter(|e| e.translation < t).count(),
                    ),
                    auc: auc(&worst, threshold),
                    rotation_auc: auc(&rotation, threshold),
                    translation_auc: auc(&translation, threshold),
                }
            })
            .collect();
        Self {
            pairs,
            mean_rotation_error: mean(|e| e.rotation),
            mean_translation_error: mean(|e| e.translation),
            thresholds,
            trajectory_error_scale_invariant: None,
            trajectory_error_unscaled: None,
            spread: None,
        }
    }

    /// The metrics of every error of `groups` (one group per independent unit: a transfer, a
    /// held-out sequence) with the spreads of their AUCs over those units.
    pub fn from_groups(groups: &[Vec<PairError>], seed: u64) -> Self {
        let errors: Vec<PairError> = groups.iter().flatten().copied().collect();
        Self {
            spread: Some(camera_spread(groups, seed)),
            ..Self::from_errors(&errors)
        }
    }

    /// Adds the means of per-trajectory errors (none given: none reported).
    pub fn with_trajectory_errors(mut self, errors: &[TrajectoryError]) -> Self {
        if !errors.is_empty() {
            let n = errors.len() as f64;
            self.trajectory_error_scale_invariant =
                Some(errors.iter().map(|e| e.scale_invariant).sum::<f64>() / n);
            self.trajectory_error_unscaled =
                Some(errors.iter().map(|e| e.unscaled).sum::<f64>() / n);
        }
        self
    }

    /// Every figure under the release's name (`Rac_3`, `Rot_Auc_3`, `SE3_Auc_3`, ...,
    /// `traj_err_scale_invariant`), so reports and fixtures compare key by key.
    pub fn release_figures(&self) -> Vec<(String, f64)> {
        let mut figures = Vec::new();
        for s in &self.thresholds {
            let t = s.threshold;
            figures.push((format!("Rac_{t}"), s.rotation_accuracy));
            figures.push((format!("Tac_{t}"), s.translation_accuracy));
            figures.push((format!("Rot_Auc_{t}"), s.rotation_auc));
            figures.push((format!("Trans_Auc_{t}"), s.translation_auc));
            figures.push((format!("SE3_Auc_{t}"), s.auc));
        }
        if let Some(v) = self.trajectory_error_scale_invariant {
            figures.push(("traj_err_scale_invariant".to_string(), v));
        }
        if let Some(v) = self.trajectory_error_unscaled {
            figures.push(("traj_err_unscaled".to_string(), v));
        }
        figures
    }

    /// The scores at `threshold` degrees, if it is one of [`THRESHOLDS`].
    pub fn at(&self, threshold: u32) -> Option<&ThresholdScores> {
        self.thresholds.iter().find(|s| s.threshold == threshold)
    }
}

/// Spreads of the headline camera figures.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraSpread {
    /// Spread of `SE3_Auc@20`.
    pub auc20: f64,
    /// Spread of `SE3_Auc@30`.
    pub auc30: f64,
}

/// The spreads of `SE3_Auc@20` and `@30` over `groups`, each group the pair errors of one
/// independent unit (a transfer, a held-out sequence).
pub fn camera_spread(groups: &[Vec<PairError>], seed: u64) -> CameraSpread {
    let auc = |threshold: u32| {
        bootstrap_spread(groups, seed, move |sample| {
            let errors: Vec<PairError> = sample.iter().flat_map(|g| g.iter().copied()).collect();
            CameraMetrics::from_errors(&errors)
                .at(threshold)
                .map_or(0.0, |s| s.auc)
        })
    };
    CameraSpread {
        auc20: auc(20),
        auc30: auc(30),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose;
    use nalgebra::{Rotation3, Vector3};

    fn yawed(degrees: f64, t: [f64; 3]) -> CameraPose {
        let r = Rotation3::from_axis_angle(&Vector3::y_axis(), degrees.to_radians()).into_inner();
        pose(&r, &Vector3::from(t))
    }

    #[test]
    fn pair_errors_match_hand_computed_angles() {
        // Rotations about one axis compose by adding angles: 10° vs 14° is a 4° error.
        let e = pair_error(&yawed(10.0, [1.0, 0.0, 0.0]), &yawed(14.0, [1.0, 1.0, 0.0]));
        assert!((e.rotation - 4.0).abs() < 1e-9, "{e:?}");
        assert!((e.translation - 45.0).abs() < 1e-9, "{e:?}");
        // The translation angle is sign-free: the opposite direction is no error at all.
        let e = pair_error(&yawed(0.0, [0.0, 0.0, 2.0]), &yawed(0.0, [0.0, 0.0, -5.0]));
        assert!(
            e.rotation.abs() < 1e-9 && e.translation.abs() < 1e-6,
            "{e:?}"
        );
        // 120° between directions reads as 60°.
        let e = pair_error(
            &yawed(0.0, [1.0, 0.0, 0.0]),
            &yawed(0.0, [-0.5, 3f64.sqrt() / 2.0, 0.0]),
        );
        assert!((e.translation - 60.0).abs() < 1e-9, "{e:?}");
        let e = pair_error(&yawed(0.0, [1.0, 0.0, 0.0]), &yawed(0.0, [0.0; 3]));
        assert_eq!(e.translation, 90.0);
    }

    #[test]
    fn trajectory_pairs_use_relative_poses_in_both_orders_of_world() {
        let reference = [
            yawed(0.0, [0.0, 0.0, 0.0]),
            yawed(10.0, [1.0, 0.0, 0.0]),
            yawed(20.0, [2.0, 0.0, 0.5]),
        ];
        // The same trajectory in another world frame (`T_i * S`, here `T_i * inv(inv(S))`)
        // has identical relative poses: zero error.
        let shift = yawed(33.0, [0.3, -2.0, 7.0]);
        let moved: Vec<CameraPose> = reference
            .iter()
            .map(|p| p.relative_to(&CameraPose::identity().relative_to(&shift)))
            .collect();
        let errors = trajectory_errors(&reference, &moved);
        assert_eq!(errors.len(), 3);
        assert!(
            errors
                .iter()
                .all(|e| e.rotation < 1e-6 && e.translation < 1e-5),
            "{errors:?}"
        );
        // Over-rotating the last frame by 6° gives errors of 0, 6 and 6 degrees.
        let mut bent = reference;
        bent[2] = yawed(26.0, [2.0, 0.0, 0.5]);
        let rotations: Vec<f64> = trajectory_errors(&reference, &bent)
            .iter()
            .map(|e| (e.rotation * 1e6).round() / 1e6)
            .collect();
        assert_eq!(rotations, vec![0.0, 6.0, 6.0]);
    }

    #[test]
    fn accuracies_and_auc_from_the_histogram() {
        let errors = [
            PairError {
                rotation: 0.5,
                translation: 2.5,
            },
            PairError {
                rotation: 4.0,
                translation: 1.0,
            },
            PairError {
                rotation: 12.0,
                translation: 40.0,
            },
            PairError {
                rotation: 1.0,
                translation: 1.0,
            },
        ];
        let metrics = CameraMetrics::from_errors(&errors);
        let at3 = metrics.at(3).unwrap();
        assert_eq!(at3.rotation_accuracy, 0.5);
        assert_eq!(at3.translation_accuracy, 0.75);
        let at5 = metrics.at(5).unwrap();
        assert_eq!(at5.rotation_accuracy, 0.75);
        assert_eq!(metrics.at(15).unwrap().translation_accuracy, 0.75);
        // max errors 2.5, 4, 40, 1 fall in bins 2, 4, none, 1 of width 30/31 degree
        // (bin = floor(e * 31 / 30)). Cumulative shares over bins 0..: 0, .25, .5, .5, .75, ...;
        // AUC@3 = (0 + .25 + .5) / 3 = .25, AUC@5 = (0 + .25 + .5 + .5 + .75) / 5 = .4,
        // AUC@30 = (0 + .25 + .5 + .5 + 26 * .75) / 30.
        assert!((at3.auc - 0.25).abs() < 1e-12);
        assert!((at5.auc - 0.4).abs() < 1e-12);
        let auc30 = (0.25 + 0.5 + 0.5 + 26.0 * 0.75) / 30.0;
        assert!((metrics.at(30).unwrap().auc - auc30).abs() < 1e-12);
        // Rotation alone: 0.5, 4, 12, 1 in bins 0, 4, 12, 1: cumulative .25, .5, .5, .5, .75.
        assert!((at5.rotation_auc - (0.25 + 0.5 + 0.5 + 0.5 + 0.75) / 5.0).abs() < 1e-12);
        assert!((metrics.mean_rotation_error - 17.5 / 4.0).abs() < 1e-12);
        assert_eq!(CameraMetrics::from_errors(&[]).pairs, 0);
    }

    #[test]
    fn camera_spread_is_zero_for_agreeing_units_and_not_for_mixed_ones() {
        let exact = PairError {
            rotation: 0.0,
            translation: 0.0,
        };
        let wrong = PairError {
            rotation: 180.0,
            translation: 90.0,
        };
        let same = vec![vec![exact; 4]; 6];
        assert_eq!(camera_spread(&same, 0), CameraSpread::default());
        let mixed: Vec<Vec<PairError>> = (0..6)
            .map(|i| vec![if i % 2 == 0 { exact } else { wrong }; 4])
            .collect();
        let spread = camera_spread(&mixed, 0);
        assert!(spread.auc30 > 0.05 && spread.auc30 < 0.4, "{spread:?}");
    }
}
