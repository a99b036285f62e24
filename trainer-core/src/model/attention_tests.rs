use super::{op_by_op_attention, softmax_attention};
use burn::tensor::{Device, Distribution, Tensor};

/// The model's segment bias for segment `i % 3` over the first two thirds of the tokens, then
/// `3`: whole runs of keys are masked for some rows.
fn runs_of_segments(batch: usize, tokens: usize, device: &Device) -> Tensor<4> {
    let ids: Vec<f32> = (0..tokens)
        .map(|i| {
            if i < 2 * tokens / 3 {
                (i % 3) as f32
            } else {
                3.0
            }
        })
        .collect();
    let ids = Tensor::<1>::from_floats(ids.as_slice(), device);
    crate::model::segment_bias(ids.reshape([1, tokens]).expand([batch, tokens]))
}

/// Largest absolute difference between two tensors, over the larger one's largest magnitude.
fn relative_error<const D: usize>(actual: Tensor<D>, expected: Tensor<D>) -> f32 {
    let scale: f32 = expected.clone().abs().max().into_scalar();
    let scale = scale.max(1e-6);
    let largest: f32 = (actual - expected).abs().max().into_scalar();
    largest / scale
}

/// The fused op's output and its gradients with respect to q, k and v against the composed
/// reference, under a loss that weighs every output element differently.
fn agrees_with_composed(batch: usize, heads: usize, tokens: usize, masked: bool) {
    let device = Device::flex().autodiff();
    let shape = [batch, heads, tokens, 8];
    let draw = || Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.5), &device);
    let (q, k, v) = (draw(), draw(), draw());
    let weights = Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &device);
    let bias = masked.then(|| runs_of_segments(batch, tokens, &device));
    let run = |attend: fn(Tensor<4>, Tensor<4>, Tensor<4>, Option<&Tensor<4>>) -> Tensor<4>| {
        let (q, k, v) = (
            q.clone().require_grad(),
            k.clone().require_grad(),
            v.clone().require_grad(),
        );
        let out = attend(q.clone(), k.clone(), v.clone(), bias.as_ref());
        let grads = (out.clone() * weights.clone()).sum().backward();
        let grad = |x: &Tensor<4>| x.grad(&grads).expect("a gradient");
        [out.inner(), grad(&q), grad(&k), grad(&v)]
    };
    let fused = run(softmax_attention);
    let reference = run(op_by_op_attention);
    for (name, (actual, expected)) in ["out", "dq", "dk", "dv"]
        .iter()
        .zip(fused.into_iter().zip(reference))
    {
        let error = relative_error(actual, expected);
        assert!(
            error < 1e-5,
            "{name} (tokens={tokens} masked={masked}): relative error {error:e}"
        );
    }
}

#[test]
fn matches_the_composed_attention_and_its_gradients() {
    agrees_with_composed(2, 3, 17, false);
    agrees_with_composed(2, 3, 17, true);
}

/// Beyond 512 tokens burn-flex takes its tiled (flash) kernel, whose running maximum starts
/// at `-inf`: rows whose first keys are all masked must still come out right.
#[test]
fn long_masked_sequences_take_the_tiled_kernel_and_agree() {
    agrees_with_composed(1, 2, 600, true);
}

/// Half inputs (`model.compute`): the products run in the half, the softmax in float32 (the
/// masked forward computes its weights itself; the unmasked one is burn's op), so output and
/// gradients stay within the half's rounding of the float32 reference.
#[test]
fn half_inputs_agree_with_float32_within_the_half_rounding() {
    use burn::tensor::DType;
    let device = Device::flex().autodiff();
    let shape = [2, 3, 17, 8];
    let draw = || Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.5), &device);
    let (q, k, v) = (draw(), draw(), draw());
    for masked in [false, true] {
        let bias = masked.then(|| runs_of_segments(2, 17, &device));
        for half in [DType::BF16, DType::F16] {
            let run = |half: Option<DType>| {
                let (q, k, v) = (
                    q.clone().require_grad(),
                    k.clone().require_grad(),
                    v.clone().require_grad(),
                );
                let cast = |x: Tensor<4>| half.map_or(x.clone(), |half| x.cast(half));
                let out = softmax_attention(
                    cast(q.clone()),
                    cast(k.clone()),
                    cast(v.clone()),
                    bias.as_ref(),
                )
                .cast(DType::F32);
                let grads = out.clone().sum().backward();
                [out.inner(), q.grad(&grads).expect("a gradient")]
            };
            let [out, grad_q] = run(Some(half));
            let [reference_out, reference_grad_q] = run(None);
            let out_error = relative_error(out, reference_out);
            let grad_error = relative_error(grad_q, reference_grad_q);
            let context = format!("{half:?} masked={masked}");
            assert!(out_error < 2e-2, "{context}: output off by {out_error:e}");
            assert!(grad_error < 5e-2, "{context}: dq off by {grad_error:e}");
        }
    }
}

