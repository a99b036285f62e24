//! Two-view relative pose from matched normalised image points: the normalised 8-point
//! essential matrix inside RANSAC on the Sampson error, then the decomposition whose
//! triangulated points lie in front of both cameras.
//!
//! Convention: `x2^T E x1 = 0` with `X2 = R X1 + t`, i.e. `(R, t)` maps camera 1 to camera 2.

use data::rng::Stream;
use nalgebra::{Matrix3, SMatrix, Vector2, Vector3};

/// Minimal sample of the 8-point algorithm.
const SAMPLE: usize = 8;

/// A relative pose with its support.
#[derive(Debug, Clone)]
pub struct RelativePose {
    /// Rotation from camera 1 to camera 2.
    pub rotation: Matrix3<f64>,
    /// Unit translation direction from camera 1 to camera 2.
    pub direction: Vector3<f64>,
    /// Indices of the inlier correspondences.
    pub inliers: Vec<usize>,
    /// Depth in camera 1 of each inlier (same order), in units of the baseline, where it
    /// triangulates in front of both cameras (points near infinity may not, through noise).
    pub depths: Vec<Option<f64>>,
}

/// Similarity that moves points to zero mean and mean distance `sqrt(2)` (Hartley).
fn normaliser(points: &[Vector2<f64>]) -> Matrix3<f64> {
    let n = points.len().max(1) as f64;
    let mean = points.iter().fold(Vector2::zeros(), |a, p| a + p) / n;
    let spread = points.iter().map(|p| (p - mean).norm()).sum::<f64>() / n;
    let s = if spread > 0.0 {
        2f64.sqrt() / spread
    } else {
        1.0
    };
    Matrix3::new(s, 0.0, -s * mean.x, 0.0, s, -s * mean.y, 0.0, 0.0, 1.0)
}

fn homogeneous(p: &Vector2<f64>) -> Vector3<f64> {
    Vector3::new(p.x, p.y, 1.0)
}

/// The essential matrix through the chosen correspondences (at least 8), projected to have
/// two equal singular values and a zero one.
fn eight_point(x1: &[Vector2<f64>], x2: &[Vector2<f64>], chosen: &[usize]) -> Option<Matrix3<f64>> {
    let p1: Vec<Vector2<f64>> = chosen.iter().map(|&i| x1[i]).collect();
    let p2: Vec<Vector2<f64>> = chosen.iter().map(|&i| x2[i]).collect();
    let (t1, t2) = (normaliser(&p1), normaliser(&p2));
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for (a, b) in p1.iter().zip(&p2) {
        let a = t1 * homogeneous(a);
        let b = t2 * homogeneous(b);
        let row = SMatrix::<f64, 9, 1>::from_column_slice(&[
            b.x * a.x,
            b.x * a.y,
            b.x,
            b.y * a.x,
            b.y * a.y,
            b.y,
            a.x,
            a.y,
            1.0,
        ]);
        ata += row * row.transpose();
    }
    let eigen = ata.symmetric_eigen();
    let smallest = eigen.eigenvalues.imin();
    let e = eigen.eigenvectors.column(smallest);
    let f = Matrix3::new(e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7], e[8]);
    let e = t2.transpose() * f * t1;
    let svd = e.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let s = (svd.singular_values[0] + svd.singular_values[1]) / 2.0;
    Some(u * Matrix3::from_diagonal(&Vector3::new(s, s, 0.0)) * v_t)
}

/// First-order geometric (Sampson) error of one correspondence, in squared normalised units.
fn sampson(e: &Matrix3<f64>, a: &Vector2<f64>, b: &Vector2<f64>) -> f64 {
    let (a, b) = (homogeneous(a), homogeneous(b));
    let ea = e * a;
    let etb = e.transpose() * b;
    let residual = b.dot(&ea);
    residual * residual / (ea.x * ea.x + ea.y * ea.y + etb.x * etb.x + etb.y * etb.y).max(1e-300)
}

fn inliers(
    e: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    threshold: f64,
) -> Vec<usize> {
    (0..x1.len())
        .filter(|&i| sampson(e, &x1[i], &x2[i]) < threshold)
        .collect()
}

/// Depths `(z1, z2)` with `z2 x2 = z1 R x1 + t` in the least-squares sense.
fn triangulate(
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    a: &Vector2<f64>,
    b: &Vector2<f64>,
) -> Option<(f64, f64)> {
    let ra = r * homogeneous(a);
    let hb = homogeneous(b);
    // [ra, -hb] [z1, z2]^T = -t
    let (m11, m12, m22) = (ra.dot(&ra), -ra.dot(&hb), hb.dot(&hb));
    let (r1, r2) = (-ra.dot(t), hb.dot(t));
    let det = m11 * m22 - m12 * m12;
    if det.abs() < 1e-12 {
        return None;
    }
    Some(((m22 * r1 - m12 * r2) / det, (m11 * r2 - m12 * r1) / det))
}

