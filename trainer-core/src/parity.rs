//! Checking the model against a fixture produced by the authors' implementation.
//!
//! A fixture is `NAME.safetensors` (parameters under flax names, inputs, outputs and gradients of
//! the L1 loss) with `NAME.json` beside it holding the configuration. Users run this after
//! importing weights; the parity tests run the same code on `xfactor-tiny`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor};
use serde::Deserialize;

use crate::flax::{
    FlaxError, FlaxTensors, GRADS_PREFIX, HostTensor, PARAMS_PREFIX, load_flax, named_gradients,
};
use crate::model::{PoseLatents, XFactor};
use settings::model::{ConfigError, XFactorConfig};

/// Largest absolute error allowed on any output.
pub const OUTPUT_TOLERANCE: f32 = 1e-4;
/// Largest gradient error allowed, relative to the reference tensor's largest magnitude.
pub const GRADIENT_TOLERANCE: f32 = 1e-3;

/// The outputs a fixture holds, in the order they are reported.
pub const OUTPUT_NAMES: [&str; 6] = [
    "pose_masked",
    "pose_full",
    "render_masked",
    "render_full",
    "render_mv",
    "l1_loss",
];

/// Why a fixture could not be checked (as opposed to checked and failed).
#[derive(Debug, thiserror::Error)]
pub enum ParityError {
    /// The JSON beside the fixture could not be read.
    #[error("cannot read fixture config {path}: {source}")]
    Io {
        /// File at fault.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The JSON beside the fixture is malformed.
    #[error("fixture config {path} is invalid: {source}")]
    Json {
        /// File at fault.
        path: PathBuf,
        /// Parser error, with line and column.
        source: serde_json::Error,
    },
    /// The fixture's configuration describes no model this crate can build.
    #[error("fixture config {path}")]
    Config {
        /// File at fault.
        path: PathBuf,
        /// What is wrong.
        #[source]
        source: FixtureConfigError,
    },
    /// Tensors are missing, misshapen or unreadable.
    #[error(transparent)]
    Tensors(#[from] FlaxError),
}

/// Why a fixture's configuration describes no model this crate can build.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum FixtureConfigError {
    /// The model takes square images only.
    #[error("images must be square, got {height}x{width}")]
    NotSquare {
        /// Image height of the fixture.
        height: usize,
        /// Image width of the fixture.
        width: usize,
    },
    /// The model configuration breaks one of the model's constraints.
    #[error(transparent)]
    Model(#[from] ConfigError),
}

/// The configuration keys of a fixture JSON (other keys, such as `layout`, are ignored).
#[derive(Debug, Clone, Deserialize)]
pub struct FixtureConfig {
    /// Batch size of the stored inputs.
    pub batch: usize,
    /// Image height.
    pub height: usize,
    /// Image width.
    pub width: usize,
    /// Patch side.
    pub patch_size: usize,
    /// Model width `C`.
    pub features: usize,
    /// Attention heads.
    pub num_heads: usize,
    /// Layers in each of PoseEnc and Render.
    pub num_layers: usize,
    /// Pose-latent size.
    pub pose_dim: usize,
    /// Global tokens `G`.
    pub global_tokens: usize,
    /// Context views of the multi-view Render input.
    pub context_views_mv: usize,
}

impl FixtureConfig {
    /// The model configuration this fixture was produced with.
    pub fn model_config(&self) -> Result<XFactorConfig, FixtureConfigError> {
        if self.height != self.width {
            return Err(FixtureConfigError::NotSquare {
                height: self.height,
                width: self.width,
            });
        }
        let config = XFactorConfig {
            image_size: self.height,
            patch_size: self.patch_size,
            width: self.features,
            num_heads: self.num_heads,
            pose_layers: self.num_layers,
            render_layers: self.num_layers,
            pose_dim: self.pose_dim,
            global_tokens: self.global_tokens,
            round_qkv_bf16: false,
            pose_conditioning: settings::model::PoseConditioning::Latent,
            precision: settings::model::Precision::F32,
            compute: settings::model::Precision::F32,
        };
        config.validate()?;
        Ok(config)
    }
}

/// What a parity run measured.
#[derive(Debug, Clone)]
pub struct ParityReport {
    /// The model configuration checked.
    pub config: XFactorConfig,
    /// Largest absolute error of each output, in [`OUTPUT_NAMES`] order.
    pub output_errors: Vec<(String, f32)>,
    /// Relative error of every parameter gradient, by flax name.
    pub gradient_errors: BTreeMap<String, f32>,
    /// Largest absolute value of the reference view's pose latents (must be exactly zero).
    pub reference_pose_max_abs: f32,
}

impl ParityReport {
    /// The largest output error.
    pub fn worst_output(&self) -> (&str, f32) {
        worst(
            self.output_errors
                .iter()
                .map(|(name, e)| (name.as_str(), *e)),
        )
    }

    /// The largest relative gradient error.
    pub fn worst_gradient(&self) -> (&str, f32) {
        worst(
            self.gradient_errors
                .iter()
                .map(|(name, e)| (name.as_str(), *e)),
        )
    }

    /// Whether every output, every gradient and the reference pose are within tolerance.
    pub fn passed(&self) -> bool {
        self.output_errors
            .iter()
            .all(|(_, e)| *e <= OUTPUT_TOLERANCE)
            && self
                .gradient_errors
                .values()
                .all(|e| *e <= GRADIENT_TOLERANCE)
            && self.reference_pose_max_abs == 0.0
    }
}

fn worst<'a>(errors: impl Iterator<Item = (&'a str, f32)>) -> (&'a str, f32) {
    errors.fold(
        ("", 0.0),
        |worst, current| {
            if current.1 > worst.1 { current } else { worst }
        },
    )
}

