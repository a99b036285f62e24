//! Sparse features for two-view geometry: Harris corners with sub-pixel refinement,
//! zero-mean unit-norm patch descriptors, and mutual-nearest matching with a ratio test.

use data::Image;

/// Harris' trace weight `k`.
const HARRIS_K: f64 = 0.04;
/// Standard deviation of the pre-smoothing applied before gradients and descriptors.
const SMOOTH_SIGMA: f64 = 1.0;
/// Standard deviation of the structure-tensor window.
const TENSOR_SIGMA: f64 = 1.5;
/// Radius of the non-maximum suppression window.
const NMS_RADIUS: usize = 2;
/// Corners weaker than this share of the strongest are dropped.
const RELATIVE_THRESHOLD: f64 = 1e-5;
/// Radius of the square descriptor patch.
pub const PATCH_RADIUS: usize = 7;
/// Patches flatter than this standard deviation (intensities in `[0, 1]`) have no descriptor.
const MIN_PATCH_STD: f64 = 0.01;
/// Best match distance must be below this share of the second best.
const RATIO: f64 = 0.9;
/// Radius of the square window Lucas-Kanade aligns.
const TRACK_RADIUS: isize = 7;
/// Most Gauss-Newton steps of one alignment.
const TRACK_ITERATIONS: usize = 30;
/// An alignment has converged when its step is shorter than this, pixels.
const TRACK_TOLERANCE: f64 = 1e-3;
/// Farthest an alignment may move a matched corner, pixels.
const TRACK_REACH: f64 = 2.0;
/// Least normalised correlation of an aligned window with the frame-0 window.
const TRACK_MIN_NCC: f64 = 0.9;

/// A grayscale plane with intensities in `[0, 1]`.
#[derive(Debug, Clone)]
pub struct Plane {
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// Row-major values.
    pub values: Vec<f64>,
}

impl Plane {
    /// Luma of a `[-1, 1]` RGB image.
    pub fn from_image(image: &Image) -> Self {
        let values = image
            .pixels
            .chunks_exact(3)
            .map(|p| {
                let [r, g, b] = [p[0], p[1], p[2]].map(|v| (f64::from(v) + 1.0) / 2.0);
                0.299 * r + 0.587 * g + 0.114 * b
            })
            .collect();
        Self {
            height: image.height,
            width: image.width,
            values,
        }
    }

    /// The pre-smoothed luma that corners, descriptors and alignment work on.
    pub fn smoothed(image: &Image) -> Self {
        Self::from_image(image).blurred(SMOOTH_SIGMA)
    }

    /// Bilinear sample at column `x`, row `y` (clamped borders).
    fn sample(&self, y: f64, x: f64) -> f64 {
        let (y0, x0) = (y.floor(), x.floor());
        let (fy, fx) = (y - y0, x - x0);
        let (y0, x0) = (y0 as isize, x0 as isize);
        (1.0 - fy) * ((1.0 - fx) * self.at(y0, x0) + fx * self.at(y0, x0 + 1))
            + fy * ((1.0 - fx) * self.at(y0 + 1, x0) + fx * self.at(y0 + 1, x0 + 1))
    }

    fn at(&self, y: isize, x: isize) -> f64 {
        let y = y.clamp(0, self.height as isize - 1) as usize;
        let x = x.clamp(0, self.width as isize - 1) as usize;
        self.values[y * self.width + x]
    }

    /// Separable Gaussian blur with clamped borders.
    fn blurred(&self, sigma: f64) -> Self {
        let radius = (3.0 * sigma).ceil() as isize;
        let kernel: Vec<f64> = (-radius..=radius)
            .map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp())
            .collect();
        let sum: f64 = kernel.iter().sum();
        let kernel: Vec<f64> = kernel.iter().map(|k| k / sum).collect();
        let pass = |plane: &Plane, horizontal: bool| -> Plane {
            let mut values = Vec::with_capacity(plane.values.len());
            for y in 0..plane.height as isize {
                for x in 0..plane.width as isize {
                    values.push(
                        (-radius..=radius)
                            .zip(&kernel)
                            .map(|(d, k)| {
                                k * if horizontal {
                                    plane.at(y, x + d)
                                } else {
                                    plane.at(y + d, x)
                                }
                            })
                            .sum(),
                    );
                }
            }
            Plane {
                height: plane.height,
                width: plane.width,
                values,
            }
        };
        pass(&pass(self, true), false)
    }

    fn map(&self, f: impl Fn(isize, isize) -> f64) -> Self {
        let values = (0..self.height as isize)
            .flat_map(|y| (0..self.width as isize).map(move |x| (y, x)))
            .map(|(y, x)| f(y, x))
            .collect();
        Self {
            height: self.height,
            width: self.width,
            values,
        }
    }
}