/// A query row the bias masks entirely (no such row in the model: every token sees its own
/// segment) gets a zero output and finite gradients, as burn's own attention gives, not NaN.
#[test]
fn a_fully_masked_row_gives_zeros_not_nan() {
    let device = Device::flex().autodiff();
    let shape = [1, 2, 6, 8];
    let draw = || Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &device);
    let (q, k, v) = (
        draw().require_grad(),
        draw().require_grad(),
        draw().require_grad(),
    );
    let row = Tensor::<4>::full([1, 1, 1, 6], f32::NEG_INFINITY, &device);
    let bias = Tensor::cat(vec![row, Tensor::zeros([1, 1, 5, 6], &device)], 2);
    let out = softmax_attention(q.clone(), k.clone(), v.clone(), Some(&bias));
    let masked_row: f32 = out.clone().narrow(2, 0, 1).abs().max().into_scalar();
    assert_eq!(masked_row, 0.0);
    let grads = out.sum().backward();
    for (name, x) in [("q", &q), ("k", &k), ("v", &v)] {
        let grad = x.grad(&grads).expect("a gradient");
        let has_nan: bool = grad.is_nan().any().into_scalar();
        assert!(!has_nan, "d{name} has NaN");
    }
}

/// bf16 (`model.compute`) never reaches cubecl's attention kernels, whose f16 tiles would turn
/// values above 65504 into infinities, with or without the segment bias; burn-flex's and
/// libtorch's kernels keep the inputs' range and take it without a bias.
#[test]
fn bf16_never_routes_through_half_tiles() {
    use super::{FusedKernel, routes_to_burns_op};
    use burn::backend::FloatDType;
    for biased in [false, true] {
        assert!(!routes_to_burns_op(
            FloatDType::BF16,
            FusedKernel::HalfTiles,
            biased
        ));
        assert!(!routes_to_burns_op(
            FloatDType::F32,
            FusedKernel::HalfTiles,
            biased
        ));
        assert!(routes_to_burns_op(
            FloatDType::F32,
            FusedKernel::Float32,
            biased
        ));
    }
    assert!(routes_to_burns_op(
        FloatDType::BF16,
        FusedKernel::Float32,
        false
    ));
    assert!(!routes_to_burns_op(
        FloatDType::BF16,
        FusedKernel::Float32,
        true
    ));
}

/// Scores far above f16's largest value (65504) on the Cube backend (wgpu; lavapipe on a host
/// without a GPU), under the segment bias: the output and the gradients stay finite and equal
/// burn-flex's op-by-op float32 reference. Every key shares one large component, so the scores
/// are about 8.5e4 while their differences (what the softmax sees) stay near 1.
#[test]
fn scores_above_the_half_range_stay_finite_on_the_cube_backend() {
    use crate::backend::{Backend, BackendDevices};
    let (batch, heads, tokens) = (2, 2, 19);
    let shape = [batch, heads, tokens, 8];
    let flex = Device::flex().autodiff();
    let normal = |std: f64| Tensor::<4>::random(shape, Distribution::Normal(0.0, std), &flex);
    let shared = Tensor::<4>::full([batch, heads, 1, 8], 300.0, &flex).expand(shape);
    let q = normal(1.0) + Tensor::<4>::full(shape, 100.0, &flex);
    let k = shared + normal(0.03);
    let (v, weights) = (normal(1.0), normal(1.0));
    let largest_score: f32 = q
        .clone()
        .matmul(k.clone().swap_dims(2, 3))
        .abs()
        .max()
        .into_scalar();
    assert!(largest_score / 8f32.sqrt() > 65504.0, "{largest_score}");
    let run =
        |device: &Device,
         attend: fn(Tensor<4>, Tensor<4>, Tensor<4>, Option<&Tensor<4>>) -> Tensor<4>| {
            let on = |x: &Tensor<4>| Tensor::<4>::from_data(x.to_data(), device).require_grad();
            let (q, k, v) = (on(&q), on(&k), on(&v));
            let bias = runs_of_segments(batch, tokens, device);
            let out = attend(q.clone(), k.clone(), v.clone(), Some(&bias));
            let grads = (out.clone() * Tensor::from_data(weights.to_data(), device))
                .sum()
                .backward();
            let grad = |x: &Tensor<4>| {
                let grad = x.grad(&grads).expect("a gradient");
                Tensor::<4>::from_data(grad.to_data(), &Device::flex())
            };
            [
                Tensor::<4>::from_data(out.inner().to_data(), &Device::flex()),
                grad(&q),
                grad(&k),
                grad(&v),
            ]
        };
    let cube = Backend::Wgpu
        .device()
        .expect("a wgpu adapter (lavapipe where there is no GPU)")
        .autodiff();
    let actual = run(&cube, softmax_attention);
    let expected = run(&flex, op_by_op_attention);
    for (name, (actual, expected)) in ["out", "dq", "dk", "dv"]
        .iter()
        .zip(actual.into_iter().zip(expected))
    {
        let finite: bool = actual.clone().is_finite().all().into_scalar();
        assert!(finite, "{name} is not finite on the Cube backend");
        // Scores near 8.5e4 carry float32's rounding of about 0.008 into the softmax.
        let error = relative_error(actual, expected);
        assert!(error < 3e-2, "{name}: relative error {error:e}");
    }
}
