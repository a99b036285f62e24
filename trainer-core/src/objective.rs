//! The two training objectives: stage 1 (stereo-monocular transferability) and stage 2
//! (multi-view fine-tune), each as XFactor's transfer objective or as the plain autoencoding
//! of the paper's ablations ([`ObjectiveVariant`]: no mask, no swap, no self-decoding). Both reduce to one computation over an [`ObjectiveBatch`]: PoseEnc on
//! `(reference, view)` pairs, slot copy and swap, Render of the clean context views,
//! `L1 + w * LPIPS`. Stage 1 is the case of one context view.
//!
//! Every random choice for global sample `i` of step `s` comes from a stream keyed by
//! `(seed, s, i)`, so which process or thread builds a sample never changes it.

use burn::tensor::{Device, Tensor, TensorData};

use data::Image;
use settings::objective::{ObjectiveVariant, Stage1Config, Stage2Config};

use crate::augment::{AugmentDraw, Augmentation};
use crate::lpips::Lpips;
use crate::model::{PoseLatents, XFactor};
use data::rng::Stream;

/// Tags that separate each stage's draws from every other use of `(seed, step, sample)`.
const STAGE1_STREAM: u64 = 0x5354_4147_4531;
const STAGE2_STREAM: u64 = 0x5354_4147_4532;

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
    pub augmentation: Augmentation,
    /// The extra-view variants' augmentation of the pair `(reference, extra view)`, drawn
    /// after everything else so the other draws are those of a pair sample.
    pub extra_augmentation: Augmentation,
}

/// The draws and batches of stage 1, computed from its settings.
pub trait Stage1Objective {
    /// The draws of global sample `sample` at `step`.
    fn draw(&self, seed: u64, step: u64, sample: u64) -> Stage1Draw;
    /// Assembles one (micro-)batch from `(context, target)` frame pairs whose first element is
    /// global sample `first_sample` of `step`.
    fn batch(
        &self,
        pairs: &[(Image, Image)],
        seed: u64,
        step: u64,
        first_sample: u64,
        patch_size: usize,
        device: &Device,
    ) -> ObjectiveBatch;
    /// The extra-view variants' batch from samples of three frames (reference, extra view,
    /// target; the frame indices are not used): Render gets the reference and the extra view
    /// as context; PoseEnc reads pairs, or all three at once for `extra_view_encoder_decoder`.
    fn batch_with_extra_view(
        &self,
        samples: &[Vec<(u64, Image)>],
        seed: u64,
        step: u64,
        first_sample: u64,
        patch_size: usize,
        device: &Device,
    ) -> ObjectiveBatch;
}

impl Stage1Objective for Stage1Config {
    fn draw(&self, seed: u64, step: u64, sample: u64) -> Stage1Draw {
        let mut stream = Stream::new(&[seed, STAGE1_STREAM, step, sample]);
        let self_decode = stream.bernoulli(self.self_decode_probability);
        let unmasked = stream.bernoulli(self.unmasked_probability);
        let pair = QuadrantMask::PAIRS[stream.below(6) as usize];
        let augmentation = self.augment.draw(&mut stream);
        let extra_augmentation = self.augment.draw(&mut stream);
        let transfer = self.variant.transferability();
        Stage1Draw {
            self_decode: transfer && self_decode,
            mask: QuadrantMask {
                marked: if unmasked || !transfer {
                    [false; 4]
                } else {
                    pair
                },
            },
            augmentation,
            extra_augmentation,
        }
    }

    fn batch(
        &self,
        pairs: &[(Image, Image)],
        seed: u64,
        step: u64,
        first_sample: u64,
        patch_size: usize,
        device: &Device,
    ) -> ObjectiveBatch {
        let mut builder = BatchBuilder::new(2, patch_size);
        for (offset, (first, second)) in pairs.iter().enumerate() {
            let draw = self.draw(seed, step, first_sample + offset as u64);
            let target = if draw.self_decode { first } else { second };
            builder.push(
                &[first, target],
                &draw.mask,
                std::slice::from_ref(&draw.augmentation),
            );
        }
        builder.finish(device)
    }

