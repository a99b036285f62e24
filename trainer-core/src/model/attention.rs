//! Softmax attention whose backward pass keeps no `N x N` matrix between the forward and the
//! backward pass (issue 33: the scores, weights and products the autodiff graph kept per
//! attention were most of a step's device memory).
//!
//! Under autodiff it records one node that keeps only `q`, `k`, `v` and the bias; its backward
//! pass recomputes the weights from them, one attention at a time, as flash attention's
//! backward does. The forward pass is burn's attention op where that op computes what the
//! backward pass assumes (burn-flex's tiled kernel on the CPU, libtorch's kernels), else the
//! weights in float32 and one product ([`routes_to_burns_op`]). cubecl's devices never take
//! burn's op: its tensor-core flash kernels round every input to f16 tiles, where bf16 values
//! above 65504 become infinite, and its fallback takes the softmax in the inputs' type.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::ops::AttentionModuleOptions;
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Cube, Dispatch, Flex, backend_extension};
use burn::backend::{DType, FloatDType, TensorMetadata};
use burn::tensor::Tensor;

/// Attention as one differentiable op on every backend the trainer runs on, over
/// `(batch, heads, tokens, d)` inputs. Two methods rather than an optional bias: the extension
/// macro routes tensors, not options of them.
#[backend_extension(Autodiff, Cube: cfg(all()), Flex: cfg(all()), LibTorch: cfg(feature = "libtorch"))]
pub trait SoftmaxAttention: Backend {
    /// `softmax(q kᵀ / sqrt(d)) v`.
    fn softmax_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// `softmax(q kᵀ / sqrt(d) + bias) v`; `bias` `(batch, 1, tokens, tokens)` is broadcast
    /// over heads.
    fn biased_softmax_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// What burn's attention op computes an attention in on a backend.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FusedKernel {
    /// Float32 inputs in float32 (burn-flex, which computes halves in float32 too; libtorch,
    /// which keeps float32 inputs off its flash kernels).
    Float32,
    /// Possibly in f16 tiles: cubecl's tensor-core flash kernels take their tiles in f16
    /// whatever the inputs' type (bf16 and float32 included), where autotune picks them, and
    /// its fallback takes the scores and the softmax in the inputs' type.
    HalfTiles,
}

/// Whether burn's attention op computes the forward pass of inputs of type `compute` on a
/// backend whose fused kernel is `fused`, with or without a bias; else the float32 weights
/// the backward pass recomputes, and one product.
///
/// - float32 only where the fused kernel stays in float32;
/// - a half (`model.compute`) without a bias where the kernel keeps the inputs' range;
///   never on cubecl's devices, whose f16 tiles would turn bf16 values above 65504 into
///   infinities (and whose fallback would take the softmax in bf16);
/// - a half with a bias nowhere: burn's unfused path would take the softmax in the half.
fn routes_to_burns_op(compute: FloatDType, fused: FusedKernel, biased: bool) -> bool {
    match (compute, fused) {
        (FloatDType::F32, fused) => fused == FusedKernel::Float32,
        (_, FusedKernel::HalfTiles) => false,
        (_, FusedKernel::Float32) => !biased,
    }
}

/// The concrete backends' forward pass ([`attention_forward`] with what their fused kernel
/// computes in).
macro_rules! concrete_attention {
    ($backend:ty, $fused:expr) => {
        impl SoftmaxAttention for $backend {
            fn softmax_attention(
                q: FloatTensor<Self>,
                k: FloatTensor<Self>,
                v: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                attention_forward::<Self>(q, k, v, None, $fused)
            }

            fn biased_softmax_attention(
                q: FloatTensor<Self>,
                k: FloatTensor<Self>,
                v: FloatTensor<Self>,
                bias: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                attention_forward::<Self>(q, k, v, Some(bias), $fused)
            }
        }
    };
}

concrete_attention!(Cube, FusedKernel::HalfTiles);
concrete_attention!(Flex, FusedKernel::Float32);
#[cfg(feature = "libtorch")]
concrete_attention!(burn::backend::LibTorch, FusedKernel::Float32);

