//! The image every sample is made of. It sits apart from the batch types so that decoding,
//! which produces images, and the batch source's errors, which name decoding failures, can both
//! use it without depending on each other.

/// A channels-last RGB image with values in `[-1, 1]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// `height * width * 3` values, row-major, channels last.
    pub pixels: Vec<f32>,
}
