//! Photometric augmentation of PoseEnc's input: colour jitter and Gaussian blur as the authors'
//! release computes them with dm_pix (additive brightness, per-channel-mean contrast, HSV
//! saturation and hue, no clipping between the ops and one clip at the end; blur on the
//! `[-1, 1]` image with zero padding). Each operation is a plain function of its parameters so
//! `release-ops` fixtures can check it alone.

use data::Image;
use data::rng::Stream;
use settings::objective::AugmentConfig;

/// The four jitter operations, applied in a random order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JitterOp {
    /// Add a constant to every channel.
    Brightness,
    /// Scale the distance from each channel's spatial mean.
    Contrast,
    /// Scale the HSV saturation.
    Saturation,
    /// Shift the HSV hue.
    Hue,
}

/// Drawn colour-jitter parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorJitter {
    /// Added to every channel (in `[0, 1]` units), in `[-b, b]`.
    pub brightness: f32,
    /// Contrast factor in `[1 - c, 1 + c]`.
    pub contrast: f32,
    /// Saturation factor in `[1 - s, 1 + s]`.
    pub saturation: f32,
    /// Hue shift in `[-h, h]` (fraction of a turn).
    pub hue: f32,
    /// Order of application.
    pub order: [JitterOp; 4],
}

/// Parameters drawn for one pair.
#[derive(Debug, Clone, PartialEq)]
pub struct Augmentation {
    /// Colour jitter, when drawn.
    pub jitter: Option<ColorJitter>,
    /// Blur sigma, when drawn.
    pub blur_sigma: Option<f32>,
    /// Blur kernel side.
    pub blur_kernel: usize,
}

/// Draws the augmentation of one sample from its settings.
pub trait AugmentDraw {
    /// Draws one pair's parameters; always consumes the same number of values from `stream`,
    /// so later draws do not shift with earlier outcomes.
    fn draw(&self, stream: &mut Stream) -> Augmentation;
}

impl AugmentDraw for AugmentConfig {
    fn draw(&self, stream: &mut Stream) -> Augmentation {
        let apply_jitter = stream.bernoulli(self.jitter_probability);
        let brightness = stream.uniform_in(-self.brightness, self.brightness) as f32;
        let contrast = stream.uniform_in(1.0 - self.contrast, 1.0 + self.contrast) as f32;
        let saturation = stream.uniform_in(1.0 - self.saturation, 1.0 + self.saturation) as f32;
        let hue = stream.uniform_in(-self.hue, self.hue) as f32;
        let mut order = [
            JitterOp::Brightness,
            JitterOp::Contrast,
            JitterOp::Saturation,
            JitterOp::Hue,
        ];
        for i in (1..order.len()).rev() {
            order.swap(i, stream.below(i as u64 + 1) as usize);
        }
        let apply_blur = stream.bernoulli(self.blur_probability);
        let sigma = stream.uniform_in(self.blur_sigma_min, self.blur_sigma_max) as f32;
        Augmentation {
            jitter: apply_jitter.then_some(ColorJitter {
                brightness,
                contrast,
                saturation,
                hue,
                order,
            }),
            blur_sigma: apply_blur.then_some(sigma),
            blur_kernel: self.blur_kernel,
        }
    }
}

impl Augmentation {
    /// Applies jitter then blur to a copy of `image`.
    pub fn apply(&self, image: &Image) -> Image {
        let jittered = match &self.jitter {
            Some(jitter) => jitter.apply(image),
            None => image.clone(),
        };
        match self.blur_sigma {
            Some(sigma) => gaussian_blur(&jittered, self.blur_kernel, sigma),
            None => jittered,
        }
    }
}

impl ColorJitter {
    /// The four operations in `order` on the image mapped to `[0, 1]`, unclipped in between,
    /// then `clip(2 * (y - 0.5), -1, 1)`.
    pub fn apply(&self, image: &Image) -> Image {
        let mut unit = to_unit(image);
        for op in self.order {
            match op {
                JitterOp::Brightness => adjust_brightness(&mut unit, self.brightness),
                JitterOp::Contrast => adjust_contrast(&mut unit, self.contrast),
                JitterOp::Saturation => adjust_saturation(&mut unit, self.saturation),
                JitterOp::Hue => adjust_hue(&mut unit, self.hue),
            }
        }
        from_unit(image, &unit)
    }
}

/// `(x + 1) / 2`: the `[0, 1]` values dm_pix works on.
pub fn to_unit(image: &Image) -> Vec<f32> {
    image.pixels.iter().map(|v| (v + 1.0) / 2.0).collect()
}

/// `clip(2 * (y - 0.5), -1, 1)` with `image`'s shape: the one clip of the jitter.
pub fn from_unit(image: &Image, unit: &[f32]) -> Image {
    Image {
        height: image.height,
        width: image.width,
        pixels: unit
            .iter()
            .map(|v| (2.0 * (v - 0.5)).clamp(-1.0, 1.0))
            .collect(),
    }
}