    fn batch_with_extra_view(
        &self,
        samples: &[Vec<(u64, Image)>],
        seed: u64,
        step: u64,
        first_sample: u64,
        patch_size: usize,
        device: &Device,
    ) -> ObjectiveBatch {
        let mut builder = BatchBuilder::new(3, patch_size);
        builder.joint_encoder = self.variant == ObjectiveVariant::ExtraViewEncoderDecoder;
        for (offset, frames) in samples.iter().enumerate() {
            let draw = self.draw(seed, step, first_sample + offset as u64);
            let (reference, extra) = (&frames[0].1, &frames[1].1);
            let target = if draw.self_decode {
                reference
            } else {
                &frames[2].1
            };
            builder.push(
                &[reference, extra, target],
                &draw.mask,
                &[draw.extra_augmentation, draw.augmentation],
            );
        }
        builder.finish(device)
    }
}

/// Collects samples of `views` ordered frames (reference first, target last) into host buffers.
struct BatchBuilder {
    views: usize,
    patch_size: usize,
    /// PoseEnc reads all `views` frames in one pass (with the first augmentation) instead of
    /// one `(reference, view)` pair per view.
    joint_encoder: bool,
    shape: Option<(usize, usize)>,
    samples: usize,
    encoder_pairs: Vec<f32>,
    context: Vec<f32>,
    target: Vec<f32>,
    encoder_mask: Vec<f32>,
    mask: Vec<f32>,
    copy_slot: Vec<f32>,
}

impl BatchBuilder {
    fn new(views: usize, patch_size: usize) -> Self {
        Self {
            views,
            patch_size,
            joint_encoder: false,
            shape: None,
            samples: 0,
            encoder_pairs: Vec::new(),
            context: Vec::new(),
            target: Vec::new(),
            encoder_mask: Vec::new(),
            mask: Vec::new(),
            copy_slot: Vec::new(),
        }
    }

    /// Adds one sample: `frames` ordered reference first, target last; `augmentations[i]` is
    /// applied to both frames of PoseEnc's pair `(reference, frames[i + 1])`.
    fn push(&mut self, frames: &[&Image], mask: &QuadrantMask, augmentations: &[Augmentation]) {
        let reference = frames[0];
        self.shape = Some((reference.height, reference.width));
        let grid = reference.height / self.patch_size.max(1);
        let patch_mask = mask.patch_mask(grid);
        if self.joint_encoder {
            for frame in frames {
                self.encoder_pairs
                    .extend_from_slice(&augmentations[0].apply(frame).pixels);
            }
            self.encoder_mask.extend_from_slice(&patch_mask);
        } else {
            for (view, augmentation) in frames[1..].iter().zip(augmentations) {
                self.encoder_pairs
                    .extend_from_slice(&augmentation.apply(reference).pixels);
                self.encoder_pairs
                    .extend_from_slice(&augmentation.apply(view).pixels);
                self.encoder_mask.extend_from_slice(&patch_mask);
            }
        }
        for frame in &frames[..self.views - 1] {
            self.context.extend_from_slice(&frame.pixels);
        }
        self.target
            .extend_from_slice(&frames[self.views - 1].pixels);
        self.mask.extend(patch_mask);
        self.copy_slot.push(f32::from(u8::from(mask.is_empty())));
        self.samples += 1;
    }

    fn finish(self, device: &Device) -> ObjectiveBatch {
        let (height, width) = self.shape.unwrap_or((0, 0));
        let (b, contexts) = (self.samples, self.views - 1);
        let tokens = self.mask.len() / b.max(1);
        let (encoder_samples, encoder_views) = if self.joint_encoder {
            (b, self.views)
        } else {
            (b * contexts, 2)
        };
        ObjectiveBatch {
            encoder_pairs: upload(
                self.encoder_pairs,
                [encoder_samples, encoder_views, height, width, 3],
                device,
            ),
            encoder_mask: upload(self.encoder_mask, [encoder_samples, tokens], device),
            joint_encoder: self.joint_encoder,
            context: upload(self.context, [b, contexts, height, width, 3], device),
            target: upload(self.target, [b, height, width, 3], device),
            mask: upload(self.mask, [b, tokens], device),
            copy_slot: upload(self.copy_slot, [b, 1, 1, 1], device),
        }
    }
}

