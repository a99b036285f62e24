//! Explicit cameras for the "SE(3) & Plücker" ablation: the camera vector PoseEnc reads for a
//! view, and the Plücker ray map of its pixels that Render is conditioned on in place of a
//! latent.
//!
//! A camera vector `c` (10 values) is `(r, t, φ)`:
//! - `r` (6): the first two columns of the camera-to-reference rotation, offset so that `r = 0`
//!   is the identity, made orthonormal by Gram-Schmidt (the continuous 6-d representation of
//!   Zhou et al., 2019); the third column is their cross product;
//! - `t` (3): the camera centre in the reference camera's frame;
//! - `φ`: the log focal length relative to a 60° field of view.
//!
//! PoseEnc's reference view reads exactly `c = 0`, the identity camera. A sample's views share
//! one focal length (RayZer's assumption), the target's, read with its pose.

use burn::tensor::{Tensor, TensorData};

use settings::model::{CAMERA_VECTOR_VALUES, PLUCKER_VALUES};

/// Focal length of `φ = 0` in units of the image side: a 60° field of view, `1 / (2 tan 30°)`.
pub const REFERENCE_FOCAL: f64 = 0.866_025_403_784_438_6;

/// Added under square roots so a degenerate vector has a finite gradient.
const NORM_EPSILON: f64 = 1e-12;

/// Cross product over the last axis (of size 3).
fn cross<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> Tensor<D> {
    let axis = D - 1;
    let part = |t: &Tensor<D>, i: usize| t.clone().narrow(axis, i, 1);
    Tensor::cat(
        vec![
            part(&a, 1) * part(&b, 2) - part(&a, 2) * part(&b, 1),
            part(&a, 2) * part(&b, 0) - part(&a, 0) * part(&b, 2),
            part(&a, 0) * part(&b, 1) - part(&a, 1) * part(&b, 0),
        ],
        axis,
    )
}

/// Scales the last axis to unit length.
fn normalize<const D: usize>(v: Tensor<D>) -> Tensor<D> {
    let norm = (v.clone() * v.clone())
        .sum_dim(D - 1)
        .add_scalar(NORM_EPSILON)
        .sqrt();
    v / norm
}

/// The rotation of camera vectors `(..., 10)` as its three columns, each `(..., 3)`.
pub fn rotation_columns<const D: usize>(cameras: Tensor<D>) -> [Tensor<D>; 3] {
    let axis = D - 1;
    let device = cameras.device();
    let a1 = cameras.clone().narrow(axis, 0, 3);
    let a2 = cameras.narrow(axis, 3, 3);
    let offset = |values: [f32; 3]| {
        let mut shape = [1; D];
        shape[axis] = 3;
        Tensor::<D>::from_data(TensorData::new(values.to_vec(), shape), &device)
    };
    let b1 = normalize(a1 + offset([1.0, 0.0, 0.0]));
    let a2 = a2 + offset([0.0, 1.0, 0.0]);
    let along = (b1.clone() * a2.clone()).sum_dim(axis);
    let b2 = normalize(a2 - b1.clone() * along);
    let b3 = cross(b1.clone(), b2.clone());
    [b1, b2, b3]
}

