//! Bundle adjustment of corners tracked from frame 0: every corner is a point on its frame-0
//! ray at an unknown inverse depth, every later frame a rigid motion from frame 0, and
//! Levenberg-Marquardt minimises the Huber-robust reprojection error of all tracked corners in
//! all later frames at once. Sharing the structure between frames is what pins down the
//! translation directions of short baselines and makes the translation lengths of all frames
//! consistent (one overall scale stays free; the damping holds it).

use nalgebra::{DMatrix, DVector, Matrix2x3, Matrix3, Rotation3, Vector2, Vector3};

/// Points closer than this (in the bundle's length unit) to a camera's plane do not project.
const MIN_DEPTH: f64 = 1e-9;

/// One tracked corner seen in a later frame.
#[derive(Debug, Clone, Copy)]
pub struct Observation {
    /// Index of the frame-0 corner.
    pub point: usize,
    /// Frame it is seen in (at least 1).
    pub frame: usize,
    /// Normalised image position in that frame.
    pub position: Vector2<f64>,
}

/// Which unknowns an adjustment may move.
#[derive(Debug, Clone)]
pub struct Free {
    /// Per frame (frame 0 is never moved).
    pub frames: Vec<bool>,
    /// Whether the inverse depths move.
    pub points: bool,
}

/// The unknowns: world-to-camera motions from frame 0 and inverse depths of frame-0 corners.
#[derive(Debug, Clone)]
pub struct Bundle {
    /// `(x, y, 1)` of each corner in frame 0.
    pub rays: Vec<Vector3<f64>>,
    /// Inverse depth of each corner along its ray (non-positive: not yet known).
    pub inverse_depths: Vec<f64>,
    /// Rotation from frame 0 to each frame (frame 0: identity).
    pub rotations: Vec<Matrix3<f64>>,
    /// Translation from frame 0 to each frame (frame 0: zero).
    pub translations: Vec<Vector3<f64>>,
}

/// Where each free unknown of an adjustment sits in its parameter vector.
struct Layout {
    /// Offset of each frame's rotation increment and translation (six values), when free.
    frames: Vec<Option<usize>>,
    /// Offset of the first inverse depth.
    points_at: usize,
    /// Whether the inverse depths are free.
    points: bool,
    /// Number of free unknowns.
    size: usize,
}

impl Layout {
    /// The layout of `free`'s unknowns for `frames` frames and `points` corners.
    fn new(free: &Free, frames: usize, points: usize) -> Self {
        let mut offsets = vec![None; frames];
        let mut size = 0;
        for (frame, offset) in offsets.iter_mut().enumerate().skip(1) {
            if free.frames[frame] {
                *offset = Some(size);
                size += 6;
            }
        }
        let points_at = size;
        if free.points {
            size += points;
        }
        Self {
            frames: offsets,
            points_at,
            points: free.points,
            size,
        }
    }
}

/// Huber loss of a residual of norm `s` with threshold `delta`.
fn huber(s: f64, delta: f64) -> f64 {
    if s <= delta {
        0.5 * s * s
    } else {
        delta * (s - 0.5 * delta)
    }
}

impl Bundle {
    /// The point of corner `point` in the camera of `frame`, split into the rotated
    /// frame-0 point `q` and the full point `q + t`.
    fn in_camera(&self, point: usize, frame: usize) -> (Vector3<f64>, Vector3<f64>) {
        let q = self.rotations[frame] * self.rays[point] / self.inverse_depths[point];
        (q, q + self.translations[frame])
    }

    /// Reprojection residual of one observation, or `None` when the point is not in front of
    /// both cameras.
    pub fn residual(&self, observation: &Observation) -> Option<Vector2<f64>> {
        if self.inverse_depths[observation.point] <= 0.0 {
            return None;
        }
        let (_, x) = self.in_camera(observation.point, observation.frame);
        (x.z > MIN_DEPTH).then(|| Vector2::new(x.x / x.z, x.y / x.z) - observation.position)
    }

