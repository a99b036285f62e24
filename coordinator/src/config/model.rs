//! The `model:` section: a preset, and any of its dimensions overridden key by key, so a job
//! can train the paper's model, a smaller study of it or an ablation's bottleneck without code.

use serde::{Deserialize, Serialize};
use settings::XFactorConfig;
use settings::model::{CAMERA_VECTOR_VALUES, ConfigError, PoseConditioning, Precision};

/// A preset and the dimensions that replace its own.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// `tiny`, `small`, `benchmark` or `paper`: the dimensions not set below.
    pub preset: ModelPreset,
    /// Training resolution (defaults to the preset's; `tiny` defaults to 32); a multiple of
    /// `patch_size`.
    #[serde(default)]
    pub image_size: Option<usize>,
    /// Patch side in pixels.
    #[serde(default)]
    pub patch_size: Option<usize>,
    /// Model width `C`.
    #[serde(default)]
    pub width: Option<usize>,
    /// Attention heads; `width / num_heads` must be a multiple of 4 (2D RoPE).
    #[serde(default)]
    pub num_heads: Option<usize>,
    /// Multi-view layers in PoseEnc.
    #[serde(default)]
    pub pose_layers: Option<usize>,
    /// Multi-view layers in Render.
    #[serde(default)]
    pub render_layers: Option<usize>,
    /// Pose-latent size `Cp` (the paper's "Bottleneck" ablation uses 16; `se3_plucker` needs
    /// the camera vector's 10, its default there).
    #[serde(default)]
    pub pose_dim: Option<usize>,
    /// Learned global tokens `G` per PoseEnc view.
    #[serde(default)]
    pub global_tokens: Option<usize>,
    /// Round q/k/v to bfloat16 as the authors' mixed precision does.
    #[serde(default)]
    pub round_qkv_bf16: bool,
    /// The release's mixed precision (`bf16`, as it trains; `f16`; or `f32`, the default): its
    /// rounding points in that half type, with float32 weights and optimizer state.
    #[serde(default)]
    pub precision: Precision,
    /// The type products and attention compute in (`f32`, the default; `bf16` for speed on
    /// tensor cores, as torch's autocast; `f16` is refused, it would need loss scaling), with
    /// float32 weights and optimizer state.
    #[serde(default)]
    pub compute: Precision,
}

/// The model sizes a job can name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelPreset {
    /// Trains in seconds on a laptop CPU.
    Tiny,
    /// The smallest whose pose latents transfer a camera path to another scene after minutes
    /// of CPU training (width 64, 4 heads, 2 + 2 layers, `Cp = 16`, `G = 4`, 32x32).
    Small,
    /// The benchmark model (64x64, width 256).
    Benchmark,
    /// The paper's model (305M parameters).
    Paper,
}

impl ModelConfig {
    /// A preset with none of its dimensions overridden.
    pub fn preset(preset: ModelPreset) -> Self {
        Self {
            preset,
            image_size: None,
            patch_size: None,
            width: None,
            num_heads: None,
            pose_layers: None,
            render_layers: None,
            pose_dim: None,
            global_tokens: None,
            round_qkv_bf16: false,
            precision: Precision::F32,
            compute: Precision::F32,
        }
    }

    /// The model configuration: the preset's with the overrides and Render's `conditioning`
    /// (which the objective variants decide), checked. Under Plücker-ray conditioning `pose_dim`
    /// defaults to the camera vector's size.
    pub fn resolve(&self, conditioning: PoseConditioning) -> Result<XFactorConfig, ConfigError> {
        let mut config = match self.preset {
            ModelPreset::Tiny => XFactorConfig::tiny(32),
            ModelPreset::Small => XFactorConfig::small(32),
            ModelPreset::Benchmark => XFactorConfig::benchmark(),
            ModelPreset::Paper => XFactorConfig::paper(),
        };
        for (slot, value) in [
            (&mut config.image_size, self.image_size),
            (&mut config.patch_size, self.patch_size),
            (&mut config.width, self.width),
            (&mut config.num_heads, self.num_heads),
            (&mut config.pose_layers, self.pose_layers),
            (&mut config.render_layers, self.render_layers),
            (&mut config.pose_dim, self.pose_dim),
            (&mut config.global_tokens, self.global_tokens),
        ] {
            if let Some(value) = value {
                *slot = value;
            }
        }
        config.round_qkv_bf16 = self.round_qkv_bf16;
        config.precision = self.precision;
        config.compute = self.compute;
        config.pose_conditioning = conditioning;
        if conditioning == PoseConditioning::PluckerRays && self.pose_dim.is_none() {
            config.pose_dim = CAMERA_VECTOR_VALUES;
        }
        config.validate().map(|()| config)
    }

    /// The key under `model:` a resolve error is best reported at: the one the file set, of
    /// those the rule relates.
    pub fn key_at_fault(&self, error: &ConfigError) -> &'static str {
        match error {
            ConfigError::Zero { field } => field,
            ConfigError::PatchGrid { .. } if self.patch_size.is_some() => "patch_size",
            ConfigError::PatchGrid { .. } => "image_size",
            ConfigError::HeadSize { .. } if self.num_heads.is_some() => "num_heads",
            ConfigError::HeadSize { .. } => "width",
            ConfigError::CameraVector { .. } => "pose_dim",
            ConfigError::F16Compute => "compute",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_replace_only_the_dimensions_they_name() {
        let mut model = ModelConfig::preset(ModelPreset::Benchmark);
        model.pose_dim = Some(16);
        model.render_layers = Some(2);
        let config = model.resolve(PoseConditioning::Latent).unwrap();
        let mut expected = XFactorConfig::benchmark();
        expected.pose_dim = 16;
        expected.render_layers = 2;
        assert_eq!(config, expected);
    }

    #[test]
    fn a_broken_rule_is_blamed_on_the_key_the_file_set() {
        let mut model = ModelConfig::preset(ModelPreset::Paper);
        model.num_heads = Some(12);
        let error = model.resolve(PoseConditioning::Latent).unwrap_err();
        assert_eq!(model.key_at_fault(&error), "num_heads");
        let mut model = ModelConfig::preset(ModelPreset::Paper);
        model.width = Some(1000);
        let error = model.resolve(PoseConditioning::Latent).unwrap_err();
        assert_eq!(model.key_at_fault(&error), "width");
        let mut model = ModelConfig::preset(ModelPreset::Tiny);
        model.patch_size = Some(5);
        let error = model.resolve(PoseConditioning::Latent).unwrap_err();
        assert_eq!(model.key_at_fault(&error), "patch_size");
    }

    #[test]
    fn plucker_conditioning_reads_a_camera_vector() {
        let mut model = ModelConfig::preset(ModelPreset::Tiny);
        let config = model.resolve(PoseConditioning::PluckerRays).unwrap();
        assert_eq!(config.pose_dim, CAMERA_VECTOR_VALUES);
        assert_eq!(config.pose_conditioning, PoseConditioning::PluckerRays);
        model.pose_dim = Some(16);
        let error = model.resolve(PoseConditioning::PluckerRays).unwrap_err();
        assert_eq!(model.key_at_fault(&error), "pose_dim");
        assert!(
            error.to_string().contains("pose_dim 16 must be 10"),
            "{error}"
        );
    }
}