/// dm_pix `adjust_brightness`: adds `delta` to every value.
pub fn adjust_brightness(unit: &mut [f32], delta: f32) {
    unit.iter_mut().for_each(|v| *v += delta);
}

/// dm_pix `adjust_contrast`: `factor * (x - mean) + mean` with the spatial mean of each channel.
pub fn adjust_contrast(unit: &mut [f32], factor: f32) {
    let pixels = (unit.len() / 3).max(1);
    let mut sums = [0.0f64; 3];
    for rgb in unit.chunks_exact(3) {
        for (sum, v) in sums.iter_mut().zip(rgb) {
            *sum += f64::from(*v);
        }
    }
    let means = sums.map(|s| (s / pixels as f64) as f32);
    for rgb in unit.chunks_exact_mut(3) {
        for (v, mean) in rgb.iter_mut().zip(means) {
            *v = factor * (*v - mean) + mean;
        }
    }
}

/// dm_pix `adjust_saturation`: HSV saturation times `factor`, clipped to `[0, 1]`.
pub fn adjust_saturation(unit: &mut [f32], factor: f32) {
    for rgb in unit.chunks_exact_mut(3) {
        let (h, s, v) = rgb_to_hsv(rgb[0], rgb[1], rgb[2]);
        rgb.copy_from_slice(&hsv_to_rgb(h, (s * factor).clamp(0.0, 1.0), v));
    }
}

/// dm_pix `adjust_hue`: HSV hue plus `delta`, modulo one turn.
pub fn adjust_hue(unit: &mut [f32], delta: f32) {
    for rgb in unit.chunks_exact_mut(3) {
        let (h, s, v) = rgb_to_hsv(rgb[0], rgb[1], rgb[2]);
        rgb.copy_from_slice(&hsv_to_rgb(floor_mod_one(h + delta), s, v));
    }
}

/// `x % 1.0` with the sign of the divisor, as numpy and jax compute it.
fn floor_mod_one(x: f32) -> f32 {
    let r = x % 1.0;
    if r < 0.0 { r + 1.0 } else { r }
}

/// dm_pix's RGB to HSV, including its behaviour outside `[0, 1]` (values are not clipped
/// between jitter ops, so inputs can leave the range).
fn rgb_to_hsv(r: f32, g: f32, b: f32) -> (f32, f32, f32) {
    let value = r.max(g).max(b);
    let minimum = r.min(g).min(b);
    let range = value - minimum;
    let saturation = if value > 0.0 { range / value } else { 0.0 };
    if range <= 0.0 {
        return (0.0, saturation, value);
    }
    let norm = 1.0 / (6.0 * range);
    let hue = if value == r {
        norm * (g - b)
    } else if value == g {
        norm * (b - r) + 2.0 / 6.0
    } else {
        norm * (r - g) + 4.0 / 6.0
    };
    (if hue < 0.0 { hue + 1.0 } else { hue }, saturation, value)
}

/// dm_pix's HSV to RGB (piecewise-linear hue ramps).
fn hsv_to_rgb(h: f32, s: f32, v: f32) -> [f32; 3] {
    let dh = floor_mod_one(h) * 6.0;
    let dr = ((dh - 3.0).abs() - 1.0).clamp(0.0, 1.0);
    let dg = (2.0 - (dh - 2.0).abs()).clamp(0.0, 1.0);
    let db = (2.0 - (dh - 4.0).abs()).clamp(0.0, 1.0);
    let one_minus_s = 1.0 - s;
    [
        v * (one_minus_s + s * dr),
        v * (one_minus_s + s * dg),
        v * (one_minus_s + s * db),
    ]
}