    /// Robust cost over `observations`; one that does not project costs as much as a residual
    /// of norm 1 (a whole field of view off).
    pub fn cost(&self, observations: &[Observation], delta: f64) -> f64 {
        observations
            .iter()
            .map(|o| huber(self.residual(o).map_or(1.0, |r| r.norm()), delta))
            .sum()
    }

    /// Levenberg-Marquardt on the Huber cost (iteratively reweighted) over the free unknowns;
    /// returns the final cost.
    pub fn adjust(
        &mut self,
        observations: &[Observation],
        free: &Free,
        delta: f64,
        iterations: usize,
    ) -> f64 {
        let layout = Layout::new(free, self.rotations.len(), self.rays.len());
        let mut current = self.cost(observations, delta);
        if layout.size == 0 {
            return current;
        }
        let mut damping = 1e-4;
        for _ in 0..iterations {
            let (h, g) = self.normal_equations(observations, &layout, delta);
            let floor = 1e-12 * h.diagonal().max().max(1e-300);
            let mut improved = false;
            for _ in 0..10 {
                let mut damped = h.clone();
                for k in 0..layout.size {
                    damped[(k, k)] += damping * h[(k, k)] + floor;
                }
                let Some(step) = damped.cholesky().map(|c| c.solve(&(-&g))) else {
                    damping *= 10.0;
                    continue;
                };
                let next = self.stepped(&step, &layout);
                let cost = next.cost(observations, delta);
                if cost < current {
                    let gain = (current - cost) / current.max(1e-300);
                    (*self, current) = (next, cost);
                    damping = (damping / 10.0).max(1e-9);
                    improved = gain > 1e-10;
                    break;
                }
                damping *= 10.0;
            }
            if !improved {
                break;
            }
        }
        current
    }

    /// The Gauss-Newton system `(JᵀWJ, JᵀWr)` of the Huber-weighted residuals over `layout`.
    fn normal_equations(
        &self,
        observations: &[Observation],
        layout: &Layout,
        delta: f64,
    ) -> (DMatrix<f64>, DVector<f64>) {
        let mut h = DMatrix::<f64>::zeros(layout.size, layout.size);
        let mut g = DVector::<f64>::zeros(layout.size);
        for o in observations {
            let Some(r) = self.residual(o) else {
                continue;
            };
            let frame_at = layout.frames[o.frame];
            let point_at = layout.points.then_some(layout.points_at + o.point);
            if frame_at.is_none() && point_at.is_none() {
                continue;
            }
            let norm = r.norm();
            let weight = if norm <= delta { 1.0 } else { delta / norm };
            let columns = self.jacobian_columns(o, frame_at, point_at);
            for &(a, ja) in &columns {
                g[a] += weight * ja.dot(&r);
                for &(b, jb) in &columns {
                    h[(a, b)] += weight * ja.dot(&jb);
                }
            }
        }
        (h, g)
    }

    /// The free columns of observation `o`'s residual Jacobian, each with its unknown's index.
    fn jacobian_columns(
        &self,
        o: &Observation,
        frame_at: Option<usize>,
        point_at: Option<usize>,
    ) -> Vec<(usize, Vector2<f64>)> {
        let (q, x) = self.in_camera(o.point, o.frame);
        let projection = Matrix2x3::new(
            1.0 / x.z,
            0.0,
            -x.x / (x.z * x.z),
            0.0,
            1.0 / x.z,
            -x.y / (x.z * x.z),
        );
        // Columns: rotation increment (3), translation (3), inverse depth (1).
        let mut columns: Vec<(usize, Vector2<f64>)> = Vec::with_capacity(7);
        if let Some(at) = frame_at {
            let d_rotation = projection * -skew(&q);
            for k in 0..3 {
                columns.push((at + k, d_rotation.column(k).into_owned()));
                columns.push((at + 3 + k, projection.column(k).into_owned()));
            }
        }
        if let Some(at) = point_at {
            columns.push((at, projection * (-q / self.inverse_depths[o.point])));
        }
        columns
    }

