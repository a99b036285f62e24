//! Reconstruction metrics on the model's `[-1, 1]` images, computed on `[0, 1]` intensities
//! (data range 1): PSNR and SSIM with the standard Gaussian window (Wang et al. 2004: 11x11,
//! sigma 1.5, `K1 = 0.01`, `K2 = 0.03`, valid positions only, channels averaged).

use data::Image;
use serde::{Deserialize, Serialize};

/// Side of the SSIM window.
const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM window's Gaussian, in pixels.
const SSIM_SIGMA: f64 = 1.5;
/// SSIM's luminance stabiliser `(K1 L)^2` with `L = 1`.
const SSIM_C1: f64 = 0.01 * 0.01;
/// SSIM's contrast stabiliser `(K2 L)^2` with `L = 1`.
const SSIM_C2: f64 = 0.03 * 0.03;
/// PSNR reported for identical images, so reports stay finite JSON.
pub const PSNR_CAP: f64 = 100.0;

/// Autoencoding quality: targets rendered with poses read from the same video, averaged over
/// the frames rendered.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReconstructionReport {
    /// Frames rendered.
    pub frames: usize,
    /// Mean PSNR, dB.
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean LPIPS, when weights were given.
    pub lpips: Option<f64>,
    /// Bootstrap spread of the mean PSNR over the frames.
    #[serde(default)]
    pub psnr_spread: f64,
    /// Bootstrap spread of the mean SSIM over the frames.
    #[serde(default)]
    pub ssim_spread: f64,
}

/// Why two images cannot be compared.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ImageMetricError {
    /// The images differ in size.
    #[error("images differ in size: {0}x{1} vs {2}x{3}")]
    Size(usize, usize, usize, usize),
    /// SSIM's window does not fit in the image.
    #[error("SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {0}x{1}")]
    TooSmall(usize, usize),
}

fn check_sizes(a: &Image, b: &Image) -> Result<(), ImageMetricError> {
    if (a.height, a.width) != (b.height, b.width) || a.pixels.len() != b.pixels.len() {
        return Err(ImageMetricError::Size(a.height, a.width, b.height, b.width));
    }
    Ok(())
}

/// `[-1, 1]` to `[0, 1]`.
fn unit(v: f32) -> f64 {
    (f64::from(v) + 1.0) / 2.0
}

/// Peak signal-to-noise ratio in dB over all pixels and channels, capped at [`PSNR_CAP`].
pub fn psnr(a: &Image, b: &Image) -> Result<f64, ImageMetricError> {
    check_sizes(a, b)?;
    let mse = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(&x, &y)| (unit(x) - unit(y)).powi(2))
        .sum::<f64>()
        / a.pixels.len().max(1) as f64;
    Ok(if mse <= 0.0 {
        PSNR_CAP
    } else {
        (-10.0 * mse.log10()).min(PSNR_CAP)
    })
}

