//! LPIPS (VGG16 variant) as the authors' JAX code computes it, differentiable in burn.
//!
//! Weights come from a safetensors file with the names `vgg.conv{b}_{l}.weight` (HWIO),
//! `vgg.conv{b}_{l}.bias` and `lin.lin{i}` (`1x1xCx1`): the layout of the authors'
//! `vgg16_weights.h5` / `lpips_lin.h5` after `tools/convert_lpips_weights.py`, and of the parity
//! fixture `lpips-vgg16-random.safetensors`.

use std::path::Path;

use burn::module::{Module, Param};
use burn::tensor::module::{conv2d, max_pool2d};
use burn::tensor::ops::{ConvOptions, MaxPoolOptions};
use burn::tensor::{Device, Tensor, TensorData};

use crate::flax::{FlaxError, FlaxTensors};

/// Convolutions per VGG16 block.
const BLOCK_DEPTHS: [usize; 5] = [2, 2, 3, 3, 3];
/// Output channels per VGG16 block.
const BLOCK_CHANNELS: [usize; 5] = [64, 128, 256, 512, 512];
/// ImageNet statistics the VGG weights expect.
const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];
/// Added to feature norms before dividing.
const NORM_EPS: f64 = 1e-10;

/// One 3x3 'same' convolution with bias, weights stored `(out, in, 3, 3)` as burn expects.
#[derive(Module, Debug)]
pub struct Conv3x3 {
    /// `(out, in, 3, 3)` kernel.
    pub weight: Param<Tensor<4>>,
    /// `(out)` bias.
    pub bias: Param<Tensor<1>>,
}

/// The LPIPS network: VGG16's convolutional part and the five non-negative linear heads.
#[derive(Module, Debug)]
pub struct Lpips {
    /// The 13 convolutions, block by block.
    pub convs: Vec<Conv3x3>,
    /// Per-tap channel weights `(C)`.
    pub lins: Vec<Param<Tensor<1>>>,
}

impl Lpips {
    /// Reads the weights from a safetensors file of the layout above.
    pub fn from_file(path: &Path, device: &Device) -> Result<Self, FlaxError> {
        Self::from_tensors(&FlaxTensors::read(path)?, device)
    }

    /// Builds the network from already-read tensors, checking every name and shape.
    pub fn from_tensors(tensors: &FlaxTensors, device: &Device) -> Result<Self, FlaxError> {
        let mut convs = Vec::new();
        let mut in_channels = 3;
        for (block, (&depth, &channels)) in BLOCK_DEPTHS.iter().zip(&BLOCK_CHANNELS).enumerate() {
            for layer in 1..=depth {
                let prefix = format!("vgg.conv{}_{layer}", block + 1);
                let hwio =
                    tensors.expect(&format!("{prefix}.weight"), &[3, 3, in_channels, channels])?;
                let bias = tensors.expect(&format!("{prefix}.bias"), &[channels])?;
                let weight = hwio.to_tensor::<4>(device).permute([3, 2, 0, 1]);
                convs.push(Conv3x3 {
                    weight: Param::from_tensor(weight),
                    bias: Param::from_tensor(bias.to_tensor(device)),
                });
                in_channels = channels;
            }
        }
        let lins = BLOCK_CHANNELS
            .iter()
            .enumerate()
            .map(|(i, &channels)| {
                let lin = tensors.expect(&format!("lin.lin{i}"), &[1, 1, channels, 1])?;
                Ok(Param::from_tensor(
                    lin.to_tensor::<4>(device).reshape([channels]),
                ))
            })
            .collect::<Result<Vec<_>, FlaxError>>()?;
        Ok(Self { convs, lins })
    }

    /// LPIPS distance per image between `x` and `t`, both `(B, H, W, 3)` in `[-1, 1]`;
    /// returns `(B)`.
    pub fn distance(&self, x: Tensor<4>, t: Tensor<4>) -> Tensor<1> {
        let batch = x.dims()[0];
        let both = Tensor::cat(vec![x, t], 0);
        let mut distance: Option<Tensor<1>> = None;
        for (tap, lin) in self.features(both).into_iter().zip(&self.lins) {
            let [_, channels, _, _] = tap.dims();
            let norm = tap.clone().square().sum_dim(1).sqrt() + NORM_EPS;
            let unit = tap / norm;
            let difference =
                (unit.clone().narrow(0, 0, batch) - unit.narrow(0, batch, batch)).square();
            let weighted = difference * lin.val().reshape([1, channels, 1, 1]);
            let per_image = weighted.sum_dim(1).mean_dims(&[2, 3]).reshape([batch]);
            distance = Some(match distance {
                Some(sum) => sum + per_image,
                None => per_image,
            });
        }
        distance.expect("LPIPS has five taps")
    }

    /// The five tapped ReLU outputs (`relu1_2` ... `relu5_3`), NCHW.
    fn features(&self, images: Tensor<4>) -> Vec<Tensor<4>> {
        let device = images.device();
        let stats = |values: [f32; 3]| {
            Tensor::<4>::from_data(TensorData::new(values.to_vec(), [1, 3, 1, 1]), &device)
        };
        let unit = (images.permute([0, 3, 1, 2]) + 1.0) * 0.5;
        let mut x = (unit - stats(IMAGENET_MEAN)) / stats(IMAGENET_STD);
        let mut convs = self.convs.iter();
        let mut taps = Vec::with_capacity(BLOCK_DEPTHS.len());
        for (block, &depth) in BLOCK_DEPTHS.iter().enumerate() {
            if block > 0 {
                x = max_pool2d(x, MaxPoolOptions::new([2, 2]));
            }
            for conv in convs.by_ref().take(depth) {
                let out = conv2d(
                    x,
                    conv.weight.val(),
                    Some(conv.bias.val()),
                    ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
                );
                x = burn::tensor::activation::relu(out);
            }
            taps.push(x.clone());
        }
        taps
    }
}
