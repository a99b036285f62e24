//! Stage 1: the stereo-monocular transferability objective.
//!
//! Every random choice for global sample `i` of step `s` comes from a stream keyed by
//! `(seed, s, i)`, so which process or thread builds a sample never changes it.

use burn::tensor::{Device, Tensor, TensorData};

use crate::augment::{AugmentConfig, Image};
use crate::lpips::Lpips;
use crate::model::{PoseLatents, XFactor};
use crate::rng::Stream;

/// Tag that separates stage-1 draws from every other use of the same `(seed, step, sample)`.
const STAGE1_STREAM: u64 = 0x5354_4147_4531;

/// Stage-1 probabilities (defaults: the paper's) and the augmentation of PoseEnc's input.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
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
}

impl Default for Stage1Config {
    fn default() -> Self {
        Self {
            self_decode_probability: 0.05,
            unmasked_probability: 0.05,
            lpips_weight: 0.5,
            augment: AugmentConfig::default(),
        }
    }
}

/// The quadrants of the patch grid marked as segment 1: two of the four, or none.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QuadrantMask {
    /// Marked quadrants in order top-left, top-right, bottom-left, bottom-right.
    pub marked: [bool; 4],
}

impl QuadrantMask {
    /// The six ways of marking two quadrants.
    const PAIRS: [[bool; 4]; 6] = [
        [true, true, false, false],
        [true, false, true, false],
        [true, false, false, true],
        [false, true, true, false],
        [false, true, false, true],
        [false, false, true, true],
    ];

    /// Whether nothing is marked.
    pub fn is_empty(&self) -> bool {
        !self.marked.iter().any(|&m| m)
    }

    /// The `grid x grid` patch mask, row-major, `1.0` on marked quadrants.
    pub fn patch_mask(&self, grid: usize) -> Vec<f32> {
        let half = grid / 2;
        (0..grid * grid)
            .map(|i| {
                let quadrant = 2 * usize::from(i / grid >= half) + usize::from(i % grid >= half);
                f32::from(u8::from(self.marked[quadrant]))
            })
            .collect()
    }
}

/// Everything drawn for one stage-1 sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Stage1Draw {
    /// The target is the context frame itself.
    pub self_decode: bool,
    /// Quadrants in segment 1.
    pub mask: QuadrantMask,
    /// Photometric augmentation of both frames as PoseEnc sees them.
    pub augmentation: crate::augment::Augmentation,
}

impl Stage1Config {
    /// The draws of global sample `sample` at `step`.
    pub fn draw(&self, seed: u64, step: u64, sample: u64) -> Stage1Draw {
        let mut stream = Stream::new(&[seed, STAGE1_STREAM, step, sample]);
        let self_decode = stream.bernoulli(self.self_decode_probability);
        let unmasked = stream.bernoulli(self.unmasked_probability);
        let pair = QuadrantMask::PAIRS[stream.below(6) as usize];
        let augmentation = self.augment.draw(&mut stream);
        Stage1Draw {
            self_decode,
            mask: QuadrantMask {
                marked: if unmasked { [false; 4] } else { pair },
            },
            augmentation,
        }
    }

    /// Assembles the tensors of one (micro-)batch from `(context, target)` frame pairs whose
    /// first element is global sample `first_sample` of `step`.
    pub fn batch(
        &self,
        pairs: &[(Image, Image)],
        seed: u64,
        step: u64,
        first_sample: u64,
        patch_size: usize,
        device: &Device,
    ) -> Stage1Batch {
        let count = pairs.len();
        let (height, width) = pairs
            .first()
            .map_or((0, 0), |(image, _)| (image.height, image.width));
        let grid = height / patch_size.max(1);
        let mut encoder = Vec::with_capacity(count * 2 * height * width * 3);
        let mut context = Vec::with_capacity(count * height * width * 3);
        let mut target = Vec::with_capacity(count * height * width * 3);
        let mut mask = Vec::with_capacity(count * grid * grid);
        let mut copy = Vec::with_capacity(count);
        for (offset, (first, second)) in pairs.iter().enumerate() {
            let draw = self.draw(seed, step, first_sample + offset as u64);
            let second = if draw.self_decode { first } else { second };
            encoder.extend(draw.augmentation.apply(first).pixels);
            encoder.extend(draw.augmentation.apply(second).pixels);
            context.extend_from_slice(&first.pixels);
            target.extend_from_slice(&second.pixels);
            mask.extend(draw.mask.patch_mask(grid));
            copy.push(f32::from(u8::from(draw.mask.is_empty())));
        }
        Stage1Batch {
            encoder_pair: Tensor::from_data(
                TensorData::new(encoder, [count, 2, height, width, 3]),
                device,
            ),
            context: Tensor::from_data(
                TensorData::new(context, [count, 1, height, width, 3]),
                device,
            ),
            target: Tensor::from_data(TensorData::new(target, [count, height, width, 3]), device),
            mask: Tensor::from_data(TensorData::new(mask, [count, grid * grid]), device),
            copy_slot: Tensor::from_data(TensorData::new(copy, [count, 1, 1, 1]), device),
        }
    }
}

