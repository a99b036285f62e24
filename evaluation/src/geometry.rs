//! Conversions between the generated scenes' [`CameraPose`] and nalgebra, and the few rigid-body
//! operations the metrics, oracles and probe share.

use data::scenes::CameraPose;
use nalgebra::{Matrix3, Vector3};

/// The rotation of `pose` as an nalgebra matrix, for linear algebra on poses.
pub fn rotation(pose: &CameraPose) -> Matrix3<f64> {
    let r = pose.rotation;
    Matrix3::new(
        r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
    )
}

/// The translation of `pose` as an nalgebra vector.
pub fn translation(pose: &CameraPose) -> Vector3<f64> {
    Vector3::from(pose.translation)
}

/// A [`CameraPose`] from nalgebra parts, so estimators can hand back the project's pose type.
pub fn pose(rotation: &Matrix3<f64>, translation: &Vector3<f64>) -> CameraPose {
    CameraPose {
        rotation: std::array::from_fn(|i| std::array::from_fn(|j| rotation[(i, j)])),
        translation: [translation[0], translation[1], translation[2]],
    }
}

/// The angle of a rotation matrix in degrees, clamped so rounding never yields NaN: the
/// rotation error of the camera metrics.
pub fn rotation_angle_degrees(rotation: &Matrix3<f64>) -> f64 {
    ((rotation.trace() - 1.0) / 2.0)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Every pose of `poses` expressed relative to `poses[reference]` (`T_i * inv(T_ref)`), so the
/// reference becomes the identity: the relative poses the pose latents stand for.
pub fn relative_to_reference(poses: &[CameraPose], reference: usize) -> Vec<CameraPose> {
    match poses.get(reference) {
        Some(anchor) => poses.iter().map(|p| p.relative_to(anchor)).collect(),
        None => poses.to_vec(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_and_round_trips() {
        let r = nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), 0.5).into_inner();
        assert!((rotation_angle_degrees(&r) - 0.5f64.to_degrees()).abs() < 1e-9);
        let p = pose(&r, &Vector3::new(1.0, 2.0, 3.0));
        assert_eq!(rotation(&p), r);
        assert_eq!(translation(&p), Vector3::new(1.0, 2.0, 3.0));
        let rel = relative_to_reference(&[p, CameraPose::identity()], 0);
        assert!(rotation_angle_degrees(&rotation(&rel[0])) < 1e-6);
        assert!(translation(&rel[0]).norm() < 1e-9);
    }
}