/// A corner: sub-pixel position (column, row) and its descriptor.
#[derive(Debug, Clone)]
pub struct Feature {
    /// Column, in pixels (pixel centres at integer values).
    pub x: f64,
    /// Row, in pixels.
    pub y: f64,
    /// Zero-mean unit-norm patch.
    pub descriptor: Vec<f64>,
}

/// The strongest `max_corners` Harris corners of `image` that have a descriptor.
pub fn detect(image: &Image, max_corners: usize) -> Vec<Feature> {
    let smooth = Plane::smoothed(image);
    let gx = smooth.map(|y, x| (smooth.at(y, x + 1) - smooth.at(y, x - 1)) / 2.0);
    let gy = smooth.map(|y, x| (smooth.at(y + 1, x) - smooth.at(y - 1, x)) / 2.0);
    let xx = gx.map(|y, x| gx.at(y, x).powi(2)).blurred(TENSOR_SIGMA);
    let yy = gy.map(|y, x| gy.at(y, x).powi(2)).blurred(TENSOR_SIGMA);
    let xy = gx
        .map(|y, x| gx.at(y, x) * gy.at(y, x))
        .blurred(TENSOR_SIGMA);
    let response = xx.map(|y, x| {
        let (a, b, c) = (xx.at(y, x), yy.at(y, x), xy.at(y, x));
        a * b - c * c - HARRIS_K * (a + b).powi(2)
    });
    let strongest = response.values.iter().copied().fold(0.0, f64::max);
    let border = PATCH_RADIUS.max(NMS_RADIUS) + 1;
    let mut corners = Vec::new();
    for y in border..smooth.height.saturating_sub(border) {
        for x in border..smooth.width.saturating_sub(border) {
            let value = response.values[y * smooth.width + x];
            if value <= RELATIVE_THRESHOLD * strongest {
                continue;
            }
            let r = NMS_RADIUS as isize;
            let is_max = (-r..=r).all(|dy| {
                (-r..=r).all(|dx| {
                    (dy == 0 && dx == 0) || response.at(y as isize + dy, x as isize + dx) < value
                })
            });
            if is_max {
                corners.push((value, y, x));
            }
        }
    }
    corners.sort_by(|a, b| b.0.total_cmp(&a.0));
    corners
        .into_iter()
        .filter_map(|(_, y, x)| {
            let (yi, xi) = (y as isize, x as isize);
            let offset = |minus: f64, centre: f64, plus: f64| {
                let curvature = minus - 2.0 * centre + plus;
                if curvature < 0.0 {
                    (0.5 * (minus - plus) / curvature).clamp(-0.5, 0.5)
                } else {
                    0.0
                }
            };
            let centre = response.at(yi, xi);
            let dx = offset(response.at(yi, xi - 1), centre, response.at(yi, xi + 1));
            let dy = offset(response.at(yi - 1, xi), centre, response.at(yi + 1, xi));
            descriptor(&smooth, y, x).map(|descriptor| Feature {
                x: x as f64 + dx,
                y: y as f64 + dy,
                descriptor,
            })
        })
        .take(max_corners)
        .collect()
}

/// The zero-mean unit-norm patch around `(y, x)`, or `None` for a flat patch.
fn descriptor(plane: &Plane, y: usize, x: usize) -> Option<Vec<f64>> {
    let r = PATCH_RADIUS as isize;
    let mut patch: Vec<f64> = (-r..=r)
        .flat_map(|dy| (-r..=r).map(move |dx| (dy, dx)))
        .map(|(dy, dx)| plane.at(y as isize + dy, x as isize + dx))
        .collect();
    let mean = patch.iter().sum::<f64>() / patch.len() as f64;
    patch.iter_mut().for_each(|v| *v -= mean);
    let norm = patch.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm / (patch.len() as f64).sqrt() < MIN_PATCH_STD {
        return None;
    }
    patch.iter_mut().for_each(|v| *v /= norm);
    Some(patch)
}

/// Best and second-best correlation of `query` among the `candidates` within `max_shift`
/// pixels: `(index, best, second)`.
fn nearest(query: &Feature, candidates: &[Feature], max_shift: f64) -> Option<(usize, f64, f64)> {
    let mut best = (usize::MAX, f64::MIN, f64::MIN);
    for (index, c) in candidates.iter().enumerate() {
        if (c.x - query.x).abs() > max_shift || (c.y - query.y).abs() > max_shift {
            continue;
        }
        let score: f64 = query
            .descriptor
            .iter()
            .zip(&c.descriptor)
            .map(|(a, b)| a * b)
            .sum();
        if score > best.1 {
            best = (index, score, best.1);
        } else if score > best.2 {
            best.2 = score;
        }
    }
    (best.0 != usize::MAX).then_some(best)
}

