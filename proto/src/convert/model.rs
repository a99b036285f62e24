//! The model's configuration on the wire.

use settings::XFactorConfig;
use settings::model::{PoseConditioning, Precision};

use super::size;
use crate::v1;

impl From<&XFactorConfig> for v1::ModelConfig {
    fn from(c: &XFactorConfig) -> Self {
        Self {
            image_size: c.image_size as u64,
            patch_size: c.patch_size as u64,
            width: c.width as u64,
            num_heads: c.num_heads as u64,
            pose_layers: c.pose_layers as u64,
            render_layers: c.render_layers as u64,
            pose_dim: c.pose_dim as u64,
            global_tokens: c.global_tokens as u64,
            round_qkv_bf16: c.round_qkv_bf16,
            plucker_ray_conditioning: c.pose_conditioning == PoseConditioning::PluckerRays,
            precision: precision_to_wire(c.precision),
            compute: precision_to_wire(c.compute),
        }
    }
}

impl From<&v1::ModelConfig> for XFactorConfig {
    fn from(m: &v1::ModelConfig) -> Self {
        Self {
            image_size: size(m.image_size),
            patch_size: size(m.patch_size),
            width: size(m.width),
            num_heads: size(m.num_heads),
            pose_layers: size(m.pose_layers),
            render_layers: size(m.render_layers),
            pose_dim: size(m.pose_dim),
            global_tokens: size(m.global_tokens),
            round_qkv_bf16: m.round_qkv_bf16,
            pose_conditioning: if m.plucker_ray_conditioning {
                PoseConditioning::PluckerRays
            } else {
                PoseConditioning::Latent
            },
            precision: precision_from_wire(m.precision),
            compute: precision_from_wire(m.compute),
        }
    }
}

fn precision_to_wire(precision: Precision) -> i32 {
    let wire = match precision {
        Precision::F32 => v1::Precision::F32,
        Precision::Bf16 => v1::Precision::Bf16,
        Precision::F16 => v1::Precision::F16,
    };
    wire as i32
}

/// Both ends speak the same PROTOCOL_VERSION, so every value is known; an unknown one could
/// only be f32's zero.
fn precision_from_wire(value: i32) -> Precision {
    match v1::Precision::try_from(value) {
        Ok(v1::Precision::Bf16) => Precision::Bf16,
        Ok(v1::Precision::F16) => Precision::F16,
        Ok(v1::Precision::F32) | Err(_) => Precision::F32,
    }
}