fn upload<const D: usize>(values: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// The tensors of one batch of either stage, `V` views per sample (reference first, target
/// last).
#[derive(Debug, Clone)]
pub struct ObjectiveBatch {
    /// Augmented `(reference, view_i)` pairs for `i = 1..V`, `(B * (V-1), 2, H, W, 3)`; with
    /// `joint_encoder`, all `V` views of each sample, `(B, V, H, W, 3)`.
    pub encoder_pairs: Tensor<5>,
    /// The sample's patch mask repeated for each of its pairs, `(B * (V-1), T)`; with
    /// `joint_encoder`, `(B, T)`.
    pub encoder_mask: Tensor<2>,
    /// PoseEnc reads each sample's views in one pass rather than pair by pair.
    pub joint_encoder: bool,
    /// The un-augmented context views (reference first), `(B, V-1, H, W, 3)`.
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

/// The pieces of one loss evaluation.
#[derive(Debug, Clone)]
pub struct ObjectiveLoss {
    /// `mean |target - pred|`.
    pub l1: Tensor<1>,
    /// Mean LPIPS distance, when an LPIPS network is given.
    pub lpips: Option<Tensor<1>>,
    /// `l1 + weight * lpips`.
    pub total: Tensor<1>,
}

/// Runs either stage's objective on a batch: PoseEnc on every `(reference, view)` pair with the
/// mask, the reference's latent set to exactly zero (what PoseEnc itself returns for view 0),
/// slot copy for unmasked samples, slot swap, Render of the clean context, `L1 + w * LPIPS`.
pub fn objective_loss(
    model: &XFactor,
    lpips: Option<&Lpips>,
    lpips_weight: f64,
    batch: &ObjectiveBatch,
) -> ObjectiveLoss {
    let [b, contexts, _, _, _] = batch.context.dims();
    let encoded = model
        .pose_enc
        .forward_masked(batch.encoder_pairs.clone(), batch.encoder_mask.clone());
    let [_, _, _, pose_dim] = encoded.dims();
    // The latent of every view after the reference: from the joint pass directly, or from
    // the second view of each pair.
    let views = if batch.joint_encoder {
        encoded.narrow(1, 1, contexts)
    } else {
        encoded.narrow(1, 1, 1).reshape([b, contexts, 2, pose_dim])
    };
    let latents = Tensor::cat(vec![views.zeros_like().narrow(1, 0, 1), views], 1);
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
    ObjectiveLoss { l1, lpips, total }
}

/// Everything drawn for one stage-2 sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Stage2Draw {
    /// Positions into the sample's frames in model order: the "middlest" frame first, the rest
    /// shuffled, the last one the target.
    pub order: Vec<usize>,
    /// When the target is replaced, the context position (into `order`) that replaces it.
    pub self_decode_from: Option<usize>,
    /// Quadrants in segment 1.
    pub mask: QuadrantMask,
    /// Photometric augmentation of each PoseEnc pair `(reference, frame i)`, `i = 1..V`: one
    /// draw per pair, shared by its two frames, as the release draws them.
    pub augmentations: Vec<Augmentation>,
}

/// The draws and batches of stage 2, computed from its settings.
pub trait Stage2Objective {
    /// The draws of global sample `sample` at `step`, for frames with these indices into their
    /// video (any order).
    fn draw(&self, seed: u64, step: u64, sample: u64, frame_indices: &[u64]) -> Stage2Draw;
    /// Assembles one (micro-)batch from samples of `views` frames, each `(frame index in its
    /// video, image)`, the first sample being global sample `first_sample` of `step`.
    fn batch(
        &self,
        samples: &[Vec<(u64, Image)>],
        seed: u64,
        step: u64,
        first_sample: u64,
        patch_size: usize,
        device: &Device,
    ) -> ObjectiveBatch;
}

impl Stage2Objective for Stage2Config {
    fn draw(&self, seed: u64, step: u64, sample: u64, frame_indices: &[u64]) -> Stage2Draw {
        let mut stream = Stream::new(&[seed, STAGE2_STREAM, step, sample]);
        let mut sorted: Vec<usize> = (0..frame_indices.len()).collect();
        sorted.sort_by_key(|&i| frame_indices[i]);
        let reference = middlest(frame_indices);
        let mut order = vec![reference];
        order.extend(sorted.into_iter().filter(|&i| i != reference));
        for i in (2..order.len()).rev() {
            let j = 1 + stream.below(i as u64) as usize;
            order.swap(i, j);
        }
        let self_decode = stream.bernoulli(self.self_decode_probability);
        let contexts = order.len().saturating_sub(1).max(1) as u64;
        let replacement = stream.below(contexts) as usize;
        let unmasked = stream.bernoulli(self.unmasked_probability);
        let pair = QuadrantMask::PAIRS[stream.below(6) as usize];
        let augmentations = (1..order.len())
            .map(|_| self.augment.draw(&mut stream))
            .collect();
        let transfer = self.variant.transferability();
        Stage2Draw {
            order,
            self_decode_from: (transfer && self_decode).then_some(replacement),
            mask: QuadrantMask {
                marked: if unmasked || !transfer {
                    [false; 4]
                } else {
                    pair
                },
            },
            augmentations,
        }
    }

    fn batch(
        &self,
        samples: &[Vec<(u64, Image)>],
        seed: u64,
        step: u64,
        first_sample: u64,
        patch_size: usize,
        device: &Device,
    ) -> ObjectiveBatch {
        let mut builder = BatchBuilder::new(self.views, patch_size);
        for (offset, frames) in samples.iter().enumerate() {
            let indices: Vec<u64> = frames.iter().map(|(index, _)| *index).collect();
            let draw = self.draw(seed, step, first_sample + offset as u64, &indices);
            let mut ordered: Vec<&Image> = draw.order.iter().map(|&i| &frames[i].1).collect();
            if let Some(source) = draw.self_decode_from {
                let last = ordered.len() - 1;
                ordered[last] = ordered[source];
            }
            builder.push(&ordered, &draw.mask, &draw.augmentations);
        }
        builder.finish(device)
    }
}

/// The position of the frame with the smallest `max(|f - first|, |f - last|)`, where `first`
/// and `last` are the smallest and largest frame indices (the window's ends).
pub fn middlest(frame_indices: &[u64]) -> usize {
    let first = frame_indices.iter().copied().min().unwrap_or(0);
    let last = frame_indices.iter().copied().max().unwrap_or(0);
    (0..frame_indices.len())
        .min_by_key(|&i| {
            let f = frame_indices[i];
            (f - first).max(last - f)
        })
        .unwrap_or(0)
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
    fn stage2_orders_middlest_first_and_shuffles_the_rest() {
        // Ends 3 and 30: frame 20 is at most 17 from either end, frame 12 up to 18.
        assert_eq!(middlest(&[10, 3, 20, 12, 5, 30]), 2);
        assert_eq!(middlest(&[0, 1]), 0);
        let config = Stage2Config::default();
        let indices = [40u64, 0, 7, 22, 13, 30];
        let (mut replaced, draws) = (0usize, 20_000u64);
        let mut target_counts = [0usize; 6];
        for sample in 0..draws {
            let draw = config.draw(3, 9, sample, &indices);
            assert_eq!(draw.order[0], 3, "frame 22 is the middlest of 0..40");
            let mut sorted = draw.order.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, vec![0, 1, 2, 3, 4, 5]);
            target_counts[*draw.order.last().unwrap()] += 1;
            if let Some(source) = draw.self_decode_from {
                assert!(source < 5);
                replaced += 1;
            }
        }
        let rate = replaced as f64 / draws as f64;
        assert!((rate - 0.02).abs() < 0.004, "{rate}");
        assert_eq!(target_counts[3], 0);
        for (position, count) in target_counts.iter().enumerate().filter(|(p, _)| *p != 3) {
            let share = *count as f64 / draws as f64;
            assert!((share - 0.2).abs() < 0.015, "position {position}: {share}");
        }
    }

    #[test]
    fn stage2_draws_augmentation_per_pair() {
        let config = Stage2Config::default();
        let indices = [0u64, 3, 6, 9, 12, 15];
        let draw = config.draw(1, 2, 3, &indices);
        assert_eq!(
            draw.augmentations.len(),
            5,
            "one draw per (reference, frame) pair"
        );
        assert_eq!(draw, config.draw(1, 2, 3, &indices));
        // Two pairs of a sample are equal only when neither is jittered nor blurred
        // (probability 0.07^2), so nearly every sample's first two pairs differ.
        let differing = (0..200u64)
            .filter(|&sample| {
                let draw = config.draw(1, 2, sample, &indices);
                draw.augmentations[0] != draw.augmentations[1]
            })
            .count();
        assert!(differing >= 190, "{differing} of 200");
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
