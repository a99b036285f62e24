//! The release's mixed precision as rounding points (SPEC "Mixed precision in the release"):
//! a tensor at such a point is rounded to the half type and carried on in float32, which is
//! what a half-precision op followed by a float32 one computes. Weights, gradients and the
//! optimizer's state stay float32; the backward pass goes through the casts unchanged.

use burn::tensor::{DType, Tensor};
use settings::XFactorConfig;
use settings::model::Precision;

/// `x` rounded to `precision`'s half type (unchanged for `f32`).
pub fn round<const D: usize>(x: Tensor<D>, precision: Precision) -> Tensor<D> {
    match precision {
        Precision::F32 => x,
        Precision::Bf16 => x.cast(DType::BF16).cast(DType::F32),
        Precision::F16 => x.cast(DType::F16).cast(DType::F32),
    }
}

/// Where q, k and v are rounded: the model's mixed precision, or bfloat16 alone when only
/// `round_qkv_bf16` asks for it.
pub fn qkv_precision(config: &XFactorConfig) -> Precision {
    match config.precision {
        Precision::F32 if config.round_qkv_bf16 => Precision::Bf16,
        precision => precision,
    }
}
