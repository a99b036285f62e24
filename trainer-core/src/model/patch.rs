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