/// The backward pass of [`SoftmaxAttention`]: its state is the inputs, not the weights.
#[derive(Debug)]
struct AttentionBackward;

impl<B: Backend> Backward<B, 3> for AttentionBackward {
    type State = (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        Option<FloatTensor<B>>,
    );

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node_q, node_k, node_v] = ops.parents;
        let grad_out = grads.consume::<B>(&ops.node);
        let (q, k, v, bias) = ops.state;
        // Products run in the inputs' type (a half under `model.compute`), the softmax and its
        // Jacobian in float32, as torch's autocast does.
        let compute = float_dtype::<B>(&q);
        let scale = scale_of::<B>(&q);
        let weights = softmax_weights::<B>(q.clone(), k.clone(), bias, scale);
        if let Some(node) = node_v {
            let weights = cast_to::<B>(weights.clone(), compute);
            let grad_v = B::float_matmul(B::float_transpose(weights), grad_out.clone());
            grads.register::<B>(node.id, grad_v);
        }
        // dS = P ∘ (dP − rowsum(P ∘ dP)), with dP = dO vᵀ: the softmax's Jacobian applied to
        // dP; rowsum(P ∘ dP) equals rowsum(dO ∘ O), so the output need not be kept.
        let grad_weights = B::float_matmul(grad_out, B::float_transpose(v));
        let grad_weights = cast_to::<B>(grad_weights, FloatDType::F32);
        let row_dot = B::float_sum_dim(B::float_mul(weights.clone(), grad_weights.clone()), 3);
        let grad_scores = B::float_mul(weights, B::float_sub(grad_weights, row_dot));
        let grad_scores = cast_to::<B>(grad_scores, compute);
        if let Some(node) = node_q {
            let grad_q = B::float_matmul(grad_scores.clone(), k);
            grads.register::<B>(node.id, B::float_mul_scalar(grad_q, scale.into()));
        }
        if let Some(node) = node_k {
            let grad_k = B::float_matmul(B::float_transpose(grad_scores), q);
            grads.register::<B>(node.id, B::float_mul_scalar(grad_k, scale.into()));
        }
    }
}

/// `1 / sqrt(d)` for queries of head size `d`.
fn scale_of<B: Backend>(q: &FloatTensor<B>) -> f64 {
    let head_dim = TensorMetadata::shape(q)[3];
    1.0 / (head_dim as f64).sqrt()
}

/// The float type `tensor` holds: a half, or float32 (the model has no other).
fn float_dtype<B: Backend>(tensor: &FloatTensor<B>) -> FloatDType {
    match TensorMetadata::dtype(tensor) {
        DType::BF16 => FloatDType::BF16,
        DType::F16 => FloatDType::F16,
        _ => FloatDType::F32,
    }
}

/// `tensor` in `dtype`; no cast recorded where it already is (fusion would record one).
fn cast_to<B: Backend>(tensor: FloatTensor<B>, dtype: FloatDType) -> FloatTensor<B> {
    if float_dtype::<B>(&tensor) == dtype {
        tensor
    } else {
        B::float_cast(tensor, dtype)
    }
}

/// The attention weights `softmax(q kᵀ · scale + bias)` over the last axis, in float32
/// whatever the inputs' type (the scores are computed in it), shifted by the row maximum so
/// that `exp` cannot overflow. A row the bias masks entirely gets zero weights, not NaN, as in
/// burn's own attention.
fn softmax_weights<B: Backend>(
    q: FloatTensor<B>,
    k: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
    scale: f64,
) -> FloatTensor<B> {
    let scores = B::float_matmul(B::float_mul_scalar(q, scale.into()), B::float_transpose(k));
    let scores = cast_to::<B>(scores, FloatDType::F32);
    let scores = match bias {
        Some(bias) => B::float_add(scores, cast_to::<B>(bias, FloatDType::F32)),
        None => scores,
    };
    let shift = B::float_clamp_min(B::float_max_dim(scores.clone(), 3), f32::MIN.into());
    let exponentials = B::float_exp(B::float_sub(scores, shift));
    let normaliser = B::float_sum_dim(exponentials.clone(), 3);
    let normaliser = B::float_clamp_min(normaliser, f32::MIN_POSITIVE.into());
    B::float_div(exponentials, normaliser)
}