/// Plücker ray tokens of per-patch cameras.
///
/// `cameras: (B, V, T, 10)` gives each patch token of each view the camera its pixels are seen
/// with; `focal: (B, V, T, 1)` the `φ` to use for them. Patches lie row-major on a
/// `grid x grid` grid of `patch x patch` pixels. Returns `(B, V, T, 6 p^2)`: for each pixel
/// of the patch in `(row, column)` order (as [`super::patchify`] orders them), the unit ray
/// direction `d` in the reference frame and its moment `t x d`.
///
/// A pixel at column `x`, row `y` of an `S x S` image looks along
/// `R (u / f, v / f, 1)` with `u = (x + 0.5) / S - 0.5`, `v = (y + 0.5) / S - 0.5`,
/// `f = REFERENCE_FOCAL exp(φ)`.
pub fn plucker_tokens(
    cameras: Tensor<4>,
    focal: Tensor<4>,
    patch: usize,
    grid: usize,
) -> Tensor<4> {
    let [b, v, tokens, values] = cameras.dims();
    assert_eq!(values, CAMERA_VECTOR_VALUES, "camera vectors");
    assert_eq!(tokens, grid * grid, "tokens of a {grid}x{grid} grid");
    let device = cameras.device();
    let pixels = patch * patch;
    let side = (grid * patch) as f32;
    let (mut u, mut w) = (Vec::with_capacity(tokens * pixels), Vec::new());
    for row in 0..grid {
        for col in 0..grid {
            for y in 0..patch {
                for x in 0..patch {
                    u.push(((col * patch + x) as f32 + 0.5) / side - 0.5);
                    w.push(((row * patch + y) as f32 + 0.5) / side - 0.5);
                }
            }
        }
    }
    let plane = |coordinates: Vec<f32>| {
        Tensor::<5>::from_data(
            TensorData::new(coordinates, [1, 1, tokens, pixels, 1]),
            &device,
        )
    };
    let focal = focal
        .exp()
        .mul_scalar(REFERENCE_FOCAL)
        .reshape([b, v, tokens, 1, 1]);
    let [c1, c2, c3] = rotation_columns(cameras.clone()).map(|c| c.reshape([b, v, tokens, 1, 3]));
    let direction = normalize(
        c1 * (plane(u) / focal.clone())
            + c2 * (plane(w) / focal)
            + c3.expand([b, v, tokens, pixels, 3]),
    );
    let centre = cameras
        .narrow(3, 6, 3)
        .reshape([b, v, tokens, 1, 3])
        .expand([b, v, tokens, pixels, 3]);
    let moment = cross(centre, direction.clone());
    Tensor::cat(vec![direction, moment], 4).reshape([b, v, tokens, pixels * PLUCKER_VALUES])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.try_into_vec_as::<f32>().unwrap()
    }

    #[test]
    fn the_zero_vector_is_the_identity_rotation() {
        let device = Device::flex();
        let zero = Tensor::<2>::zeros([1, CAMERA_VECTOR_VALUES], &device);
        let columns = rotation_columns(zero).map(values);
        assert_eq!(
            columns,
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(|c| c.to_vec())
        );
    }

    #[test]
    fn rotations_are_orthonormal_and_right_handed() {
        let device = Device::flex();
        let raw = vec![0.3, -1.2, 0.5, 2.0, 0.7, -0.4, 0.0, 0.0, 0.0, 0.0];
        let cameras = Tensor::<2>::from_data(TensorData::new(raw, [1, 10]), &device);
        let [b1, b2, b3] = rotation_columns(cameras).map(values);
        let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
        for (a, b, want) in [
            (&b1, &b1, 1.0),
            (&b2, &b2, 1.0),
            (&b3, &b3, 1.0),
            (&b1, &b2, 0.0),
            (&b1, &b3, 0.0),
            (&b2, &b3, 0.0),
        ] {
            assert!((dot(a, b) - want).abs() < 1e-6, "{a:?} . {b:?}");
        }
        let det = b1[0] * (b2[1] * b3[2] - b2[2] * b3[1]) - b1[1] * (b2[0] * b3[2] - b2[2] * b3[0])
            + b1[2] * (b2[0] * b3[1] - b2[1] * b3[0]);
        assert!((det - 1.0).abs() < 1e-6, "det {det}");
    }

    #[test]
    fn a_quarter_turn_camera_rays_as_by_hand() {
        // Rotation 90° about y: columns (0, 0, -1), (0, 1, 0), (1, 0, 0); centre (1, 2, 3);
        // focal twice the reference's. Two views, a 2x2 grid of 2x2 patches.
        let device = Device::flex();
        let turn = [-1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 2f32.ln()];
        let mut raw = vec![0.0f32; 10 * 4];
        for _ in 0..4 {
            raw.extend_from_slice(&turn);
        }
        let cameras = Tensor::<4>::from_data(TensorData::new(raw, [1, 2, 4, 10]), &device);
        let focal = cameras.clone().narrow(3, 9, 1);
        let rays = values(plucker_tokens(cameras, focal, 2, 2));
        assert_eq!(rays.len(), 2 * 4 * 24);
        let (side, f) = (4.0, 2.0 * REFERENCE_FOCAL);
        for (token, row, col) in [(0usize, 0usize, 0usize), (3, 1, 1)] {
            for (pixel, y, x) in [(0usize, 0usize, 0usize), (1, 0, 1), (3, 1, 1)] {
                let u = ((col * 2 + x) as f64 + 0.5) / side - 0.5;
                let w = ((row * 2 + y) as f64 + 0.5) / side - 0.5;
                // The identity camera of view 0: direction (u/F, w/F, 1), moment 0.
                let d0 = [u / REFERENCE_FOCAL, w / REFERENCE_FOCAL, 1.0];
                // View 1: R (u/f, w/f, 1) = (1, w/f, -u/f).
                let d1 = [1.0, w / f, -u / f];
                for (view, d, centre) in [(0usize, d0, [0.0; 3]), (1, d1, [1.0, 2.0, 3.0])] {
                    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    let d = d.map(|x| x / n);
                    let m = [
                        centre[1] * d[2] - centre[2] * d[1],
                        centre[2] * d[0] - centre[0] * d[2],
                        centre[0] * d[1] - centre[1] * d[0],
                    ];
                    let at = ((view * 4 + token) * 4 + pixel) * 6;
                    for (i, want) in d.iter().chain(&m).enumerate() {
                        let got = f64::from(rays[at + i]);
                        assert!(
                            (got - want).abs() < 1e-5,
                            "view {view} token {token} pixel {pixel} value {i}: {got} vs {want}"
                        );
                    }
                }
            }
        }
    }
}