/// Reads the configuration JSON beside `fixture` (same stem, `.json`).
pub fn read_fixture_config(fixture: &Path) -> Result<FixtureConfig, ParityError> {
    let path = fixture.with_extension("json");
    let text = std::fs::read_to_string(&path).map_err(|source| ParityError::Io {
        path: path.clone(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|source| ParityError::Json { path, source })
}

/// Loads the fixture's parameters into a model on `device` (autodiff is enabled here), runs
/// every call the fixture recorded plus the backward pass, and measures the differences.
pub fn check_fixture(fixture: &Path, device: &Device) -> Result<ParityReport, ParityError> {
    let fixture_config = read_fixture_config(fixture)?;
    let config_error = |source: FixtureConfigError| ParityError::Config {
        path: fixture.with_extension("json"),
        source,
    };
    let config = fixture_config.model_config().map_err(config_error)?;
    let tensors = FlaxTensors::read(fixture)?;
    let device = device.clone().autodiff();
    let model = XFactor::new(&config, 0, &device)
        .map_err(|source| config_error(FixtureConfigError::Model(source)))?;
    let model = load_flax(model, &tensors, PARAMS_PREFIX)?;

    let input = |name: &str| tensors.require(&format!("input.{name}"));
    let pair: Tensor<5> = input("pair")?.to_tensor(&device);
    let mask: Tensor<2> = input("pmask")?.to_tensor(&device);
    let context_mv: Tensor<5> = input("ctx_mv")?.to_tensor(&device);
    let pose_mv: Tensor<3> = input("pose_mv")?.to_tensor(&device);

    let outputs = run_fixture_calls(&model, pair, mask, context_mv, pose_mv);
    let reference_pose_max_abs = max_abs(outputs.pose_masked.clone().narrow(1, 0, 1))
        .max(max_abs(outputs.pose_full.clone().narrow(1, 0, 1)));
    let gradients = named_gradients(&model, &outputs.l1_loss.backward());

    let measured = [
        HostTensor::from_tensor(outputs.pose_masked),
        HostTensor::from_tensor(outputs.pose_full),
        HostTensor::from_tensor(outputs.render_masked),
        HostTensor::from_tensor(outputs.render_full),
        HostTensor::from_tensor(outputs.render_mv),
        HostTensor::from_tensor(outputs.l1_loss),
    ];
    let mut output_errors = Vec::new();
    for (name, ours) in OUTPUT_NAMES.iter().zip(&measured) {
        let reference = tensors.require(&format!("output.{name}"))?;
        output_errors.push((name.to_string(), max_abs_difference(name, ours, reference)?));
    }

    let mut gradient_errors = BTreeMap::new();
    for reference_name in tensors.names_with_prefix(GRADS_PREFIX) {
        let name = &reference_name[GRADS_PREFIX.len()..];
        let reference = tensors.require(reference_name)?;
        let ours = gradients.get(name).cloned().unwrap_or_else(|| HostTensor {
            shape: reference.shape.clone(),
            values: vec![0.0; reference.values.len()],
        });
        let scale = reference.max_abs().max(f32::MIN_POSITIVE);
        let error = max_abs_difference(reference_name, &ours, reference)? / scale;
        gradient_errors.insert(name.to_string(), error);
    }

    Ok(ParityReport {
        config,
        output_errors,
        gradient_errors,
        reference_pose_max_abs,
    })
}

/// Everything a fixture records, computed by this crate.
struct FixtureOutputs {
    pose_masked: Tensor<4>,
    pose_full: Tensor<3>,
    render_masked: Tensor<4>,
    render_full: Tensor<4>,
    render_mv: Tensor<4>,
    l1_loss: Tensor<1>,
}

fn run_fixture_calls(
    model: &XFactor,
    pair: Tensor<5>,
    mask: Tensor<2>,
    context_mv: Tensor<5>,
    pose_mv: Tensor<3>,
) -> FixtureOutputs {
    let [batch, _, height, width, channels] = pair.dims();
    let context = pair.clone().narrow(1, 0, 1);
    let target = pair
        .clone()
        .narrow(1, 1, 1)
        .reshape([batch, height, width, channels]);

    let pose_masked = model.pose_enc.forward_masked(pair.clone(), mask.clone());
    let swapped = Tensor::cat(
        vec![
            pose_masked.clone().narrow(2, 1, 1),
            pose_masked.clone().narrow(2, 0, 1),
        ],
        2,
    );
    let render_masked = model.render.forward(
        context.clone(),
        PoseLatents::PerSegment(swapped),
        Some(mask),
    );
    let pose_full = model.pose_enc.forward(pair.clone());
    let render_full = model.render_pair(pair);
    let render_mv = model
        .render
        .forward(context_mv, PoseLatents::Single(pose_mv), None);
    let l1_loss = (target - render_masked.clone()).abs().mean();
    FixtureOutputs {
        pose_masked,
        pose_full,
        render_masked,
        render_full,
        render_mv,
        l1_loss,
    }
}

fn max_abs<const D: usize>(tensor: Tensor<D>) -> f32 {
    tensor.abs().max().into_scalar::<f32>()
}

fn max_abs_difference(
    name: &str,
    ours: &HostTensor,
    reference: &HostTensor,
) -> Result<f32, FlaxError> {
    if ours.values.len() != reference.values.len() {
        return Err(FlaxError::Shape {
            name: name.to_string(),
            expected: ours.shape.clone(),
            found: reference.shape.clone(),
        });
    }
    Ok(ours
        .values
        .iter()
        .zip(&reference.values)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs())))
}
