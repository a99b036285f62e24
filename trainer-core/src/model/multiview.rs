//! The fused multi-view layer: global attention across all views plus per-view attention, both
//! restricted by segment ids, then a gated MLP.

use burn::module::{Module, Param};
use burn::tensor::Tensor;

use super::attention::softmax_attention;
use super::init::ParamInit;
use super::layers::{Dense, LayerNorm, LayerScale, Mlp2, RmsNorm, gelu_tanh, rms_normalize};
use super::precision::{self, from_compute, linear_in, to_compute};
use super::rope::RopeTable;
use settings::model::Precision;

/// Additive attention biases derived once per forward pass from the tokens' segment ids and
/// shared by every layer: `0` where attention is allowed, `-inf` where segments differ. `None`
/// means every token may attend to every other.
#[derive(Debug, Clone)]
pub struct SegmentMasks {
    /// `(B, 1, V*T', V*T')`, broadcast over heads.
    global: Option<Tensor<4>>,
    /// `(B*V, 1, T', T')`, broadcast over heads.
    per_view: Option<Tensor<4>>,
}

impl SegmentMasks {
    /// No restriction: all tokens share one segment.
    pub fn unrestricted() -> Self {
        Self {
            global: None,
            per_view: None,
        }
    }

    /// Builds the biases from float segment ids `(B, V, T')`.
    pub fn from_segments(segments: Tensor<3>) -> Self {
        let [b, v, t] = segments.dims();
        Self {
            global: Some(segment_bias(segments.clone().reshape([b, v * t]))),
            per_view: Some(segment_bias(segments.reshape([b * v, t]))),
        }
    }
}

/// The additive attention bias of float segment ids `(rows, n)`: `(rows, 1, n, n)`, `0` where
/// query and key share a segment and `-inf` where they do not.
pub fn segment_bias(ids: Tensor<2>) -> Tensor<4> {
    let [rows, n] = ids.dims();
    let query = ids.clone().reshape([rows, n, 1]).expand([rows, n, n]);
    let key = ids.reshape([rows, 1, n]).expand([rows, n, n]);
    let forbidden = (query - key).not_equal_elem(0.0);
    Tensor::zeros([rows, n, n], &forbidden.device())
        .mask_fill(forbidden, f32::NEG_INFINITY)
        .reshape([rows, 1, n, n])
}

/// One multi-view transformer layer (see SPEC "Multi-view layer").
#[derive(Module, Debug)]
pub struct MultiViewLayer {
    /// Pre-attention LayerNorm, scale only.
    pub attn_norm: LayerNorm,
    /// Fused projection to `q, k, v, qs, ks, vs`.
    pub qkv: Dense,
    /// RMSNorm on global queries.
    pub q_norm: RmsNorm,
    /// RMSNorm on global keys.
    pub k_norm: RmsNorm,
    /// RMSNorm on per-view queries.
    pub qs_norm: RmsNorm,
    /// RMSNorm on per-view keys.
    pub ks_norm: RmsNorm,
    /// `2C -> C` projection of both attention outputs.
    pub out_proj: Dense,
    /// Gate on the attention branch.
    pub attn_scale: LayerScale,
    /// LayerNorm (scale and bias) before the MLP.
    pub mlp_norm: LayerNorm,
    /// `C -> 4C -> C` MLP.
    pub mlp: Mlp2,
    /// Gate on the MLP branch.
    pub mlp_scale: LayerScale,
    /// Heads `h`.
    pub num_heads: usize,
    /// The half type q, k, v are rounded to before attention, as in the authors' release.
    #[module(skip)]
    pub qkv_precision: Precision,
}

