//! The pose probe's projection onto SO(3) inside the forward pass (the release's
//! `orthogonal_projection_kernel`: `R = U diag(1, 1, det(U V^T)) V^T` of `M = U S V^T`) and its
//! exact backward pass, so the probe's loss is taken on a true rotation.
//!
//! The backward pass follows from writing `M = U' S' V^T` with `U' = U D` and signed singular
//! values `S' = D S`: then `R = U' V^T` and `dR = U' Omega V^T` with the skew
//! `Omega_ij = (P_ij - P_ji) / (s'_i + s'_j)`, `P = U'^T dM V`. Its adjoint maps `dL/dR` to
//! `dL/dM = U' Z V^T`, `Z_ij = (K_ij - K_ji) / (s'_i + s'_j)`, `K = U'^T (dL/dR) V`. Division uses
//! the release's `x / (x^2 + 1e-8)` so coincident signed values do not blow up.

use nalgebra::Matrix3;

/// Added to the squared denominator, as the release's `safe_inverse`.
const SAFE_EPS: f64 = 1e-8;

/// `U' = U D`, signed singular values and `V` of `m`, the smallest singular value last.
fn signed_svd(m: &Matrix3<f64>) -> (Matrix3<f64>, [f64; 3], Matrix3<f64>) {
    let svd = m.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return (Matrix3::identity(), [1.0; 3], Matrix3::identity());
    };
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
    let mut u_sorted = Matrix3::zeros();
    let mut v_sorted = Matrix3::zeros();
    let mut values = [0.0; 3];
    let v = v_t.transpose();
    for (to, &from) in order.iter().enumerate() {
        u_sorted.set_column(to, &u.column(from));
        v_sorted.set_column(to, &v.column(from));
        values[to] = svd.singular_values[from];
    }
    if (u_sorted * v_sorted.transpose()).determinant() < 0.0 {
        u_sorted.set_column(2, &(-u_sorted.column(2)));
        values[2] = -values[2];
    }
    (u_sorted, values, v_sorted)
}

/// The rotation nearest to `m` (determinant +1).
pub fn project(m: &Matrix3<f64>) -> Matrix3<f64> {
    let (u, _, v) = signed_svd(m);
    u * v.transpose()
}

/// `dL/dM` given `dL/dR` at `R = project(m)`.
pub fn project_backward(m: &Matrix3<f64>, grad_r: &Matrix3<f64>) -> Matrix3<f64> {
    let (u, s, v) = signed_svd(m);
    let k = u.transpose() * grad_r * v;
    let mut z = Matrix3::zeros();
    for i in 0..3 {
        for j in 0..3 {
            if i != j {
                let denominator = s[i] + s[j];
                let inverse = denominator / (denominator * denominator + SAFE_EPS);
                z[(i, j)] = (k[(i, j)] - k[(j, i)]) * inverse;
            }
        }
    }
    u * z * v.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn matrices() -> Vec<Matrix3<f64>> {
        vec![
            Matrix3::new(0.9, 0.2, -0.1, 0.1, 1.2, 0.3, -0.2, 0.1, 0.7),
            // Negative determinant: the projection flips the weakest direction.
            Matrix3::new(0.5, 0.1, 0.0, -0.2, 0.4, 0.3, 0.1, 0.2, -0.9),
        ]
    }

    #[test]
    fn projection_recovers_a_rotation_from_a_noisy_one() {
        let r = nalgebra::Rotation3::from_euler_angles(0.1, -0.3, 0.7).into_inner();
        let noisy = r * 1.7 + Matrix3::from_element(0.01);
        assert!((project(&noisy) - r).norm() < 0.02);
        assert!((project(&-r).determinant() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn projections_are_rotations() {
        for m in matrices() {
            let r = project(&m);
            assert!((r.determinant() - 1.0).abs() < 1e-9);
            assert!((r * r.transpose() - Matrix3::identity()).norm() < 1e-9);
        }
    }

    #[test]
    fn the_backward_pass_matches_finite_differences() {
        let g = Matrix3::new(0.3, -0.7, 0.2, 0.5, 0.1, -0.4, -0.6, 0.8, 0.9);
        for m in matrices() {
            let analytic = project_backward(&m, &g);
            let h = 1e-6;
            for i in 0..3 {
                for j in 0..3 {
                    let mut plus = m;
                    plus[(i, j)] += h;
                    let mut minus = m;
                    minus[(i, j)] -= h;
                    let numeric =
                        (project(&plus) - project(&minus)).component_mul(&g).sum() / (2.0 * h);
                    // The safe inverse biases the result by about 1e-8 / (s_i + s_j)^2
                    // relative, visible where a negative determinant brings two signed
                    // singular values close.
                    assert!(
                        (numeric - analytic[(i, j)]).abs() < 1e-5 * (1.0 + analytic[(i, j)].abs()),
                        "({i},{j}): {numeric} vs {}",
                        analytic[(i, j)]
                    );
                }
            }
        }
    }
}
