//! 2D rotary position embedding over the patch grid.

use burn::tensor::{Device, Tensor, TensorData};

/// Precomputed `cos`/`sin` tables for one token layout: a `rows x cols` patch grid followed by
/// `identity_tokens` tokens (PoseEnc's global tokens) that are left unrotated.
#[derive(Debug, Clone)]
pub struct RopeTable {
    cos: Tensor<6>,
    sin: Tensor<6>,
}

impl RopeTable {
    /// The tables rounded to `precision`'s half type (Render's RoPE table under the release's
    /// mixed precision).
    pub fn rounded(self, precision: settings::model::Precision) -> Self {
        Self {
            cos: super::precision::round(self.cos, precision),
            sin: super::precision::round(self.sin, precision),
        }
    }

    /// Builds the tables for head size `head_dim` (a multiple of 4).
    ///
    /// Frequencies `w_i = 10000^(-i / (d/4))`, each repeated twice; a patch at `(I, J)` gets the
    /// angles `concat(w * I, w * J)`.
    pub fn new(
        rows: usize,
        cols: usize,
        identity_tokens: usize,
        head_dim: usize,
        device: &Device,
    ) -> Self {
        let quarter = head_dim / 4;
        let freqs: Vec<f64> = (0..quarter)
            .flat_map(|i| {
                let w = 10000f64.powf(-(i as f64) / quarter as f64);
                [w, w]
            })
            .collect();
        let tokens = rows * cols + identity_tokens;
        let mut cos = Vec::with_capacity(tokens * head_dim);
        let mut sin = Vec::with_capacity(tokens * head_dim);
        for row in 0..rows {
            for col in 0..cols {
                let angles = freqs
                    .iter()
                    .map(|w| w * row as f64)
                    .chain(freqs.iter().map(|w| w * col as f64));
                for angle in angles {
                    cos.push(angle.cos() as f32);
                    sin.push(angle.sin() as f32);
                }
            }
        }
        cos.extend(std::iter::repeat_n(1.0f32, identity_tokens * head_dim));
        sin.extend(std::iter::repeat_n(0.0f32, identity_tokens * head_dim));
        let shape = [1, 1, tokens, 1, 1, head_dim];
        Self {
            cos: Tensor::from_data(TensorData::new(cos, shape), device),
            sin: Tensor::from_data(TensorData::new(sin, shape), device),
        }
    }

    /// Rotates `x: (B, V, T', n, h, d)` (`n` tensors of heads per token): `x * cos + rot(x) *
    /// sin`, where `rot` maps each pair `(x[2k], x[2k+1])` to `(-x[2k+1], x[2k])`.
    pub fn apply(&self, x: Tensor<6>) -> Tensor<6> {
        let [b, v, t, n, h, d] = x.dims();
        let pairs = x.clone().reshape([b, v, t, n * h, d / 2, 2]);
        let even = pairs.clone().narrow(5, 0, 1);
        let odd = pairs.narrow(5, 1, 1);
        let rotated = Tensor::cat(vec![odd.neg(), even], 5).reshape([b, v, t, n, h, d]);
        x * self.cos.clone() + rotated * self.sin.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_keeps_pair_norms_and_leaves_extra_tokens_alone() {
        let device = Device::flex();
        let (rows, cols, extra, d) = (2, 3, 2, 8);
        let tokens = rows * cols + extra;
        let values: Vec<f32> = (0..tokens * d).map(|i| (i as f32 * 0.37).sin()).collect();
        let x = Tensor::<6>::from_data(
            TensorData::new(values.clone(), [1, 1, tokens, 1, 1, d]),
            &device,
        );
        let rotated = RopeTable::new(rows, cols, extra, d, &device)
            .apply(x)
            .try_into_vec_as::<f32>()
            .unwrap();
        for pair in 0..tokens * d / 2 {
            let before = values[2 * pair].hypot(values[2 * pair + 1]);
            let after = rotated[2 * pair].hypot(rotated[2 * pair + 1]);
            assert!((before - after).abs() < 1e-5);
        }
        // Patch (0, 0) has angle zero and the extra tokens are the identity.
        assert_eq!(rotated[..d], values[..d]);
        assert_eq!(rotated[rows * cols * d..], values[rows * cols * d..]);
        // Patch (0, 1): the first d/2 angles use the row (0), the last d/2 the column (1).
        assert_eq!(rotated[d..d + d / 2], values[d..d + d / 2]);
        assert_ne!(rotated[d + d / 2..2 * d], values[d + d / 2..2 * d]);
    }
}
