//! Render: decodes the target view from context views and per-view pose latents.

use burn::module::Module;
use burn::tensor::Tensor;
use burn::tensor::activation::sigmoid;

use super::camera::plucker_tokens;
use super::init::ParamInit;
use super::layers::{LayerNorm, Mlp2, Mlp3, gelu_tanh};
use super::multiview::{MultiViewLayer, SegmentMasks};
use super::patch::{patchify, unpatchify};
use super::precision::{qkv_precision, round};
use super::rope::RopeTable;
use settings::XFactorConfig;
use settings::model::{CAMERA_VECTOR_VALUES, PoseConditioning, Precision};

/// Pose latents handed to Render, one per view with the target's last. Under Plücker-ray
/// conditioning they are camera vectors (see [`super::camera`]).
#[derive(Debug, Clone)]
pub enum PoseLatents {
    /// `(B, V, 2, Cp)`: a latent per mask segment; each patch takes the one of its segment.
    PerSegment(Tensor<4>),
    /// `(B, V, Cp)`: one latent for every patch of a view.
    Single(Tensor<3>),
}

/// The monocular (one context view) or multi-view (several) renderer.
#[derive(Module, Debug)]
pub struct Render {
    /// `concat(patch, pose) -> C` lift of context tokens.
    pub context_lift: Mlp2,
    /// `pose -> C` lift of target tokens.
    pub target_lift: Mlp2,
    /// The multi-view layers.
    pub layers: Vec<MultiViewLayer>,
    /// LayerNorm before the pixel head.
    pub out_norm: LayerNorm,
    /// `C -> 3p^2` pixel head.
    pub pixel_head: Mlp3,
    /// Patch side `p`.
    pub patch_size: usize,
    /// Heads `h`, which set RoPE's head size.
    pub num_heads: usize,
    /// Whether tokens carry latents or the Plücker rays of cameras.
    #[module(skip)]
    pub conditioning: PoseConditioning,
    /// Where the release's mixed precision rounds Render: its input pixels, RoPE table, final
    /// LayerNorm, pixel head and sigmoid.
    #[module(skip)]
    pub precision: Precision,
}

impl Render {
    /// A freshly initialised renderer.
    pub fn new(config: &XFactorConfig, init: &mut ParamInit) -> Self {
        let width = config.width;
        Self {
            context_lift: Mlp2::new(
                init,
                config.patch_values() + config.pose_token_values(),
                4 * width,
                width,
            ),
            target_lift: Mlp2::new(init, config.pose_token_values(), 4 * width, width),
            layers: (0..config.render_layers)
                .map(|_| MultiViewLayer::new(init, width, config.num_heads, qkv_precision(config)))
                .collect(),
            out_norm: LayerNorm::new(init, width, true),
            pixel_head: Mlp3::new(init, width, 4 * width, width, config.patch_values()),
            patch_size: config.patch_size,
            num_heads: config.num_heads,
            conditioning: config.pose_conditioning,
            precision: config.precision,
        }
    }

    /// `context: (B, V-1, H, W, 3)`, `poses` for all `V` views (target last; camera vectors
    /// under Plücker-ray conditioning, turned into ray maps here), optional patch
    /// `mask: (B, T)` of 0/1 used both to pick per-segment latents and as segment ids.
    /// Returns the target image `(B, H, W, 3)` in `[-1, 1]`.
    pub fn forward(
        &self,
        context: Tensor<5>,
        poses: PoseLatents,
        mask: Option<Tensor<2>>,
    ) -> Tensor<4> {
        let [b, contexts, height, width, channels] = context.dims();
        let views = contexts + 1;
        let device = context.device();
        let grid = (height / self.patch_size, width / self.patch_size);
        let patches = grid.0 * grid.1;

        let token_poses = self.token_poses(poses, mask.as_ref(), b, contexts, grid);

        let context_patches = patchify(
            round(
                context.reshape([b * contexts, height, width, channels]),
                self.precision,
            ),
            self.patch_size,
        )
        .reshape([
            b,
            contexts,
            patches,
            self.patch_size * self.patch_size * channels,
        ]);
        let context_tokens = self.context_lift.forward(Tensor::cat(
            vec![context_patches, token_poses.clone().narrow(1, 0, contexts)],
            3,
        ));
        let target_tokens = self.target_lift.forward(token_poses.narrow(1, contexts, 1));
        let mut z = Tensor::cat(vec![context_tokens, target_tokens], 1);
        let c = z.dims()[3];

        let masks = match mask {
            Some(mask) => SegmentMasks::from_segments(
                mask.reshape([b, 1, patches]).expand([b, views, patches]),
            ),
            None => SegmentMasks::unrestricted(),
        };
        let rope =
            RopeTable::new(grid.0, grid.1, 0, c / self.num_heads, &device).rounded(self.precision);
        for layer in &self.layers {
            z = layer.forward(z, &rope, &masks);
        }

        let target = z.narrow(1, contexts, 1).reshape([b, patches, c]);
        unpatchify(self.pixels(target), self.patch_size, height)
    }

    /// Pulled out of [`Self::forward`]: the pose token of every patch of every view for
    /// `V = contexts + 1` views on a `grid` of `T` patches. Each patch takes its view's single
    /// latent, or the latent of its segment in `mask: (B, T)` (segment 0 without a mask), giving
    /// `(B, V, T, Cp)`; under Plücker-ray conditioning those camera vectors become ray tokens
    /// `(B, V, T, 6 p^2)`.
    fn token_poses(
        &self,
        poses: PoseLatents,
        mask: Option<&Tensor<2>>,
        b: usize,
        contexts: usize,
        grid: (usize, usize),
    ) -> Tensor<4> {
        let views = contexts + 1;
        let patches = grid.0 * grid.1;
        let token_poses = match poses {
            PoseLatents::Single(poses) => {
                let [_, _, cp] = poses.dims();
                poses
                    .reshape([b, views, 1, cp])
                    .expand([b, views, patches, cp])
            }
            PoseLatents::PerSegment(poses) => {
                let [_, _, _, cp] = poses.dims();
                let slot = |i: usize| poses.clone().narrow(2, i, 1);
                match mask {
                    Some(mask) => {
                        let m = mask.clone().reshape([b, 1, patches, 1]);
                        slot(0) * (m.clone().neg() + 1.0) + slot(1) * m
                    }
                    None => slot(0).expand([b, views, patches, cp]),
                }
            }
        };
        match self.conditioning {
            PoseConditioning::Latent => token_poses,
            PoseConditioning::PluckerRays => {
                // Every view takes the target's focal length, patch by patch (so a segment's
                // camera keeps its own intrinsics through the swap).
                let focal = token_poses
                    .clone()
                    .narrow(1, contexts, 1)
                    .narrow(3, CAMERA_VECTOR_VALUES - 1, 1)
                    .expand([b, views, patches, 1]);
                plucker_tokens(token_poses, focal, self.patch_size, grid.0)
            }
        }
    }

    /// The target tokens `(B, T, C)` to patch pixels `(B, T, 3 p^2)` in `[-1, 1]`: final
    /// LayerNorm, pixel head and sigmoid, each rounded where the mixed precision says.
    fn pixels(&self, target: Tensor<3>) -> Tensor<3> {
        let normed = round(self.out_norm.forward(target), self.precision);
        let pixels = round(self.pixel_head.forward(gelu_tanh(normed)), self.precision);
        (round(sigmoid(pixels), self.precision) - 0.5) * 2.0
    }
}