    /// A copy of the bundle with the free unknowns moved by `step`, laid out as in `layout`.
    fn stepped(&self, step: &DVector<f64>, layout: &Layout) -> Bundle {
        let mut next = self.clone();
        for (frame, offset) in layout.frames.iter().enumerate() {
            if let Some(at) = *offset {
                let omega = Vector3::new(step[at], step[at + 1], step[at + 2]);
                next.rotations[frame] = Rotation3::new(omega).into_inner() * self.rotations[frame];
                next.translations[frame] += Vector3::new(step[at + 3], step[at + 4], step[at + 5]);
            }
        }
        if layout.points {
            for (point, depth) in next.inverse_depths.iter_mut().enumerate() {
                if *depth > 0.0 {
                    *depth += step[layout.points_at + point];
                }
            }
        }
        next
    }

    /// Depth along its frame-0 ray of corner `point` from one observation in another frame
    /// (least squares on the cross product), with the parallax it rests on (sine of the angle
    /// between the two rays).
    pub fn triangulate(&self, observation: &Observation) -> Option<(f64, f64)> {
        let seen = Vector3::new(observation.position.x, observation.position.y, 1.0);
        let rotated = self.rotations[observation.frame] * self.rays[observation.point];
        let a = seen.cross(&rotated);
        let b = seen.cross(&self.translations[observation.frame]);
        let depth = -a.dot(&b) / a.norm_squared().max(1e-300);
        let parallax = a.norm() / (seen.norm() * rotated.norm());
        (depth.is_finite() && depth > 0.0).then_some((depth, parallax))
    }
}

/// `[v]_x`, the cross-product matrix.
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use data::rng::Stream;

    #[test]
    fn recovers_motions_and_depths_from_a_perturbed_start() {
        let mut stream = Stream::new(&[3]);
        let frames = 4;
        let rotations: Vec<Matrix3<f64>> = (0..frames)
            .map(|k| {
                Rotation3::from_euler_angles(0.0, 0.03 * k as f64, 0.01 * k as f64).into_inner()
            })
            .collect();
        let translations: Vec<Vector3<f64>> = (0..frames)
            .map(|k| Vector3::new(0.1 * k as f64, 0.01 * k as f64, 0.02 * k as f64))
            .collect();
        let points: Vec<Vector3<f64>> = (0..60)
            .map(|_| {
                Vector3::new(
                    stream.uniform_in(-2.0, 2.0),
                    stream.uniform_in(-1.5, 1.5),
                    stream.uniform_in(3.0, 8.0),
                )
            })
            .collect();
        let mut observations = Vec::new();
        for (point, p) in points.iter().enumerate() {
            for frame in 1..frames {
                let x = rotations[frame] * p + translations[frame];
                observations.push(Observation {
                    point,
                    frame,
                    position: Vector2::new(x.x / x.z, x.y / x.z),
                });
            }
        }
        let mut bundle = Bundle {
            rays: points.iter().map(|p| p / p.z).collect(),
            inverse_depths: points.iter().map(|p| 1.2 / p.z).collect(),
            rotations: rotations
                .iter()
                .map(|r| Rotation3::new(Vector3::new(0.01, -0.01, 0.0)).into_inner() * r)
                .collect(),
            translations: translations.iter().map(|t| t * 0.9).collect(),
        };
        bundle.rotations[0] = Matrix3::identity();
        let free = Free {
            frames: vec![true; frames],
            points: true,
        };
        let cost = bundle.adjust(&observations, &free, 1e-2, 100);
        assert!(cost < 1e-16, "{cost}");
        for frame in 1..frames {
            let angle = crate::geometry::rotation_angle_degrees(
                &(rotations[frame].transpose() * bundle.rotations[frame]),
            );
            assert!(angle < 1e-4, "{angle}");
            let direction = bundle.translations[frame].normalize();
            assert!(direction.dot(&translations[frame].normalize()) > 1.0 - 1e-9);
        }
        // One overall scale: every frame's translation length relative to the last one's.
        let scale = bundle.translations[3].norm() / translations[3].norm();
        let ratio = bundle.translations[1].norm() / translations[1].norm() / scale;
        assert!((ratio - 1.0).abs() < 1e-6, "{ratio}");
    }
}
