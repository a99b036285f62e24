//! Patchify and its exact inverse.

use burn::tensor::Tensor;

/// `(N, H, W, 3) -> (N, T, 3p^2)`: patches in row-major grid order, each flattened in
/// `(row-in-patch, col-in-patch, channel)` order.
pub fn patchify(images: Tensor<4>, patch: usize) -> Tensor<3> {
    let [n, height, width, channels] = images.dims();
    let (rows, cols) = (height / patch, width / patch);
    images
        .reshape([n, rows, patch, cols, patch, channels])
        .permute([0, 1, 3, 2, 4, 5])
        .reshape([n, rows * cols, patch * patch * channels])
}

/// `(N, T, 3p^2) -> (N, H, W, 3)` for a square `side x side` image; inverse of [`patchify`].
pub fn unpatchify(tokens: Tensor<3>, patch: usize, side: usize) -> Tensor<4> {
    let [n, _, values] = tokens.dims();
    let channels = values / (patch * patch);
    let grid = side / patch;
    tokens
        .reshape([n, grid, grid, patch, patch, channels])
        .permute([0, 1, 3, 2, 4, 5])
        .reshape([n, side, side, channels])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    #[test]
    fn patch_order_is_row_major_and_unpatchify_inverts_it() {
        let device = Device::flex();
        let (side, patch) = (4, 2);
        let values: Vec<f32> = (0..side * side * 3).map(|i| i as f32).collect();
        let image =
            Tensor::<4>::from_data(TensorData::new(values.clone(), [1, side, side, 3]), &device);
        let tokens = patchify(image, patch);
        assert_eq!(tokens.dims(), [1, 4, 12]);
        let flat = tokens.clone().try_into_vec_as::<f32>().unwrap();
        // Token 1 is the top-right patch; its first value is pixel (0, 2) channel 0, its fourth
        // is pixel (0, 3) channel 0, its seventh is pixel (1, 2) channel 0.
        let pixel = |row: usize, col: usize| ((row * side + col) * 3) as f32;
        assert_eq!(flat[12], pixel(0, 2));
        assert_eq!(flat[15], pixel(0, 3));
        assert_eq!(flat[18], pixel(1, 2));
        let back = unpatchify(tokens, patch, side)
            .try_into_vec_as::<f32>()
            .unwrap();
        assert_eq!(back, values);
    }
}