/// The tensors of one stage-1 batch.
#[derive(Debug, Clone)]
pub struct Stage1Batch {
    /// Augmented `(context, target)` as PoseEnc sees them, `(B, 2, H, W, 3)`.
    pub encoder_pair: Tensor<5>,
    /// The un-augmented context frame, `(B, 1, H, W, 3)`.
    pub context: Tensor<5>,
    /// The frame to reconstruct, `(B, H, W, 3)`.
    pub target: Tensor<4>,
    /// Patch mask (segment ids), `(B, T)`.
    pub mask: Tensor<2>,
    /// `1` where nothing was marked, so slot 1 takes slot 0's latent, `(B, 1, 1, 1)`.
    pub copy_slot: Tensor<4>,
}

/// Swaps the two segment slots of `(B, V, 2, Cp)` latents.
pub fn swap_slots(latents: Tensor<4>) -> Tensor<4> {
    Tensor::cat(
        vec![latents.clone().narrow(2, 1, 1), latents.narrow(2, 0, 1)],
        2,
    )
}

/// The pieces of one stage-1 loss evaluation.
#[derive(Debug, Clone)]
pub struct Stage1Loss {
    /// `mean |target - pred|`.
    pub l1: Tensor<1>,
    /// Mean LPIPS distance, when an LPIPS network is given.
    pub lpips: Option<Tensor<1>>,
    /// `l1 + weight * lpips`.
    pub total: Tensor<1>,
}

/// Runs the stage-1 objective on a batch: PoseEnc on the augmented pair with the mask, slot
/// copy for unmasked samples, slot swap, Render of the clean context, `L1 + w * LPIPS`.
pub fn stage1_loss(
    model: &XFactor,
    lpips: Option<&Lpips>,
    lpips_weight: f64,
    batch: &Stage1Batch,
) -> Stage1Loss {
    let latents = model
        .pose_enc
        .forward_masked(batch.encoder_pair.clone(), batch.mask.clone());
    let slot0 = latents.clone().narrow(2, 0, 1);
    let slot1 = latents.narrow(2, 1, 1);
    let copy = batch.copy_slot.clone();
    let slot1 = slot0.clone() * copy.clone() + slot1 * (copy.neg() + 1.0);
    let swapped = swap_slots(Tensor::cat(vec![slot0, slot1], 2));
    let prediction = model.render.forward(
        batch.context.clone(),
        PoseLatents::PerSegment(swapped),
        Some(batch.mask.clone()),
    );
    let l1 = (batch.target.clone() - prediction.clone()).abs().mean();
    let lpips = lpips.map(|network| network.distance(batch.target.clone(), prediction).mean());
    let total = match &lpips {
        Some(distance) if lpips_weight != 0.0 => l1.clone() + distance.clone() * lpips_weight,
        _ => l1.clone(),
    };
    Stage1Loss { l1, lpips, total }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masks_are_two_quadrants_or_none_with_the_right_frequencies() {
        let config = Stage1Config::default();
        let draws = 20_000u64;
        let (mut empty, mut self_decode) = (0, 0);
        let mut pair_counts = [0usize; 6];
        for sample in 0..draws {
            let draw = config.draw(7, 3, sample);
            self_decode += usize::from(draw.self_decode);
            if draw.mask.is_empty() {
                empty += 1;
                continue;
            }
            assert_eq!(draw.mask.marked.iter().filter(|&&m| m).count(), 2);
            let index = QuadrantMask::PAIRS
                .iter()
                .position(|p| *p == draw.mask.marked)
                .unwrap();
            pair_counts[index] += 1;
        }
        let rate = |n: usize| n as f64 / draws as f64;
        assert!((rate(empty) - 0.05).abs() < 0.006, "{}", rate(empty));
        assert!((rate(self_decode) - 0.05).abs() < 0.006);
        for count in pair_counts {
            assert!((rate(count) - 0.95 / 6.0).abs() < 0.012, "{pair_counts:?}");
        }
    }

    #[test]
    fn draws_depend_only_on_seed_step_and_sample() {
        let config = Stage1Config::default();
        assert_eq!(config.draw(1, 2, 3), config.draw(1, 2, 3));
        let distinct = (0..50)
            .filter(|&s| config.draw(1, 2, s) != config.draw(1, 3, s))
            .count();
        assert!(distinct > 40);
    }

    #[test]
    fn quadrant_geometry_is_row_major() {
        let mask = QuadrantMask {
            marked: [false, true, true, false],
        };
        let grid = mask.patch_mask(4);
        #[rustfmt::skip]
        let expected = [
            0.0, 0.0, 1.0, 1.0,
            0.0, 0.0, 1.0, 1.0,
            1.0, 1.0, 0.0, 0.0,
            1.0, 1.0, 0.0, 0.0,
        ];
        assert_eq!(grid, expected);
    }

    #[test]
    fn swap_exchanges_the_slots() {
        let device = Device::flex();
        let latents = Tensor::<4>::from_data(
            TensorData::new(vec![1.0f32, 2.0, 3.0, 4.0], [1, 1, 2, 2]),
            &device,
        );
        let swapped = swap_slots(latents).try_into_vec_as::<f32>().unwrap();
        assert_eq!(swapped, vec![3.0, 4.0, 1.0, 2.0]);
    }
}
