//! XFactor's two networks in burn, computing what the authors' JAX release computes.

mod attention;
mod camera;
mod init;
mod layers;
mod multiview;
mod patch;
mod pose_enc;
mod precision;
mod render;
mod rope;

pub use attention::{SoftmaxAttention, op_by_op_attention, softmax_attention};
pub use camera::{REFERENCE_FOCAL, plucker_tokens, rotation_columns};
pub use init::ParamInit;
pub use layers::{Dense, LayerNorm, LayerScale, Mlp2, Mlp3, RmsNorm, gelu_tanh};
pub use multiview::{MultiViewLayer, SegmentMasks, segment_bias};
pub use patch::{patchify, unpatchify};
pub use pose_enc::PoseEnc;
pub use render::{PoseLatents, Render};
pub use rope::RopeTable;

use burn::module::Module;
use burn::tensor::{Device, Tensor};

use settings::model::{ConfigError, XFactorConfig};

/// Both networks, trained jointly and saved as one.
#[derive(Module, Debug)]
pub struct XFactor {
    /// The stereo pose encoder.
    pub pose_enc: PoseEnc,
    /// The renderer.
    pub render: Render,
}

impl XFactor {
    /// Builds a freshly initialised model (the authors' from-scratch initialisation), every
    /// parameter drawn from a stream keyed by `seed` and its position in the model.
    pub fn new(config: &XFactorConfig, seed: u64, device: &Device) -> Result<Self, ConfigError> {
        config.validate()?;
        let mut init = ParamInit::new(seed, device).computing_in(config.compute);
        let pose_enc = PoseEnc::new(config, &mut init);
        let render = Render::new(config, &mut init);
        Ok(Self { pose_enc, render })
    }

    /// Renders each pair's second view from its first, with both poses read from the unmasked
    /// pair: `pair (B, 2, H, W, 3)` -> `(B, H, W, 3)`. This is plain autoencoding and the
    /// fixture's `render_full`.
    pub fn render_pair(&self, pair: Tensor<5>) -> Tensor<4> {
        let poses = self.pose_enc.forward(pair.clone());
        self.render
            .forward(pair.narrow(1, 0, 1), PoseLatents::Single(poses), None)
    }
}