impl MultiViewLayer {
    /// A freshly initialised layer of width `width`.
    pub fn new(
        init: &mut ParamInit,
        width: usize,
        num_heads: usize,
        qkv_precision: Precision,
    ) -> Self {
        let head_dim = width / num_heads;
        Self {
            attn_norm: LayerNorm::new(init, width, false),
            qkv: Dense::new(init, width, 6 * width, false),
            q_norm: RmsNorm::new(init, num_heads, head_dim),
            k_norm: RmsNorm::new(init, num_heads, head_dim),
            qs_norm: RmsNorm::new(init, num_heads, head_dim),
            ks_norm: RmsNorm::new(init, num_heads, head_dim),
            out_proj: Dense::new(init, 2 * width, width, true),
            attn_scale: LayerScale::new(init, width),
            mlp_norm: LayerNorm::new(init, width, true),
            mlp: Mlp2::new(init, width, 4 * width, width),
            mlp_scale: LayerScale::new(init, width),
            num_heads,
            qkv_precision,
        }
    }

    /// `z: (B, V, T', C)` -> same shape.
    pub fn forward(&self, z: Tensor<4>, rope: &RopeTable, masks: &SegmentMasks) -> Tensor<4> {
        let [b, v, t, c] = z.dims();
        let (h, d) = (self.num_heads, c / self.num_heads);
        let normed = self.attn_norm.forward(z.clone());
        // The fused `C -> 6C` projection is applied as three products with column blocks of its
        // kernel, so q, k, qs, ks come out as one contiguous (B, V, T', 4, h, d) tensor to be
        // normalised and rotated together, with no copy of the activations.
        let compute = self.qkv.compute;
        let kernel = self.qkv.kernel.val();
        let columns = |start: usize, count: usize| kernel.clone().narrow(1, start * c, count * c);
        let project = |weight: Tensor<2>| linear_in(normed.clone(), weight, None, compute);
        let queries_keys =
            project(Tensor::cat(vec![columns(0, 2), columns(3, 2)], 1)).reshape([b, v, t, 4, h, d]);
        let values = project(columns(2, 1));
        let view_values = project(columns(5, 1));
        let alphas = Tensor::stack::<3>(
            vec![
                self.q_norm.alpha.val(),
                self.k_norm.alpha.val(),
                self.qs_norm.alpha.val(),
                self.ks_norm.alpha.val(),
            ],
            0,
        );
        let queries_keys = rope.apply(rms_normalize(queries_keys, alphas.unsqueeze::<6>()));
        let part = |index: usize| queries_keys.clone().narrow(3, index, 1);

        // q, k, v in the compute type after the release's rounding; the output back in float32.
        let heads = |x: Tensor<6>, rows: usize, tokens: usize| {
            to_compute(
                self.round(x.reshape([rows, tokens, h, d]).swap_dims(1, 2)),
                compute,
            )
        };
        let global_heads = |x: Tensor<6>| heads(x, b, v * t);
        let global = softmax_attention(
            global_heads(part(0)),
            global_heads(part(1)),
            global_heads(values.reshape([b, v, t, 1, h, d])),
            masks.global.as_ref(),
        );
        let global = from_compute(global, compute)
            .swap_dims(1, 2)
            .reshape([b, v, t, c]);

        let view_heads = |x: Tensor<6>| heads(x, b * v, t);
        let per_view = softmax_attention(
            view_heads(part(2)),
            view_heads(part(3)),
            view_heads(view_values.reshape([b, v, t, 1, h, d])),
            masks.per_view.as_ref(),
        );
        let per_view = from_compute(per_view, compute)
            .swap_dims(1, 2)
            .reshape([b, v, t, c]);

        // The `2C -> C` output projection of concat(global, per_view), as two products with the
        // kernel's row blocks instead of materialising the concatenation.
        let out_kernel = self.out_proj.kernel.val();
        let attended = linear_in(global, out_kernel.clone().narrow(0, 0, c), None, compute)
            + linear_in(
                per_view,
                out_kernel.narrow(0, c, c),
                self.out_proj.bias.as_ref().map(Param::val),
                compute,
            );
        let z0 = z + self.attn_scale.forward(attended);
        let mlp_out = self
            .mlp
            .forward(gelu_tanh(self.mlp_norm.forward(z0.clone())));
        z0 + self.mlp_scale.forward(mlp_out)
    }

    fn round(&self, x: Tensor<4>) -> Tensor<4> {
        precision::round(x, self.qkv_precision)
    }
}
