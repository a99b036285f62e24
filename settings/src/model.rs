//! The model's hyper-parameters and their validation.

use serde::{Deserialize, Serialize};

/// Every size that shapes XFactor's two networks.
///
/// The same struct is embedded in cluster YAML files, written beside checkpoints and read from
/// fixture JSON, so a model can always be rebuilt from what sits next to its weights.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct XFactorConfig {
    /// Square training image side in pixels (`H = W`); must be a multiple of `patch_size`.
    pub image_size: usize,
    /// Patch side `p`; tokens carry `3 p^2` pixel values.
    pub patch_size: usize,
    /// Model width `C`.
    pub width: usize,
    /// Attention heads `h`; `C / h` must be a multiple of 4 for 2D RoPE.
    pub num_heads: usize,
    /// Multi-view layers in PoseEnc.
    pub pose_layers: usize,
    /// Multi-view layers in Render.
    pub render_layers: usize,
    /// Pose-latent size `Cp`.
    pub pose_dim: usize,
    /// Learned global tokens `G` appended (twice) to every PoseEnc view.
    pub global_tokens: usize,
    /// Round q, k, v to bfloat16 before attention as the authors' release does; off by default
    /// because the float32 model is the reference.
    #[serde(default)]
    pub round_qkv_bf16: bool,
    /// What Render is conditioned on: XFactor's pose latents (default), or the Plücker ray maps
    /// of explicit cameras (the `se3_plucker` ablation).
    #[serde(default)]
    pub pose_conditioning: PoseConditioning,
    /// Where the release's mixed precision rounds, in which half type (SPEC "Mixed precision
    /// in the release"); `f32` (the default) rounds nowhere. Weights, gradients and the
    /// optimizer's state stay float32 whatever this says.
    #[serde(default)]
    pub precision: Precision,
    /// The type matrix products and attention compute in, as torch's autocast: `f32` (the
    /// default, the parity reference), or `bf16` for speed on tensor cores (`f16` is refused:
    /// it would need loss scaling). Weights, gradients, the optimizer's state, norms, the
    /// softmax and the loss stay float32.
    #[serde(default)]
    pub compute: Precision,
}

/// The float type of the release's mixed-precision points: q/k/v before attention, and
/// Render's input pixels, RoPE table, final LayerNorm, pixel head and sigmoid. Each is
/// rounded to this type; everything else (and every weight) stays float32.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// No rounding: the float32 model, the reference.
    #[default]
    F32,
    /// bfloat16, as the release trains (`MIXED=True`).
    Bf16,
    /// IEEE half, for devices whose half is f16 (bf16 is storage-only on some Vulkan drivers).
    F16,
}

impl Precision {
    /// The YAML spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
            Self::F16 => "f16",
        }
    }
}

/// Values in the explicit camera vector PoseEnc reads for a view under
/// [`PoseConditioning::PluckerRays`]: a 6-d rotation, a translation and a log focal length.
pub const CAMERA_VECTOR_VALUES: usize = 10;

/// Values per pixel of a Plücker ray map: the unit direction and the moment.
pub const PLUCKER_VALUES: usize = 6;

/// How a view's pose reaches Render.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseConditioning {
    /// Each token carries its view's `Cp`-d pose latent (XFactor).
    #[default]
    Latent,
    /// PoseEnc's `Cp = 10` output is read as an explicit camera (relative SE(3) pose and focal
    /// length) and each token carries the Plücker rays of its pixels (after RayZer).
    PluckerRays,
}

