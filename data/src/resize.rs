//! The release's frame resize (`center_crop_resize` in its `data/video_dataset.py`): crop the
//! centred square, sample it at `linspace(0, N - 1, size)` (corners aligned) with plain
//! bilinear weights between the four neighbours, no antialiasing, and truncate to `u8`.
//!
//! Written out in `f64` in the release's operation order so the bytes match it exactly; an
//! antialiased resize (PIL, `image`'s triangle filter) trains on visibly softer frames.

/// An 8-bit RGB image, row-major, channels last.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rgb8 {
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// `height * width * 3` bytes.
    pub bytes: Vec<u8>,
}

/// `numpy.linspace(0, n - 1, size)`: `i * step`, the last point exactly `n - 1`.
fn linspace(n: usize, size: usize) -> Vec<f64> {
    if size == 1 {
        return vec![0.0];
    }
    let step = (n as f64 - 1.0) / (size as f64 - 1.0);
    let mut coords: Vec<f64> = (0..size).map(|i| i as f64 * step).collect();
    coords[size - 1] = n as f64 - 1.0;
    coords
}

/// Centre-crops the `height x width` RGB `pixels` to a square and resizes it to `size x size`
/// as the release does.
pub fn center_crop_resize(pixels: &[u8], height: usize, width: usize, size: usize) -> Rgb8 {
    if height == size && width == size {
        return Rgb8 {
            height,
            width,
            bytes: pixels.to_vec(),
        };
    }
    let side = height.min(width);
    let (top, left) = ((height - side) / 2, (width - side) / 2);
    let at = |row: usize, col: usize, channel: usize| {
        f64::from(pixels[((top + row) * width + left + col) * 3 + channel])
    };
    if side == size {
        let mut bytes = Vec::with_capacity(side * side * 3);
        for row in 0..side {
            let start = ((top + row) * width + left) * 3;
            bytes.extend_from_slice(&pixels[start..start + side * 3]);
        }
        return Rgb8 {
            height: side,
            width: side,
            bytes,
        };
    }
    let coords = linspace(side, size);
    let taps: Vec<(usize, usize, f64)> = coords
        .iter()
        .map(|&c| {
            let low = c.floor() as usize;
            (low, (low + 1).min(side - 1), c - low as f64)
        })
        .collect();
    let mut bytes = Vec::with_capacity(size * size * 3);
    for &(y0, y1, dy) in &taps {
        for &(x0, x1, dx) in &taps {
            for channel in 0..3 {
                let top_row = (1.0 - dx) * at(y0, x0, channel) + dx * at(y0, x1, channel);
                let bottom_row = (1.0 - dx) * at(y1, x0, channel) + dx * at(y1, x1, channel);
                let value = (1.0 - dy) * top_row + dy * bottom_row;
                // `astype(uint8)` truncates towards zero; the value is already in [0, 255].
                bytes.push(value as u8);
            }
        }
    }
    Rgb8 {
        height: size,
        width: size,
        bytes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linspace_aligns_the_corners() {
        assert_eq!(linspace(5, 3), vec![0.0, 2.0, 4.0]);
        let coords = linspace(256, 64);
        assert_eq!((coords[0], coords[63]), (0.0, 255.0));
    }

    #[test]
    fn corners_are_copied_and_values_truncate() {
        // A 2x2 square resized to 3x3: the centre is the mean of four bytes, truncated.
        let image = Rgb8 {
            height: 2,
            width: 2,
            bytes: [0u8, 1, 2, 3]
                .iter()
                .flat_map(|&v| [v, v * 10, 255 - v])
                .collect(),
        };
        let out = center_crop_resize(&image.bytes, image.height, image.width, 3);
        let pixel =
            |row: usize, col: usize| &out.bytes[(row * 3 + col) * 3..(row * 3 + col) * 3 + 3];
        assert_eq!(pixel(0, 0), &[0, 0, 255]);
        assert_eq!(pixel(2, 2), &[3, 30, 252]);
        // (0 + 1 + 2 + 3) / 4 = 1.5 -> 1; (0 + 10 + 20 + 30) / 4 = 15; 253.5 -> 253.
        assert_eq!(pixel(1, 1), &[1, 15, 253]);
    }

    #[test]
    fn a_wide_frame_is_cropped_to_its_centre() {
        let image = Rgb8 {
            height: 2,
            width: 4,
            bytes: (0..8u8).flat_map(|v| [v, v, v]).collect(),
        };
        let out = center_crop_resize(&image.bytes, image.height, image.width, 2);
        assert_eq!(out.bytes, vec![1, 1, 1, 2, 2, 2, 5, 5, 5, 6, 6, 6]);
    }
}