/// The release's normalised 1-D Gaussian: `exp(-x^2 / (2 sigma^2))` at `x = i - kernel / 2`.
fn gaussian_kernel(kernel: usize, sigma: f32) -> Vec<f32> {
    let half = (kernel / 2) as isize;
    let weights: Vec<f32> = (0..kernel as isize)
        .map(|i| {
            let x = (i - half) as f32;
            (-(x * x) / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let total: f32 = weights.iter().sum();
    weights.iter().map(|w| w / total).collect()
}

/// The release's blur: a separable Gaussian (rows, then columns) on the `[-1, 1]` image with
/// zero padding ('SAME'), then clipped to `[-1, 1]`.
pub fn gaussian_blur(image: &Image, kernel: usize, sigma: f32) -> Image {
    let (height, width) = (image.height, image.width);
    let weights = gaussian_kernel(kernel, sigma);
    let half = (kernel / 2) as isize;
    let pass = |source: &[f32], vertical: bool| -> Vec<f32> {
        let mut out = vec![0.0f32; source.len()];
        for row in 0..height {
            for col in 0..width {
                for channel in 0..3 {
                    let mut acc = 0.0f32;
                    for (k, w) in weights.iter().enumerate() {
                        let offset = k as isize - half;
                        let (r, c) = if vertical {
                            (row as isize + offset, col as isize)
                        } else {
                            (row as isize, col as isize + offset)
                        };
                        if r < 0 || c < 0 || r >= height as isize || c >= width as isize {
                            continue;
                        }
                        acc += w * source[(r as usize * width + c as usize) * 3 + channel];
                    }
                    out[(row * width + col) * 3 + channel] = acc;
                }
            }
        }
        out
    };
    let blurred = pass(&pass(&image.pixels, true), false);
    Image {
        height,
        width,
        pixels: blurred.into_iter().map(|v| v.clamp(-1.0, 1.0)).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn test_image() -> Image {
        let (height, width) = (8, 8);
        let pixels = (0..height * width * 3)
            .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
            .collect();
        Image {
            height,
            width,
            pixels,
        }
    }

    #[test]
    fn drawn_parameters_stay_in_their_ranges_with_the_right_frequencies() {
        let config = AugmentConfig::default();
        let (mut jitters, mut blurs) = (0, 0);
        let draws = 20_000;
        for sample in 0..draws {
            let a = config.draw(&mut Stream::new(&[1, sample]));
            if let Some(j) = &a.jitter {
                jitters += 1;
                assert!((-0.2..=0.2).contains(&j.brightness));
                assert!((0.8..=1.2).contains(&j.contrast));
                assert!((0.8..=1.2).contains(&j.saturation));
                assert!((-0.05..=0.05).contains(&j.hue));
                let mut ops = j.order.to_vec();
                ops.dedup();
                assert_eq!(ops.len(), 4);
            }
            if let Some(sigma) = a.blur_sigma {
                blurs += 1;
                assert!((0.1..=2.0).contains(&sigma));
            }
        }
        let rate = |n: i32| n as f64 / draws as f64;
        assert!((rate(jitters) - 0.9).abs() < 0.01, "{}", rate(jitters));
        assert!((rate(blurs) - 0.3).abs() < 0.01, "{}", rate(blurs));
    }

    #[test]
    fn identity_parameters_leave_the_image_unchanged() {
        let image = test_image();
        let identity = Augmentation {
            jitter: Some(ColorJitter {
                brightness: 0.0,
                contrast: 1.0,
                saturation: 1.0,
                hue: 0.0,
                order: [
                    JitterOp::Hue,
                    JitterOp::Contrast,
                    JitterOp::Brightness,
                    JitterOp::Saturation,
                ],
            }),
            blur_sigma: None,
            blur_kernel: 7,
        };
        let out = identity.apply(&image);
        for (a, b) in out.pixels.iter().zip(&image.pixels) {
            assert!((a - b).abs() < 1e-5);
        }
    }

    #[test]
    fn blur_pads_with_zeros_and_keeps_a_constant_inside() {
        let mut image = test_image();
        image.pixels.iter_mut().for_each(|v| *v = 0.5);
        let blurred = gaussian_blur(&image, 7, 1.5);
        let at = |row: usize, col: usize| blurred.pixels[(row * 8 + col) * 3];
        // Three pixels from every border the 7-tap kernel sees only the constant.
        assert!((at(3, 3) - 0.5).abs() < 1e-6 && (at(4, 4) - 0.5).abs() < 1e-6);
        // At a corner the zero padding pulls towards 0.
        assert!(at(0, 0) < 0.4, "{}", at(0, 0));
        let image = test_image();
        let spread = |p: &[f32]| {
            let mean = p.iter().sum::<f32>() / p.len() as f32;
            p.iter().map(|v| (v - mean).powi(2)).sum::<f32>()
        };
        assert!(spread(&gaussian_blur(&image, 7, 1.5).pixels) < 0.5 * spread(&image.pixels));
    }

    #[test]
    fn hsv_round_trip_and_additive_brightness() {
        for rgb in [
            [0.9f32, 0.2, 0.1],
            [0.1, 0.8, 0.3],
            [0.2, 0.3, 0.7],
            [0.5, 0.5, 0.5],
            [0.3, 0.1, 0.2],
        ] {
            let (h, s, v) = rgb_to_hsv(rgb[0], rgb[1], rgb[2]);
            let back = hsv_to_rgb(h, s, v);
            for (a, b) in back.iter().zip(rgb) {
                assert!((a - b).abs() < 1e-6, "{rgb:?} -> {back:?}");
            }
        }
        let mut unit = vec![0.5f32, 0.25, 1.0];
        adjust_brightness(&mut unit, 0.125);
        assert_eq!(unit, vec![0.625, 0.375, 1.125]);
        // A non-positive value has no saturation: dm_pix turns such pixels grey.
        let mut dark = vec![-0.1f32, -0.3, -0.2];
        adjust_hue(&mut dark, 0.02);
        assert_eq!(dark, vec![-0.1, -0.1, -0.1]);
    }
}
