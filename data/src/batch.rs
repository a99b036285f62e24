//! What training consumes: images, the samples of one (micro-)batch, and the trait every
//! sample source implements.

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

/// The samples of one (micro-)batch, in the form its stage needs.
#[derive(Debug, Clone)]
pub enum Samples {
    /// Stage 1: `(context, target)` frames.
    Pairs(Vec<(Image, Image)>),
    /// Stage 2: frames with their index in the video.
    Views(Vec<Vec<(u64, Image)>>),
}

/// Where training samples come from. Implementations must return the same samples for the same
/// `(step, first_sample, count)`, whichever process asks: that is what makes runs reproduce.
pub trait BatchSource: Sync {
    /// Global samples `first_sample .. first_sample + count` of `step`.
    fn samples(&self, step: u64, first_sample: u64, count: usize) -> Result<Samples, String>;
}