/// The normalised 1D Gaussian of the SSIM window (the 2D window is its outer product).
fn gaussian_window() -> [f64; SSIM_WINDOW] {
    let centre = (SSIM_WINDOW / 2) as f64;
    let mut w: [f64; SSIM_WINDOW] = std::array::from_fn(|i| {
        let d = i as f64 - centre;
        (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp()
    });
    let sum: f64 = w.iter().sum();
    w.iter_mut().for_each(|v| *v /= sum);
    w
}

/// Separable "valid" Gaussian filtering of one `height x width` plane.
fn filter(plane: &[f64], height: usize, width: usize, w: &[f64; SSIM_WINDOW]) -> Vec<f64> {
    let out_w = width - SSIM_WINDOW + 1;
    let out_h = height - SSIM_WINDOW + 1;
    let rows: Vec<f64> = (0..height)
        .flat_map(|y| {
            (0..out_w).map(move |x| {
                (0..SSIM_WINDOW)
                    .map(|k| w[k] * plane[y * width + x + k])
                    .sum()
            })
        })
        .collect();
    (0..out_h)
        .flat_map(|y| {
            let rows = &rows;
            (0..out_w).map(move |x| {
                (0..SSIM_WINDOW)
                    .map(|k| w[k] * rows[(y + k) * out_w + x])
                    .sum()
            })
        })
        .collect()
}

/// Mean structural similarity over valid window positions and the three channels.
pub fn ssim(a: &Image, b: &Image) -> Result<f64, ImageMetricError> {
    check_sizes(a, b)?;
    let (height, width) = (a.height, a.width);
    if height < SSIM_WINDOW || width < SSIM_WINDOW {
        return Err(ImageMetricError::TooSmall(height, width));
    }
    let w = gaussian_window();
    let mut total = 0.0;
    for channel in 0..3 {
        let plane = |image: &Image| -> Vec<f64> {
            image
                .pixels
                .iter()
                .skip(channel)
                .step_by(3)
                .map(|&v| unit(v))
                .collect()
        };
        let (x, y) = (plane(a), plane(b));
        let product =
            |p: &[f64], q: &[f64]| -> Vec<f64> { p.iter().zip(q).map(|(u, v)| u * v).collect() };
        let mu_x = filter(&x, height, width, &w);
        let mu_y = filter(&y, height, width, &w);
        let xx = filter(&product(&x, &x), height, width, &w);
        let yy = filter(&product(&y, &y), height, width, &w);
        let xy = filter(&product(&x, &y), height, width, &w);
        let map: f64 = (0..mu_x.len())
            .map(|i| {
                let (mx, my) = (mu_x[i], mu_y[i]);
                let (vx, vy, cxy) = (xx[i] - mx * mx, yy[i] - my * my, xy[i] - mx * my);
                ((2.0 * mx * my + SSIM_C1) * (2.0 * cxy + SSIM_C2))
                    / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))
            })
            .sum();
        total += map / mu_x.len() as f64;
    }
    Ok(total / 3.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(side: usize, value: impl Fn(usize, usize, usize) -> f32) -> Image {
        Image {
            height: side,
            width: side,
            pixels: (0..side * side * 3)
                .map(|i| value((i / 3) / side, (i / 3) % side, i % 3))
                .collect(),
        }
    }

    #[test]
    fn psnr_of_known_differences() {
        // [0, 1] values 0.5 and 0.25: MSE 1/16, PSNR = 10 log10(16) = 12.0412 dB.
        let a = image(16, |_, _, _| 0.0);
        let b = image(16, |_, _, _| -0.5);
        assert!((psnr(&a, &b).unwrap() - 10.0 * 16f64.log10()).abs() < 1e-9);
        // Half the pixels off by 0.1 in [0, 1]: MSE 0.005, PSNR = 23.0103 dB.
        let c = image(16, |y, _, _| if y < 8 { 0.2 } else { 0.0 });
        assert!((psnr(&a, &c).unwrap() - 10.0 * 200f64.log10()).abs() < 1e-4);
        assert_eq!(psnr(&a, &a).unwrap(), PSNR_CAP);
        assert!(psnr(&a, &image(8, |_, _, _| 0.0)).is_err());
    }

    #[test]
    fn ssim_of_known_images() {
        let a = image(16, |_, _, _| 0.0);
        let b = image(16, |_, _, _| -0.5);
        // Flat images: only the luminance term, (2*.5*.25 + C1) / (.25 + .0625 + C1).
        let expected = (0.25 + SSIM_C1) / (0.3125 + SSIM_C1);
        assert!((ssim(&a, &b).unwrap() - expected).abs() < 1e-9);
        let textured = image(24, |y, x, c| {
            ((x * 7 + y * 13 + c * 5) % 17) as f32 / 8.5 - 1.0
        });
        assert!((ssim(&textured, &textured).unwrap() - 1.0).abs() < 1e-9);
        // An inverted texture has negative structure correlation.
        let inverted = Image {
            pixels: textured.pixels.iter().map(|v| -v).collect(),
            ..textured.clone()
        };
        assert!(ssim(&textured, &inverted).unwrap() < 0.0);
        assert_eq!(
            ssim(&image(8, |_, _, _| 0.0), &image(8, |_, _, _| 0.0)),
            Err(ImageMetricError::TooSmall(8, 8))
        );
    }

    #[test]
    fn window_is_normalised_and_symmetric() {
        let w = gaussian_window();
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!((w[0] - w[10]).abs() < 1e-15 && w[5] > w[4]);
    }
}