/// A configuration that cannot build a model, with the field at fault.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ConfigError {
    /// A size that must be positive is zero.
    #[error("model config: `{field}` must be positive")]
    Zero {
        /// The offending field.
        field: &'static str,
    },
    /// `image_size` does not split into whole patches.
    #[error("model config: image_size {image_size} is not a multiple of patch_size {patch_size}")]
    PatchGrid {
        /// Configured image side.
        image_size: usize,
        /// Configured patch side.
        patch_size: usize,
    },
    /// Width does not split evenly into heads whose size RoPE can rotate.
    #[error(
        "model config: width {width} / num_heads {num_heads} must be a whole head size divisible by 4 (2D RoPE)"
    )]
    HeadSize {
        /// Configured width.
        width: usize,
        /// Configured head count.
        num_heads: usize,
    },
    /// Plücker-ray conditioning reads PoseEnc's output as a camera vector of fixed size.
    #[error(
        "model config: pose_dim {pose_dim} must be {CAMERA_VECTOR_VALUES} (6-d rotation, translation, log focal length) when Render is conditioned on Plücker rays"
    )]
    CameraVector {
        /// Configured pose-latent size.
        pose_dim: usize,
    },
    /// Products in f16 need their gradients scaled up (torch's GradScaler), which the trainer
    /// does not do: float32 gradients cast to f16 underflow.
    #[error(
        "model config: compute f16 needs loss scaling, which the trainer does not do (the paper model's LayerScale branches get gradients near 5e-9, below f16's smallest value); use compute bf16, whose range is float32's"
    )]
    F16Compute,
}

impl XFactorConfig {
    /// Version of this struct's serialised form. Processes that exchange configurations (the
    /// coordinator and its workers) refuse each other when it differs.
    pub const SCHEMA_VERSION: u32 = 2;

    /// The paper's configuration: width 1024, 16 heads, patch 16, 8 + 8 layers, `Cp = 256`,
    /// 256x256 images, `G = 32`.
    pub fn paper() -> Self {
        Self {
            image_size: 256,
            patch_size: 16,
            width: 1024,
            num_heads: 16,
            pose_layers: 8,
            render_layers: 8,
            pose_dim: 256,
            global_tokens: 32,
            round_qkv_bf16: false,
            pose_conditioning: PoseConditioning::Latent,
            precision: Precision::F32,
            compute: Precision::F32,
        }
    }

    /// The benchmark configuration: 64x64, patch 8, width 256, 8 heads, 4 + 4 layers,
    /// `Cp = 64`, `G = 8`. Small enough to train on a laptop CPU.
    pub fn benchmark() -> Self {
        Self {
            image_size: 64,
            patch_size: 8,
            width: 256,
            num_heads: 8,
            pose_layers: 4,
            render_layers: 4,
            pose_dim: 64,
            global_tokens: 8,
            round_qkv_bf16: false,
            pose_conditioning: PoseConditioning::Latent,
            precision: Precision::F32,
            compute: Precision::F32,
        }
    }

    /// The smallest model whose renderer learns to follow camera motion within a minute or so
    /// of CPU training (patch 4, width 64, 4 heads, 2 + 2 layers, `Cp = 16`, `G = 4`): the
    /// learning and evaluation tests.
    pub fn small(image_size: usize) -> Self {
        Self {
            image_size,
            patch_size: 4,
            width: 64,
            num_heads: 4,
            pose_layers: 2,
            render_layers: 2,
            pose_dim: 16,
            global_tokens: 4,
            round_qkv_bf16: false,
            pose_conditioning: PoseConditioning::Latent,
            precision: Precision::F32,
            compute: Precision::F32,
        }
    }

    /// A model small enough to train in seconds on a laptop CPU (patch 4, width 32, 2 heads,
    /// 1 + 1 layers, `Cp = 8`, `G = 2`): tests, demos and smoke runs.
    pub fn tiny(image_size: usize) -> Self {
        Self {
            image_size,
            patch_size: 4,
            width: 32,
            num_heads: 2,
            pose_layers: 1,
            render_layers: 1,
            pose_dim: 8,
            global_tokens: 2,
            round_qkv_bf16: false,
            pose_conditioning: PoseConditioning::Latent,
            precision: Precision::F32,
            compute: Precision::F32,
        }
    }

