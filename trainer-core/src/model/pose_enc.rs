//! PoseEnc: the two-view stereo pose encoder.

use burn::module::{Module, Param};
use burn::tensor::{Tensor, TensorData};

use super::init::ParamInit;
use super::layers::{Dense, LayerNorm, Mlp3, gelu_tanh};
use super::multiview::{MultiViewLayer, SegmentMasks};
use super::patch::patchify;
use super::precision::qkv_precision;
use super::rope::RopeTable;
use settings::XFactorConfig;

/// Standard deviation of the initial `global_embed`.
const GLOBAL_EMBED_STD: f64 = 0.02;

/// Reads one pose latent per view relative to view 0 (the reference), whose pose is exactly zero.
#[derive(Module, Debug)]
pub struct PoseEnc {
    /// Per-patch embedding `3p^2 -> C`.
    pub patch_embed: Dense,
    /// `(G, C)` learned tokens, appended twice to every view.
    pub global_embed: Param<Tensor<2>>,
    /// The multi-view layers.
    pub layers: Vec<MultiViewLayer>,
    /// LayerNorm on the read-out global tokens.
    pub out_norm: LayerNorm,
    /// `[z, z0] (2C) -> Cp`.
    pub pose_head: Mlp3,
    /// Patch side `p`.
    pub patch_size: usize,
    /// Heads `h`, which set RoPE's head size.
    pub num_heads: usize,
}

impl PoseEnc {
    /// A freshly initialised encoder.
    pub fn new(config: &XFactorConfig, init: &mut ParamInit) -> Self {
        let width = config.width;
        Self {
            patch_embed: Dense::new(init, config.patch_values(), width, true),
            global_embed: init.normal([config.global_tokens, width], GLOBAL_EMBED_STD),
            layers: (0..config.pose_layers)
                .map(|_| MultiViewLayer::new(init, width, config.num_heads, qkv_precision(config)))
                .collect(),
            out_norm: LayerNorm::new(init, width, true),
            pose_head: Mlp3::new(init, 2 * width, 4 * width, width, config.pose_dim),
            patch_size: config.patch_size,
            num_heads: config.num_heads,
        }
    }

    /// `images: (B, V, H, W, 3)`, view 0 the reference; `mask: (B, T)` of 0/1.
    ///
    /// Returns `(B, V, 2, Cp)`: slot 0 read from segment-0 pixels, slot 1 from segment-1 pixels.
    pub fn forward_masked(&self, images: Tensor<5>, mask: Tensor<2>) -> Tensor<4> {
        self.encode(images, Some(mask))
    }

    /// Unmasked call: `images: (B, V, H, W, 3)` -> `(B, V, Cp)`.
    pub fn forward(&self, images: Tensor<5>) -> Tensor<3> {
        let latents = self.encode(images, None);
        let [b, v, _, cp] = latents.dims();
        latents.narrow(2, 0, 1).reshape([b, v, cp])
    }

    /// The release's probe input (`return_probe`): `concat(z0, z)` of the unmasked call, the
    /// normalised global tokens before the pose head, `(B, V, 2C)`; `z0` is view 0's.
    pub fn probe_features(&self, images: Tensor<5>) -> Tensor<3> {
        let read_out = self.read_out(images, None);
        let [b, v, _, c] = read_out.dims();
        let z = read_out.narrow(2, 0, 1).reshape([b, v, c]);
        let z0 = z.clone().narrow(1, 0, 1).expand([b, v, c]);
        Tensor::cat(vec![z0, z], 2)
    }

    fn encode(&self, images: Tensor<5>, mask: Option<Tensor<2>>) -> Tensor<4> {
        let read_out = self.read_out(images, mask);
        let [b, v, _, c] = read_out.dims();
        let reference = read_out.clone().narrow(1, 0, 1).expand([b, v, 2, c]);
        let relative = self
            .pose_head
            .forward(Tensor::cat(vec![read_out, reference.clone()], 3));
        let baseline = self
            .pose_head
            .forward(Tensor::cat(vec![reference.clone(), reference], 3));
        relative - baseline
    }

    /// `GELU(LayerNorm(.))` of the first token of each global copy: `(B, V, 2, C)`.
    fn read_out(&self, images: Tensor<5>, mask: Option<Tensor<2>>) -> Tensor<4> {
        let [b, v, height, width, channels] = images.dims();
        let device = images.device();
        let grid = (height / self.patch_size, width / self.patch_size);
        let patches = grid.0 * grid.1;
        let [globals, c] = self.global_embed.dims();
        let head_dim = c / self.num_heads;

        let tokens = self
            .patch_embed
            .forward(patchify(
                images.reshape([b * v, height, width, channels]),
                self.patch_size,
            ))
            .reshape([b, v, patches, c]);
        let global = self
            .global_embed
            .val()
            .reshape([1, 1, globals, c])
            .expand([b, v, globals, c]);
        let mut z = Tensor::cat(vec![tokens, global.clone(), global], 2);

        let patch_segments = match mask {
            Some(mask) => mask.reshape([b, 1, patches]).expand([b, v, patches]),
            None => Tensor::zeros([b, v, patches], &device),
        };
        let copy_segments = Tensor::<1>::from_data(
            TensorData::new(
                [vec![0.0f32; globals], vec![1.0f32; globals]].concat(),
                [2 * globals],
            ),
            &device,
        )
        .reshape([1, 1, 2 * globals])
        .expand([b, v, 2 * globals]);
        let segments = Tensor::cat(vec![patch_segments, copy_segments], 2);
        let masks = SegmentMasks::from_segments(segments);
        let rope = RopeTable::new(grid.0, grid.1, 2 * globals, head_dim, &device);
        for layer in &self.layers {
            z = layer.forward(z, &rope, &masks);
        }

        let first_of_copy = |copy: usize| z.clone().narrow(2, patches + copy * globals, 1);
        let read_out = Tensor::cat(vec![first_of_copy(0), first_of_copy(1)], 2);
        gelu_tanh(self.out_norm.forward(read_out))
    }
}
