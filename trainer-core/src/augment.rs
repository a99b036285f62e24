//! Photometric augmentation of PoseEnc's input: colour jitter and Gaussian blur with
//! torchvision's semantics, applied with the same parameters to both frames of a pair.

use data::Image;
use data::rng::Stream;
use settings::objective::AugmentConfig;

/// The four jitter operations, applied in a random order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JitterOp {
    /// Multiply intensities.
    Brightness,
    /// Blend with the mean grey level.
    Contrast,
    /// Blend with the per-pixel grey level.
    Saturation,
    /// Rotate the hue.
    Hue,
}

/// Drawn colour-jitter parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorJitter {
    /// Brightness factor in `[1 - b, 1 + b]`.
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
        let brightness = stream.uniform_in(1.0 - self.brightness, 1.0 + self.brightness) as f32;
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
        let mut unit: Vec<f32> = image.pixels.iter().map(|v| (v + 1.0) * 0.5).collect();
        if let Some(jitter) = &self.jitter {
            for op in jitter.order {
                match op {
                    JitterOp::Brightness => scale_intensity(&mut unit, jitter.brightness),
                    JitterOp::Contrast => adjust_contrast(&mut unit, jitter.contrast),
                    JitterOp::Saturation => adjust_saturation(&mut unit, jitter.saturation),
                    JitterOp::Hue => rotate_hue(&mut unit, jitter.hue),
                }
            }
        }
        if let Some(sigma) = self.blur_sigma {
            unit = gaussian_blur(&unit, image.height, image.width, self.blur_kernel, sigma);
        }
        Image {
            height: image.height,
            width: image.width,
            pixels: unit.iter().map(|v| v * 2.0 - 1.0).collect(),
        }
    }
}

fn grey(rgb: &[f32]) -> f32 {
    0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
}

fn blend(value: f32, other: f32, factor: f32) -> f32 {
    (factor * value + (1.0 - factor) * other).clamp(0.0, 1.0)
}

fn scale_intensity(unit: &mut [f32], factor: f32) {
    unit.iter_mut().for_each(|v| *v = blend(*v, 0.0, factor));
}

fn adjust_contrast(unit: &mut [f32], factor: f32) {
    let pixels = unit.len() / 3;
    let mean = unit.chunks_exact(3).map(grey).sum::<f32>() / pixels.max(1) as f32;
    unit.iter_mut().for_each(|v| *v = blend(*v, mean, factor));
}

fn adjust_saturation(unit: &mut [f32], factor: f32) {
    for rgb in unit.chunks_exact_mut(3) {
        let g = grey(rgb);
        rgb.iter_mut().for_each(|v| *v = blend(*v, g, factor));
    }
}

fn rotate_hue(unit: &mut [f32], shift: f32) {
    for rgb in unit.chunks_exact_mut(3) {
        let (h, s, v) = rgb_to_hsv(rgb[0], rgb[1], rgb[2]);
        let (r, g, b) = hsv_to_rgb((h + shift).rem_euclid(1.0), s, v);
        rgb.copy_from_slice(&[r, g, b]);
    }
}

fn rgb_to_hsv(r: f32, g: f32, b: f32) -> (f32, f32, f32) {
    let max = r.max(g).max(b);
    let min = r.min(g).min(b);
    let delta = max - min;
    let s = if max > 0.0 { delta / max } else { 0.0 };
    let h = if delta == 0.0 {
        0.0
    } else if max == r {
        ((g - b) / delta).rem_euclid(6.0) / 6.0
    } else if max == g {
        ((b - r) / delta + 2.0) / 6.0
    } else {
        ((r - g) / delta + 4.0) / 6.0
    };
    (h, s, max)
}

fn hsv_to_rgb(h: f32, s: f32, v: f32) -> (f32, f32, f32) {
    let sector = (h * 6.0).floor();
    let f = h * 6.0 - sector;
    let p = v * (1.0 - s);
    let q = v * (1.0 - s * f);
    let t = v * (1.0 - s * (1.0 - f));
    match sector as i32 % 6 {
        0 => (v, t, p),
        1 => (q, v, p),
        2 => (p, v, t),
        3 => (p, q, v),
        4 => (t, p, v),
        _ => (v, p, q),
    }
}

/// Separable Gaussian blur with reflect padding (torchvision's `gaussian_blur`).
fn gaussian_blur(unit: &[f32], height: usize, width: usize, kernel: usize, sigma: f32) -> Vec<f32> {
    let half = (kernel / 2) as isize;
    let weights: Vec<f32> = (-half..=half)
        .map(|x| (-(x * x) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f32 = weights.iter().sum();
    let weights: Vec<f32> = weights.iter().map(|w| w / total).collect();
    let reflect = |i: isize, n: usize| -> usize {
        let n = n as isize;
        let mut i = i;
        while i < 0 || i >= n {
            i = if i < 0 { -i } else { 2 * (n - 1) - i };
        }
        i as usize
    };
    let pass = |source: &[f32], horizontal: bool| -> Vec<f32> {
        let mut out = vec![0.0; source.len()];
        for row in 0..height {
            for col in 0..width {
                for channel in 0..3 {
                    let mut acc = 0.0;
                    for (k, w) in weights.iter().enumerate() {
                        let offset = k as isize - half;
                        let (r, c) = if horizontal {
                            (row, reflect(col as isize + offset, width))
                        } else {
                            (reflect(row as isize + offset, height), col)
                        };
                        acc += w * source[(r * width + c) * 3 + channel];
                    }
                    out[(row * width + col) * 3 + channel] = acc;
                }
            }
        }
        out
    };
    pass(&pass(unit, true), false)
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
                assert!((0.8..=1.2).contains(&j.brightness));
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
                brightness: 1.0,
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
    fn blur_preserves_the_mean_of_a_constant_and_smooths_edges() {
        let mut image = test_image();
        image.pixels.iter_mut().for_each(|v| *v = 0.25);
        let blur = Augmentation {
            jitter: None,
            blur_sigma: Some(1.5),
            blur_kernel: 7,
        };
        assert!(
            blur.apply(&image)
                .pixels
                .iter()
                .all(|v| (v - 0.25).abs() < 1e-5)
        );
        let image = test_image();
        let spread = |p: &[f32]| {
            let mean = p.iter().sum::<f32>() / p.len() as f32;
            p.iter().map(|v| (v - mean).powi(2)).sum::<f32>()
        };
        assert!(spread(&blur.apply(&image).pixels) < 0.5 * spread(&image.pixels));
    }

    #[test]
    fn hue_round_trip_and_brightness_scale() {
        for rgb in [
            [0.9f32, 0.2, 0.1],
            [0.1, 0.8, 0.3],
            [0.2, 0.3, 0.7],
            [0.5, 0.5, 0.5],
        ] {
            let (h, s, v) = rgb_to_hsv(rgb[0], rgb[1], rgb[2]);
            let (r, g, b) = hsv_to_rgb(h, s, v);
            assert!(
                (r - rgb[0]).abs() < 1e-6 && (g - rgb[1]).abs() < 1e-6 && (b - rgb[2]).abs() < 1e-6
            );
        }
        let mut unit = vec![0.5f32, 0.25, 1.0];
        scale_intensity(&mut unit, 1.2);
        assert_eq!(unit, vec![0.6, 0.3, 1.0]);
    }
}