/// The forward pass on `B`: burn's attention op where it computes what the backward pass
/// assumes ([`routes_to_burns_op`]), else the float32 weights the backward pass recomputes,
/// and one product in the inputs' type.
fn attention_forward<B: Backend>(
    q: FloatTensor<B>,
    k: FloatTensor<B>,
    v: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
    fused: FusedKernel,
) -> FloatTensor<B> {
    let compute = float_dtype::<B>(&q);
    if routes_to_burns_op(compute, fused, bias.is_some()) {
        return B::attention(q, k, v, None, bias, AttentionModuleOptions::default());
    }
    let scale = scale_of::<B>(&q);
    let weights = softmax_weights::<B>(q, k, bias, scale);
    B::float_matmul(cast_to::<B>(weights, compute), v)
}

impl<B: SoftmaxAttention, C: CheckpointStrategy> SoftmaxAttention for Autodiff<B, C> {
    fn softmax_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        differentiable_attention::<B, C>(q, k, v, None)
    }

    fn biased_softmax_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        differentiable_attention::<B, C>(q, k, v, Some(bias.into_primitive()))
    }
}

/// `B`'s attention recorded as one autodiff node whose state is the inputs. The bias is a
/// constant (segment masks), so it gets no gradient.
fn differentiable_attention<B: SoftmaxAttention, C: CheckpointStrategy>(
    q: FloatTensor<Autodiff<B, C>>,
    k: FloatTensor<Autodiff<B, C>>,
    v: FloatTensor<Autodiff<B, C>>,
    bias: Option<FloatTensor<B>>,
) -> FloatTensor<Autodiff<B, C>> {
    let forward = |q, k, v, bias: Option<FloatTensor<B>>| match bias {
        Some(bias) => B::biased_softmax_attention(q, k, v, bias),
        None => B::softmax_attention(q, k, v),
    };
    match AttentionBackward
        .prepare::<C>([q.node(), k.node(), v.node()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let (q, k, v) = (q.into_primitive(), k.into_primitive(), v.into_primitive());
            let state = (q.clone(), k.clone(), v.clone(), bias.clone());
            prep.finish(state, forward(q, k, v, bias))
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(
            q.into_primitive(),
            k.into_primitive(),
            v.into_primitive(),
            bias,
        )),
    }
}

/// [`SoftmaxAttention`] on tensors: `softmax(q kᵀ / sqrt(d) + bias) v`, `(B, h, N, d)` inputs,
/// `bias` `(B, 1, N, N)` (`0` where allowed, `-inf` where not) broadcast over heads.
pub fn softmax_attention(
    q: Tensor<4>,
    k: Tensor<4>,
    v: Tensor<4>,
    bias: Option<&Tensor<4>>,
) -> Tensor<4> {
    let (q, k, v) = (q.into_dispatch(), k.into_dispatch(), v.into_dispatch());
    Tensor::from_dispatch(match bias {
        Some(bias) => <Dispatch as SoftmaxAttention>::biased_softmax_attention(
            q,
            k,
            v,
            bias.clone().into_dispatch(),
        ),
        None => <Dispatch as SoftmaxAttention>::softmax_attention(q, k, v),
    })
}

/// The same attention written out op by op, each op differentiated by burn's autodiff, which
/// keeps the scores and weights of every attention until the backward pass: what the model ran
/// before [`SoftmaxAttention`], and the reference its tests and `benches/attention_step.rs`
/// hold it to.
pub fn op_by_op_attention(
    q: Tensor<4>,
    k: Tensor<4>,
    v: Tensor<4>,
    bias: Option<&Tensor<4>>,
) -> Tensor<4> {
    let head_dim = q.dims()[3];
    let scores = (q * (1.0 / (head_dim as f64).sqrt())).matmul(k.swap_dims(2, 3));
    let scores = match bias {
        Some(bias) => scores + bias.clone(),
        None => scores,
    };
    burn::tensor::activation::softmax(scores, 3).matmul(v)
}

#[cfg(test)]
#[path = "attention_tests.rs"]
mod tests;