    /// Checks every constraint the networks rely on.
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (field, value) in [
            ("image_size", self.image_size),
            ("patch_size", self.patch_size),
            ("width", self.width),
            ("num_heads", self.num_heads),
            ("pose_layers", self.pose_layers),
            ("render_layers", self.render_layers),
            ("pose_dim", self.pose_dim),
            ("global_tokens", self.global_tokens),
        ] {
            if value == 0 {
                return Err(ConfigError::Zero { field });
            }
        }
        if !self.image_size.is_multiple_of(self.patch_size) {
            return Err(ConfigError::PatchGrid {
                image_size: self.image_size,
                patch_size: self.patch_size,
            });
        }
        if !self.width.is_multiple_of(self.num_heads)
            || !(self.width / self.num_heads).is_multiple_of(4)
        {
            return Err(ConfigError::HeadSize {
                width: self.width,
                num_heads: self.num_heads,
            });
        }
        if self.pose_conditioning == PoseConditioning::PluckerRays
            && self.pose_dim != CAMERA_VECTOR_VALUES
        {
            return Err(ConfigError::CameraVector {
                pose_dim: self.pose_dim,
            });
        }
        if self.compute == Precision::F16 {
            return Err(ConfigError::F16Compute);
        }
        Ok(())
    }

    /// Head size `d = C / h`.
    pub fn head_dim(&self) -> usize {
        self.width / self.num_heads
    }

    /// Patches per image side.
    pub fn grid_side(&self) -> usize {
        self.image_size / self.patch_size
    }

    /// Patch tokens per view, `T`.
    pub fn tokens_per_view(&self) -> usize {
        self.grid_side() * self.grid_side()
    }

    /// Values per patch token, `3 p^2`.
    pub fn patch_values(&self) -> usize {
        3 * self.patch_size * self.patch_size
    }

    /// Values of the pose each Render token carries: the latent `Cp`, or the `6 p^2` Plücker
    /// values of the patch's pixels.
    pub fn pose_token_values(&self) -> usize {
        match self.pose_conditioning {
            PoseConditioning::Latent => self.pose_dim,
            PoseConditioning::PluckerRays => PLUCKER_VALUES * self.patch_size * self.patch_size,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_are_valid() {
        XFactorConfig::paper().validate().unwrap();
        XFactorConfig::benchmark().validate().unwrap();
    }

    #[test]
    fn bad_sizes_name_the_culprit() {
        let mut c = XFactorConfig::benchmark();
        c.image_size = 60;
        assert!(matches!(c.validate(), Err(ConfigError::PatchGrid { .. })));
        let mut c = XFactorConfig::benchmark();
        c.num_heads = 16;
        c.width = 96;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("num_heads 16")
        );
        let mut c = XFactorConfig::benchmark();
        c.pose_dim = 0;
        assert_eq!(c.validate(), Err(ConfigError::Zero { field: "pose_dim" }));
        let mut c = XFactorConfig::tiny(16);
        c.pose_conditioning = PoseConditioning::PluckerRays;
        assert_eq!(c.validate(), Err(ConfigError::CameraVector { pose_dim: 8 }));
        c.pose_dim = CAMERA_VECTOR_VALUES;
        c.validate().unwrap();
        assert_eq!(c.pose_token_values(), 6 * 16);
        let mut c = XFactorConfig::tiny(16);
        c.compute = Precision::F16;
        assert_eq!(c.validate(), Err(ConfigError::F16Compute));
        c.compute = Precision::Bf16;
        c.validate().unwrap();
    }

    #[test]
    fn configs_written_before_plucker_conditioning_read_as_latent() {
        let mut json = serde_json::to_value(XFactorConfig::tiny(16)).unwrap();
        json.as_object_mut().unwrap().remove("pose_conditioning");
        let read: XFactorConfig = serde_json::from_value(json).unwrap();
        assert_eq!(read, XFactorConfig::tiny(16));
    }
}
