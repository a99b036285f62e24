//! Objective settings of both stages and the photometric augmentation they apply to PoseEnc's
//! input. The draws and batches built from them live in trainer-core; here is only what a
//! cluster YAML names and an assignment carries.

use serde::{Deserialize, Serialize};

use crate::model::PoseConditioning;

/// The part every stage objective has: the weight of LPIPS in its loss, which the stage's
/// `lpips_weight` key sets and which decides whether LPIPS weights must be given.
pub trait ObjectiveSettings: Default {
    /// Weight of LPIPS in the loss (`0` trains with L1 alone).
    fn lpips_weight(&self) -> f64;
    /// Sets the weight.
    fn set_lpips_weight(&mut self, weight: f64);
}

/// Ranges and probabilities of the augmentation (defaults: the paper's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AugmentConfig {
    /// Probability of colour jitter.
    pub jitter_probability: f64,
    /// Half-width of the additive brightness shift.
    pub brightness: f64,
    /// Contrast range half-width.
    pub contrast: f64,
    /// Saturation range half-width.
    pub saturation: f64,
    /// Hue range half-width.
    pub hue: f64,
    /// Probability of Gaussian blur.
    pub blur_probability: f64,
    /// Smallest blur sigma.
    pub blur_sigma_min: f64,
    /// Largest blur sigma.
    pub blur_sigma_max: f64,
    /// Blur kernel side (odd).
    pub blur_kernel: usize,
}

impl Default for AugmentConfig {
    fn default() -> Self {
        Self {
            jitter_probability: 0.9,
            brightness: 0.2,
            contrast: 0.2,
            saturation: 0.2,
            hue: 0.05,
            blur_probability: 0.3,
            blur_sigma_min: 0.1,
            blur_sigma_max: 2.0,
            blur_kernel: 7,
        }
    }
}

/// The objective a stage trains, each a function of the same model parts (PoseEnc, Render)
/// and batches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObjectiveVariant {
    /// XFactor's transferability objective: quadrant masks, the slot swap and self-decoding at
    /// the stage's probabilities.
    #[default]
    Transfer,
    /// Plain autoencoding, the paper's "Unconstrained" ablation (with `model.pose_dim: 16`,
    /// its "Bottleneck"): PoseEnc reads the target's latent against the reference and Render
    /// draws the target from the context with it; no mask, no swap, no self-decoding. The
    /// draws are made as for `transfer` (the augmentation is the same) and then overridden.
    Autoencode,
    /// The paper's "SE(3) & Plücker" ablation (after RayZer): plain autoencoding as
    /// `autoencode`, with PoseEnc's head reading an explicit camera for each view (a relative
    /// SE(3) pose and a focal length; see `PoseConditioning::PluckerRays`) and Render
    /// conditioned on the Plücker ray maps of those cameras instead of latents. A job that
    /// names it in either stage builds its model that way.
    Se3Plucker,
    /// Stage 1 only: the transfer objective with one more context view given to Render.
    /// Samples have three frames in window order: the reference, the extra view, the target;
    /// PoseEnc reads the extra view and the target each against the reference, in its own
    /// pair, as stage 2 does.
    ExtraViewDecoder,
    /// Stage 1 only: as `extra_view_decoder`, and PoseEnc sees the extra view too: it reads the
    /// reference, the extra view and the target in one multi-view pass (one augmentation for
    /// all three).
    ExtraViewEncoderDecoder,
}

impl ObjectiveVariant {
    /// Frames per stage-1 sample: 3 for the extra-view variants, else the pair.
    pub fn stage1_frames(self) -> usize {
        match self {
            Self::ExtraViewDecoder | Self::ExtraViewEncoderDecoder => 3,
            Self::Transfer | Self::Autoencode | Self::Se3Plucker => 2,
        }
    }

    /// Whether samples get XFactor's quadrant masks, slot swap and self-decoding; the
    /// autoencoding ablations have none of them.
    pub fn transferability(self) -> bool {
        !matches!(self, Self::Autoencode | Self::Se3Plucker)
    }

    /// How the model this variant trains conditions Render on poses.
    pub fn pose_conditioning(self) -> PoseConditioning {
        match self {
            Self::Se3Plucker => PoseConditioning::PluckerRays,
            _ => PoseConditioning::Latent,
        }
    }

    /// Whether the variant only makes sense in stage 1 (stage 2 has several context views
    /// already).
    pub fn stage1_only(self) -> bool {
        self.stage1_frames() == 3
    }
}

/// Stage-1 probabilities (defaults: the paper's) and the augmentation of PoseEnc's input.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Stage1Config {
    /// Probability that the target is replaced by the context (self-decode).
    pub self_decode_probability: f64,
    /// Probability that no quadrant is marked (plain autoencoding).
    pub unmasked_probability: f64,
    /// Weight of LPIPS in the loss (`0` trains with L1 alone).
    pub lpips_weight: f64,
    /// Photometric augmentation of PoseEnc's input.
    pub augment: AugmentConfig,
    /// The objective (default: XFactor's).
    pub variant: ObjectiveVariant,
}

impl Default for Stage1Config {
    fn default() -> Self {
        Self {
            self_decode_probability: 0.05,
            unmasked_probability: 0.05,
            lpips_weight: 0.5,
            augment: AugmentConfig::default(),
            variant: ObjectiveVariant::Transfer,
        }
    }
}

/// Stage-2 settings (defaults: the paper's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Stage2Config {
    /// Frames per sample: context views plus the target.
    pub views: usize,
    /// Probability that the target is replaced by a random context frame.
    pub self_decode_probability: f64,
    /// Probability that no quadrant is marked.
    pub unmasked_probability: f64,
    /// Weight of LPIPS in the loss.
    pub lpips_weight: f64,
    /// Photometric augmentation of PoseEnc's input.
    pub augment: AugmentConfig,
    /// Start Render from stage 1's weights too (the paper's text). Off by default: the release
    /// loads only PoseEnc from stage 1 and initialises Render afresh.
    pub render_from_stage1: bool,
    /// The objective (default: XFactor's).
    pub variant: ObjectiveVariant,
}

impl Default for Stage2Config {
    fn default() -> Self {
        Self {
            views: 6,
            self_decode_probability: 0.02,
            unmasked_probability: 0.05,
            lpips_weight: 0.5,
            augment: AugmentConfig::default(),
            render_from_stage1: false,
            variant: ObjectiveVariant::Transfer,
        }
    }
}

impl ObjectiveSettings for Stage1Config {
    fn lpips_weight(&self) -> f64 {
        self.lpips_weight
    }
    fn set_lpips_weight(&mut self, weight: f64) {
        self.lpips_weight = weight;
    }
}

impl ObjectiveSettings for Stage2Config {
    fn lpips_weight(&self) -> f64 {
        self.lpips_weight
    }
    fn set_lpips_weight(&mut self, weight: f64) {
        self.lpips_weight = weight;
    }
}
