//! The release's mixed precision as rounding points (SPEC "Mixed precision in the release"):
//! a tensor at such a point is rounded to the half type and carried on in float32, which is
//! what a half-precision op followed by a float32 one computes. Weights, gradients and the
//! optimizer's state stay float32; the backward pass goes through the casts unchanged.
//!
//! Also the model's compute type (`model.compute`, torch's autocast): matrix products and
//! attention run in a half type, on float32 weights cast at each use, and hand float32 back.

use burn::tensor::module::linear;
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

/// The half type `precision` names; `None` for float32.
fn half_of(precision: Precision) -> Option<DType> {
    match precision {
        Precision::F32 => None,
        Precision::Bf16 => Some(DType::BF16),
        Precision::F16 => Some(DType::F16),
    }
}

/// `x` in the type products compute in under `compute` (unchanged for `f32`).
pub fn to_compute<const D: usize>(x: Tensor<D>, compute: Precision) -> Tensor<D> {
    match half_of(compute) {
        Some(half) => x.cast(half),
        None => x,
    }
}

/// `x` back in float32 after a product computed in `compute`'s type.
pub fn from_compute<const D: usize>(x: Tensor<D>, compute: Precision) -> Tensor<D> {
    match half_of(compute) {
        Some(_) => x.cast(DType::F32),
        None => x,
    }
}

/// `linear(x, weight, bias)` computed in `compute`'s type: the inputs are cast to it and the
/// product back to float32, so the weights (and, through the casts' backward pass, their
/// gradients) stay float32.
pub fn linear_in<const D: usize>(
    x: Tensor<D>,
    weight: Tensor<2>,
    bias: Option<Tensor<1>>,
    compute: Precision,
) -> Tensor<D> {
    let product = linear(
        to_compute(x, compute),
        to_compute(weight, compute),
        bias.map(|bias| to_compute(bias, compute)),
    );
    from_compute(product, compute)
}