/// The decomposition of `e` that puts the most inliers in front of both cameras.
fn decompose(
    e: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inliers: &[usize],
) -> Option<RelativePose> {
    let svd = e.svd(true, true);
    let (mut u, mut v_t) = (svd.u?, svd.v_t?);
    if u.determinant() < 0.0 {
        u = -u;
    }
    if v_t.determinant() < 0.0 {
        v_t = -v_t;
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let t = u.column(2).into_owned();
    let candidates = [
        (u * w * v_t, t),
        (u * w * v_t, -t),
        (u * w.transpose() * v_t, t),
        (u * w.transpose() * v_t, -t),
    ];
    candidates
        .iter()
        .map(|(r, t)| {
            let depths: Vec<Option<f64>> = inliers
                .iter()
                .map(|&i| {
                    triangulate(r, t, &x1[i], &x2[i])
                        .filter(|(z1, z2)| *z1 > 0.0 && *z2 > 0.0)
                        .map(|(z1, _)| z1)
                })
                .collect();
            let front = depths.iter().flatten().count();
            (front, r, t, depths)
        })
        .max_by_key(|c| c.0)
        .map(|(_, r, t, depths)| RelativePose {
            rotation: *r,
            direction: t.normalize(),
            inliers: inliers.to_vec(),
            depths,
        })
}

/// RANSAC settings.
#[derive(Debug, Clone, Copy)]
pub struct Ransac {
    /// Hypotheses drawn.
    pub iterations: usize,
    /// Sampson threshold, squared normalised units.
    pub threshold: f64,
    /// Seed of the sample draws.
    pub seed: u64,
}

/// Robust relative pose from correspondences `x1[i] <-> x2[i]` in normalised coordinates.
pub fn relative_pose(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    ransac: &Ransac,
) -> Option<RelativePose> {
    let n = x1.len();
    if n < SAMPLE {
        return None;
    }
    let mut stream = Stream::new(&[ransac.seed, n as u64]);
    let mut best: Option<(Matrix3<f64>, Vec<usize>)> = None;
    for _ in 0..ransac.iterations {
        let mut chosen: Vec<usize> = Vec::with_capacity(SAMPLE);
        while chosen.len() < SAMPLE {
            let i = stream.below(n as u64) as usize;
            if !chosen.contains(&i) {
                chosen.push(i);
            }
        }
        if let Some(e) = eight_point(x1, x2, &chosen) {
            let support = inliers(&e, x1, x2, ransac.threshold);
            if best.as_ref().is_none_or(|b| support.len() > b.1.len()) {
                best = Some((e, support));
            }
        }
    }
    let (mut e, mut support) = best.filter(|b| b.1.len() >= SAMPLE)?;
    // Refit on the inliers while that does not lose support (a linear refit can, when the
    // baseline is short and the problem close to degenerate).
    for _ in 0..3 {
        let Some(refit) = eight_point(x1, x2, &support) else {
            break;
        };
        let refit_support = inliers(&refit, x1, x2, ransac.threshold);
        if refit_support.len() < support.len() {
            break;
        }
        (e, support) = (refit, refit_support);
    }
    let coarse = decompose(&e, x1, x2, &support)?;
    let (rotation, direction) = refine(&coarse.rotation, &coarse.direction, x1, x2, &support);
    let e = skew(&direction) * rotation;
    let refined = decompose(&e, x1, x2, &support)?;
    // Keep the refined motion only if it still has the cheirality of the coarse one.
    Some(if refined.direction.dot(&direction) > 0.0 {
        refined
    } else {
        coarse
    })
}

/// `[v]_x`, the cross-product matrix.
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Signed Sampson residuals of `E = [t]_x R` over `chosen`.
fn residuals(
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    chosen: &[usize],
) -> Vec<f64> {
    let e = skew(t) * r;
    chosen
        .iter()
        .map(|&i| {
            let (a, b) = (homogeneous(&x1[i]), homogeneous(&x2[i]));
            let ea = e * a;
            let etb = e.transpose() * b;
            b.dot(&ea)
                / (ea.x * ea.x + ea.y * ea.y + etb.x * etb.x + etb.y * etb.y)
                    .max(1e-300)
                    .sqrt()
        })
        .collect()
}

/// Levenberg-Marquardt on the Sampson error over the five degrees of freedom of a calibrated
/// relative pose (a rotation increment and a move of the direction on the sphere): the linear
/// 8-point fit is noisy when the baseline is short, and this is what makes translation
/// directions accurate.
fn refine(
    rotation: &Matrix3<f64>,
    direction: &Vector3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    chosen: &[usize],
) -> (Matrix3<f64>, Vector3<f64>) {
    let apply = |r: &Matrix3<f64>, t: &Vector3<f64>, step: &SMatrix<f64, 5, 1>| {
        let helper = if t.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let b1 = t.cross(&helper).normalize();
        let b2 = t.cross(&b1);
        let increment =
            nalgebra::Rotation3::new(Vector3::new(step[0], step[1], step[2])).into_inner();
        (increment * r, (t + b1 * step[3] + b2 * step[4]).normalize())
    };
    let cost = |r: &Matrix3<f64>, t: &Vector3<f64>| {
        residuals(r, t, x1, x2, chosen)
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
    };
    let (mut r, mut t) = (*rotation, *direction);
    let mut current = cost(&r, &t);
    let mut damping = 1e-3;
    for _ in 0..30 {
        let base = residuals(&r, &t, x1, x2, chosen);
        let h = 1e-7;
        let columns: Vec<Vec<f64>> = (0..5)
            .map(|k| {
                let mut step = SMatrix::<f64, 5, 1>::zeros();
                step[k] = h;
                let (rk, tk) = apply(&r, &t, &step);
                residuals(&rk, &tk, x1, x2, chosen)
                    .iter()
                    .zip(&base)
                    .map(|(a, b)| (a - b) / h)
                    .collect()
            })
            .collect();
        let mut jtj = SMatrix::<f64, 5, 5>::zeros();
        let mut jtr = SMatrix::<f64, 5, 1>::zeros();
        for row in 0..base.len() {
            for a in 0..5 {
                jtr[a] += columns[a][row] * base[row];
                for b in 0..5 {
                    jtj[(a, b)] += columns[a][row] * columns[b][row];
                }
            }
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut damped = jtj;
            for k in 0..5 {
                damped[(k, k)] *= 1.0 + damping;
            }
            let Some(step) = damped.lu().solve(&(-jtr)) else {
                break;
            };
            let (rn, tn) = apply(&r, &t, &step);
            let next = cost(&rn, &tn);
            if next < current {
                (r, t, current) = (rn, tn, next);
                damping = (damping / 10.0).max(1e-9);
                improved = true;
                break;
            }
            damping *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (r, t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn recovers_a_known_motion_despite_outliers() {
        let r = Rotation3::from_euler_angles(0.05, 0.2, -0.03).into_inner();
        let t = Vector3::new(0.3, -0.05, 0.1);
        let mut stream = Stream::new(&[7]);
        let mut x1 = Vec::new();
        let mut x2 = Vec::new();
        let mut depths = Vec::new();
        for k in 0..120 {
            let p = Vector3::new(
                stream.uniform_in(-2.0, 2.0),
                stream.uniform_in(-1.5, 1.5),
                stream.uniform_in(3.0, 8.0),
            );
            let q = r * p + t;
            depths.push(p.z);
            x1.push(Vector2::new(p.x / p.z, p.y / p.z));
            if k % 5 == 0 {
                x2.push(Vector2::new(
                    stream.uniform_in(-0.5, 0.5),
                    stream.uniform_in(-0.5, 0.5),
                ));
            } else {
                x2.push(Vector2::new(q.x / q.z, q.y / q.z));
            }
        }
        let ransac = Ransac {
            iterations: 300,
            threshold: 1e-6,
            seed: 1,
        };
        let pose = relative_pose(&x1, &x2, &ransac).unwrap();
        let angle = crate::geometry::rotation_angle_degrees(&(r.transpose() * pose.rotation));
        assert!(angle < 0.01, "{angle}");
        assert!(
            pose.direction.dot(&t.normalize()) > 0.9999,
            "{}",
            pose.direction
        );
        assert!(pose.inliers.len() >= 90 && pose.inliers.iter().all(|i| i % 5 != 0));
        // Depths are in baseline units: the true depth divided by |t|.
        let expected = depths[pose.inliers[0]] / t.norm();
        let found = pose.depths[0].unwrap();
        assert!(
            (found - expected).abs() < 1e-3 * expected,
            "{found} vs {expected}"
        );
    }
}
