//! The fused multi-view layer: global attention across all views plus per-view attention, both
//! restricted by segment ids, then a gated MLP.

use burn::module::Module;
use burn::tensor::module::attention;
use burn::tensor::ops::AttentionModuleOptions;
use burn::tensor::{Bool, DType, Tensor};

use super::init::ParamInit;
use super::layers::{Dense, LayerNorm, LayerScale, Mlp2, RmsNorm, gelu_tanh};
use super::rope::RopeTable;

/// Attention masks derived once per forward pass from the tokens' segment ids and shared by
/// every layer. `None` means every token may attend to every other.
#[derive(Debug, Clone)]
pub struct SegmentMasks {
    /// `(B, h, V*T', V*T')`, true where attention is forbidden.
    global: Option<Tensor<4, Bool>>,
    /// `(B*V, h, T', T')`, true where attention is forbidden.
    per_view: Option<Tensor<4, Bool>>,
}

impl SegmentMasks {
    /// No restriction: all tokens share one segment.
    pub fn unrestricted() -> Self {
        Self {
            global: None,
            per_view: None,
        }
    }

    /// Builds the masks from float segment ids `(B, V, T')` for `num_heads` heads.
    pub fn from_segments(segments: Tensor<3>, num_heads: usize) -> Self {
        let [b, v, t] = segments.dims();
        let forbid = |ids: Tensor<2>| -> Tensor<4, Bool> {
            let [rows, n] = ids.dims();
            let query = ids.clone().reshape([rows, n, 1]).expand([rows, n, n]);
            let key = ids.reshape([rows, 1, n]).expand([rows, n, n]);
            (query - key)
                .not_equal_elem(0.0)
                .reshape([rows, 1, n, n])
                .expand([rows, num_heads, n, n])
        };
        Self {
            global: Some(forbid(segments.clone().reshape([b, v * t]))),
            per_view: Some(forbid(segments.reshape([b * v, t]))),
        }
    }
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
    /// Whether q, k, v are rounded to bfloat16 before attention, as in the authors' release.
    pub round_qkv_bf16: bool,
}

impl MultiViewLayer {
    /// A freshly initialised layer of width `width`.
    pub fn new(init: &mut ParamInit, width: usize, num_heads: usize, round_qkv_bf16: bool) -> Self {
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
            round_qkv_bf16,
        }
    }

    /// `z: (B, V, T', C)` -> same shape.
    pub fn forward(&self, z: Tensor<4>, rope: &RopeTable, masks: &SegmentMasks) -> Tensor<4> {
        let [b, v, t, c] = z.dims();
        let (h, d) = (self.num_heads, c / self.num_heads);
        let projected = self
            .qkv
            .forward(self.attn_norm.forward(z.clone()))
            .reshape([b, v, t, 6, h, d]);
        let mut parts = projected
            .chunk(6, 3)
            .into_iter()
            .map(|part| part.reshape([b, v, t, h, d]));
        let mut next = || parts.next().expect("qkv projection splits into six parts");
        let (q, k, val, qs, ks, vs) = (next(), next(), next(), next(), next(), next());
        let q = rope.apply(self.q_norm.forward(q));
        let k = rope.apply(self.k_norm.forward(k));
        let qs = rope.apply(self.qs_norm.forward(qs));
        let ks = rope.apply(self.ks_norm.forward(ks));

        let global_heads = |x: Tensor<5>| self.round(x.reshape([b, v * t, h, d]).swap_dims(1, 2));
        let global = attention(
            global_heads(q),
            global_heads(k),
            global_heads(val),
            masks.global.clone(),
            None,
            AttentionModuleOptions::default(),
        )
        .swap_dims(1, 2)
        .reshape([b, v, t, c]);

        let view_heads = |x: Tensor<5>| self.round(x.reshape([b * v, t, h, d]).swap_dims(1, 2));
        let per_view = attention(
            view_heads(qs),
            view_heads(ks),
            view_heads(vs),
            masks.per_view.clone(),
            None,
            AttentionModuleOptions::default(),
        )
        .swap_dims(1, 2)
        .reshape([b, v, t, c]);

        let attended = self
            .out_proj
            .forward(Tensor::cat(vec![global, per_view], 3));
        let z0 = z + self.attn_scale.forward(attended);
        let mlp_out = self
            .mlp
            .forward(gelu_tanh(self.mlp_norm.forward(z0.clone())));
        z0 + self.mlp_scale.forward(mlp_out)
    }

    fn round(&self, x: Tensor<4>) -> Tensor<4> {
        if self.round_qkv_bf16 {
            x.cast(DType::BF16).cast(DType::F32)
        } else {
            x
        }
    }
}