/// Index pairs `(i in a, j in b)` at most `max_shift` pixels apart on each axis that are each
/// other's nearest neighbour and pass the ratio test on descriptor distance `sqrt(2 - 2 ncc)`.
/// Frames of one video move little, and the window keeps repeated textures from matching
/// across the image.
pub fn match_features(a: &[Feature], b: &[Feature], max_shift: f64) -> Vec<(usize, usize)> {
    let distance = |ncc: f64| (2.0 - 2.0 * ncc).max(0.0).sqrt();
    let backward: Vec<Option<usize>> = b
        .iter()
        .map(|f| nearest(f, a, max_shift).map(|n| n.0))
        .collect();
    a.iter()
        .enumerate()
        .filter_map(|(i, f)| {
            let (j, best, second) = nearest(f, b, max_shift)?;
            let unique = second == f64::MIN || distance(best) < RATIO * distance(second);
            (unique && backward[j] == Some(i)).then_some((i, j))
        })
        .collect()
}

/// Sub-pixel position in `target` of the window of `template` centred on `(x, y)`: translation-
/// only Lucas-Kanade (inverse compositional) started from `guess`, on the smoothed luma. The
/// renders are Lambertian under a fixed light, so a surface point keeps its brightness across
/// views and aligning against frame 0's own window (not the previous frame's) does not drift.
/// `None` when the alignment does not converge, strays more than [`TRACK_REACH`] pixels from
/// the guess or ends on a window that correlates poorly with the template's.
pub fn align(
    template: &Plane,
    x: f64,
    y: f64,
    target: &Plane,
    guess: (f64, f64),
) -> Option<(f64, f64)> {
    let offsets: Vec<(f64, f64)> = (-TRACK_RADIUS..=TRACK_RADIUS)
        .flat_map(|dy| (-TRACK_RADIUS..=TRACK_RADIUS).map(move |dx| (dy as f64, dx as f64)))
        .collect();
    let values: Vec<f64> = offsets
        .iter()
        .map(|(dy, dx)| template.sample(y + dy, x + dx))
        .collect();
    let gradients: Vec<(f64, f64)> = offsets
        .iter()
        .map(|(dy, dx)| {
            let (py, px) = (y + dy, x + dx);
            (
                (template.sample(py, px + 1.0) - template.sample(py, px - 1.0)) / 2.0,
                (template.sample(py + 1.0, px) - template.sample(py - 1.0, px)) / 2.0,
            )
        })
        .collect();
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for (gx, gy) in &gradients {
        a += gx * gx;
        b += gx * gy;
        c += gy * gy;
    }
    let det = a * c - b * b;
    if det <= 1e-12 {
        return None;
    }
    let (mut u, mut v) = guess;
    let mut converged = false;
    for _ in 0..TRACK_ITERATIONS {
        let (mut rx, mut ry) = (0.0, 0.0);
        for (((dy, dx), t), (gx, gy)) in offsets.iter().zip(&values).zip(&gradients) {
            let error = target.sample(v + dy, u + dx) - t;
            rx += gx * error;
            ry += gy * error;
        }
        let step_x = (c * rx - b * ry) / det;
        let step_y = (a * ry - b * rx) / det;
        u -= step_x;
        v -= step_y;
        if (u - guess.0).abs() > TRACK_REACH || (v - guess.1).abs() > TRACK_REACH {
            return None;
        }
        if step_x.hypot(step_y) < TRACK_TOLERANCE {
            converged = true;
            break;
        }
    }
    let warped: Vec<f64> = offsets
        .iter()
        .map(|(dy, dx)| target.sample(v + dy, u + dx))
        .collect();
    (converged && correlation(&values, &warped) >= TRACK_MIN_NCC).then_some((u, v))
}

/// Normalised cross-correlation of two equally long windows (0 when either is flat).
fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        ab += (x - ma) * (y - mb);
        aa += (x - ma) * (x - ma);
        bb += (y - mb) * (y - mb);
    }
    if aa <= 0.0 || bb <= 0.0 {
        0.0
    } else {
        ab / (aa * bb).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blobs(side: usize, shift: f64) -> Image {
        Image {
            height: side,
            width: side,
            pixels: (0..side * side * 3)
                .map(|i| {
                    let (y, x) = ((i / 3) / side, (i / 3) % side);
                    let (y, x) = (y as f64, x as f64 - shift);
                    ((0.37 * x).sin() * (0.29 * y).cos() + (0.11 * x * y / side as f64).sin())
                        as f32
                        * 0.8
                })
                .collect(),
        }
    }

    #[test]
    fn shifted_image_matches_with_the_shift() {
        let a = detect(&blobs(64, 0.0), 200);
        let b = detect(&blobs(64, 3.0), 200);
        assert!(a.len() > 20, "{}", a.len());
        let matches = match_features(&a, &b, 16.0);
        assert!(matches.len() > 10, "{}", matches.len());
        let good = matches
            .iter()
            .filter(|&&(i, j)| {
                ((b[j].x - a[i].x) - 3.0).abs() < 1.0 && (b[j].y - a[i].y).abs() < 1.0
            })
            .count();
        assert!(
            good * 10 >= matches.len() * 8,
            "{good} of {}",
            matches.len()
        );
    }
}
