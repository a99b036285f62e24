//! Frames from bytes: decode JPEG or PNG, centre-crop to a square and resize to the training
//! size as the release does ([`super::resize`]: corner-aligned bilinear, no antialiasing,
//! truncation to `u8`), and map to the `[-1, 1]` channels-last layout the model takes.

use image::{ImageReader, RgbImage};

use crate::frame::Image;
use crate::resize::center_crop_resize;

/// Why a frame could not be turned into an image; the loader skips and counts such frames.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// Not a readable JPEG or PNG (corrupt, truncated, or another format).
    #[error("cannot decode {path}: {reason}")]
    Decode {
        /// Object the bytes came from.
        path: String,
        /// What the decoder reported.
        reason: String,
    },
    /// Zero-sized image.
    #[error("{path} has no pixels")]
    Empty {
        /// Object the bytes came from.
        path: String,
    },
}

/// Decodes `bytes` (named `path` in errors) into a `size x size` training frame.
pub fn decode_frame(bytes: &[u8], path: &str, size: usize) -> Result<Image, DecodeError> {
    let failure = |reason: String| DecodeError::Decode {
        path: path.to_string(),
        reason,
    };
    let decoded = ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| failure(e.to_string()))?
        .decode()
        .map_err(|e| failure(e.to_string()))?
        .into_rgb8();
    if decoded.width() == 0 || decoded.height() == 0 {
        return Err(DecodeError::Empty {
            path: path.to_string(),
        });
    }
    Ok(to_training_frame(&decoded, size))
}

/// Centre-crops `rgb` to a square and resizes it to `size x size` in `[-1, 1]`.
pub fn to_training_frame(rgb: &RgbImage, size: usize) -> Image {
    let (height, width) = (rgb.height() as usize, rgb.width() as usize);
    let resized = center_crop_resize(rgb.as_raw(), height, width, size);
    Image {
        height: size,
        width: size,
        pixels: resized
            .bytes
            .into_iter()
            .map(|v| 2.0 * (f32::from(v) / 255.0) - 1.0)
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::ImageFormat;

    fn encode(width: u32, height: u32, format: ImageFormat) -> Vec<u8> {
        let image = RgbImage::from_fn(width, height, |x, y| {
            image::Rgb([(x * 3) as u8, (y * 5) as u8, 128])
        });
        let mut bytes = std::io::Cursor::new(Vec::new());
        image.write_to(&mut bytes, format).unwrap();
        bytes.into_inner()
    }

    #[test]
    fn png_is_cropped_to_the_centre_and_mapped_to_minus_one_one() {
        let frame = decode_frame(&encode(60, 40, ImageFormat::Png), "a.png", 40).unwrap();
        assert_eq!(
            (frame.height, frame.width, frame.pixels.len()),
            (40, 40, 40 * 40 * 3)
        );
        // Column 0 of the crop is column 10 of the source: red = 30.
        assert!((frame.pixels[0] - (30.0 * 2.0 / 255.0 - 1.0)).abs() < 1e-6);
        assert!((frame.pixels[2] - (128.0 * 2.0 / 255.0 - 1.0)).abs() < 1e-6);
    }

    #[test]
    fn jpeg_is_resized_to_the_training_size() {
        let frame = decode_frame(&encode(64, 48, ImageFormat::Jpeg), "b.jpg", 16).unwrap();
        assert_eq!(frame.pixels.len(), 16 * 16 * 3);
        assert!(frame.pixels.iter().all(|v| (-1.0..=1.0).contains(v)));
    }

    #[test]
    fn corrupt_and_truncated_frames_are_errors_naming_the_file() {
        let error = decode_frame(b"not an image", "x/corrupt.jpg", 8).unwrap_err();
        assert!(error.to_string().contains("x/corrupt.jpg"), "{error}");
        let jpeg = encode(32, 32, ImageFormat::Jpeg);
        let error = decode_frame(&jpeg[..jpeg.len() / 3], "x/cut.jpg", 8).unwrap_err();
        assert!(error.to_string().contains("x/cut.jpg"), "{error}");
    }
}
