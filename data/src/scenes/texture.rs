//! The procedural two-colour textures of walls, floors and objects: stripes, checkers and
//! value noise.

use super::*;

/// How a texture turns a point into a blend weight between its two colours.
#[derive(Debug, Clone, Copy)]
enum Pattern {
    /// Soft-edged parallel stripes across this unit direction.
    Stripes { direction: Vec3 },
    /// A soft checkerboard (3D on spheres, 2D on flat faces).
    Checkers,
    /// Three octaves of value noise: smooth blotches and gradients.
    Noise { seed: u64 },
}

/// A procedural two-colour texture.
#[derive(Debug, Clone)]
pub(super) struct Texture {
    pattern: Pattern,
    /// Stripe period, checker cell side or noise cell side, in metres.
    period: f64,
    /// Shift of the pattern so textures do not all line up with the origin (z stays 0 so
    /// flat faces, textured at z = 0, see the full checker contrast).
    offset: Vec3,
    colours: [Vec3; 2],
}

/// An RGB colour in `[0, 1]` from hue (turns), saturation and value.
fn hsv(hue: f64, saturation: f64, value: f64) -> Vec3 {
    let h6 = hue.rem_euclid(1.0) * 6.0;
    let sector = h6.floor();
    let f = h6 - sector;
    let p = value * (1.0 - saturation);
    let q = value * (1.0 - saturation * f);
    let t = value * (1.0 - saturation * (1.0 - f));
    match sector as u32 {
        0 => [value, t, p],
        1 => [q, value, p],
        2 => [p, value, t],
        3 => [p, q, value],
        4 => [t, p, value],
        _ => [value, p, q],
    }
}

/// SplitMix64's finaliser, for hashing noise lattice points.
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A pseudo-random value in `[0, 1)` attached to an integer lattice point.
fn lattice(seed: u64, x: i64, y: i64, z: i64) -> f64 {
    let mut h = mix64(seed ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    h = mix64(h ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
    h = mix64(h ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9));
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

/// Smoothly interpolated lattice noise in `[0, 1)` with unit cells.
fn value_noise(seed: u64, p: Vec3) -> f64 {
    let cell = p.map(f64::floor);
    let s: Vec3 = from_fn(|k| {
        let f = p[k] - cell[k];
        f * f * (3.0 - 2.0 * f)
    });
    let [x, y, z] = cell.map(|v| v as i64);
    let corner = |dx: i64, dy: i64, dz: i64| {
        lattice(
            seed,
            x.wrapping_add(dx),
            y.wrapping_add(dy),
            z.wrapping_add(dz),
        )
    };
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), s[0]);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), s[0]);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), s[0]);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), s[0]);
    lerp(lerp(x00, x10, s[1]), lerp(x01, x11, s[1]), s[2])
}

/// Three octaves of value noise, normalised back to `[0, 1)`.
fn fractal_noise(seed: u64, p: Vec3) -> f64 {
    let mut sum = 0.0;
    let mut total = 0.0;
    let mut amplitude = 1.0;
    let mut frequency = 1.0;
    for octave in 0..3u64 {
        sum += amplitude * value_noise(seed.wrapping_add(octave), p.map(|v| v * frequency));
        total += amplitude;
        amplitude *= 0.5;
        frequency *= 2.0;
    }
    sum / total
}

impl Texture {
    /// A random texture whose pattern scale lies in `[period_low, period_high)` metres.
    pub(super) fn random(stream: &mut Stream, period_low: f64, period_high: f64) -> Self {
        // One light and one dark colour with unrelated hues, in random order, so every
        // texture has strong contrast.
        let light_hue = stream.uniform();
        let dark_hue = light_hue + stream.uniform_in(0.15, 0.85);
        let light = hsv(
            light_hue,
            stream.uniform_in(0.2, 0.9),
            stream.uniform_in(0.65, 1.0),
        );
        let dark = hsv(
            dark_hue,
            stream.uniform_in(0.3, 1.0),
            stream.uniform_in(0.1, 0.45),
        );
        let colours = if stream.bernoulli(0.5) {
            [light, dark]
        } else {
            [dark, light]
        };
        let period = stream.uniform_in(period_low, period_high);
        let offset = [
            stream.uniform_in(-50.0, 50.0),
            stream.uniform_in(-50.0, 50.0),
            0.0,
        ];
        let pattern = match stream.below(3) {
            0 => {
                let angle = stream.uniform_in(0.0, TAU);
                let tilt = stream.uniform_in(-0.6, 0.6);
                Pattern::Stripes {
                    direction: [
                        angle.cos() * tilt.cos(),
                        angle.sin() * tilt.cos(),
                        tilt.sin(),
                    ],
                }
            }
            1 => Pattern::Checkers,
            _ => Pattern::Noise {
                seed: stream.next_u64(),
            },
        };
        Self {
            pattern,
            period,
            offset,
            colours,
        }
    }

    /// The colour in `[0, 1]` at a texture-space point (flat faces pass `(u, v, 0)`).
    pub(super) fn colour(&self, point: Vec3) -> Vec3 {
        let p = add_scaled(point, self.offset, 1.0);
        let weight = match self.pattern {
            Pattern::Stripes { direction } => {
                0.5 + 1.5 * (dot(p, direction) * (TAU / self.period)).sin()
            }
            Pattern::Checkers => {
                let k = PI / self.period;
                0.5 + 2.5 * ((p[0] * k).sin() * (p[1] * k).sin() * (p[2] * k).cos())
            }
            Pattern::Noise { seed } => {
                let n = fractal_noise(seed, p.map(|v| v / self.period));
                0.5 + 2.5 * (n - 0.5)
            }
        }
        .clamp(0.0, 1.0);
        let [a, b] = self.colours;
        from_fn(|k| lerp(a[k], b[k], weight))
    }
}
