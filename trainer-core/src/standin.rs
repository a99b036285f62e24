//! A stand-in for the model in measurements of everything around a step: the parameters of a
//! model's layout (every tensor's size, optionally scaled down) as float32 on a device, with
//! AdamW and a fixed set of gradients, but no forward or backward pass. The data path moves,
//! sums, applies and hashes these exactly as it does the model's own, so a benchmark that
//! replaces the compute by a wait still measures the real host path.

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use settings::XFactorConfig;
use settings::optim::AdamWConfig;

use crate::flat::{
    LayoutError, flatten_gradients_into, parameter_checksum, parameter_count, unflatten_gradients,
};
use crate::model::XFactor;
use crate::optim::{AdamW, UpdateReport};
use settings::model::ConfigError;

/// The parameters of a model's layout with their optimiser and gradients.
pub struct LayoutModel {
    parameters: Vec<Param<Tensor<1>>>,
    optimizer: AdamW,
    /// One gradient per parameter, in order (burn's `GradientsParams` is not `Sync`, and the
    /// data path reads a replica from several threads).
    gradients: Vec<Tensor<1>>,
}

impl LayoutModel {
    /// Every tensor of `layout` (elements per tensor, as [`layout_of`] gives them) with
    /// `scale` times its elements (at least one), in order, on `device`.
    pub fn scaled(layout: &[usize], scale: f64, device: &Device) -> Self {
        Self::with_sizes(
            layout
                .iter()
                .map(|&size| ((size as f64 * scale).ceil() as usize).max(1)),
            device,
        )
    }

    /// Tensors of the given sizes, with deterministic values and gradients of about the
    /// magnitude the paper model's have.
    pub fn with_sizes(sizes: impl IntoIterator<Item = usize>, device: &Device) -> Self {
        let mut parameters = Vec::new();
        let mut gradients = Vec::new();
        for (index, size) in sizes.into_iter().enumerate() {
            let values = |scale: f32| -> Vec<f32> {
                (0..size)
                    .map(|i| ((i * 7919 + index * 104_729) % 2003) as f32 / 2003.0 - 0.5)
                    .map(|v| v * scale)
                    .collect()
            };
            let parameter = Param::from_tensor(Tensor::<1>::from_data(
                TensorData::new(values(0.1), [size]),
                device,
            ));
            let gradient = Tensor::<1>::from_data(TensorData::new(values(1e-4), [size]), device);
            gradients.push(gradient);
            parameters.push(parameter);
        }
        Self {
            parameters,
            optimizer: AdamW::new(AdamWConfig::default()),
            gradients,
        }
    }

    /// Values in the flat layout.
    pub fn parameter_count(&self) -> usize {
        parameter_count(&self.parameters)
    }

    /// Fresh gradients made on the device from the fixed ones (one element-wise pass, so
    /// that no one else holds them, as a backward pass's output), as a backward pass returns
    /// them.
    pub fn backward(&self) -> GradientsParams {
        let mut grads = GradientsParams::new();
        for (parameter, gradient) in self.parameters.iter().zip(&self.gradients) {
            grads.register(parameter.id, gradient.clone().mul_scalar(1.0));
        }
        grads
    }

    /// `grads` (from [`LayoutModel::backward`]) copied from the device into `out`.
    pub fn gradients_into(
        &self,
        grads: GradientsParams,
        out: &mut [f32],
    ) -> Result<(), LayoutError> {
        flatten_gradients_into(&self.parameters, grads, out)
    }

    /// The summed gradients `sum` copied to the device, one tensor per parameter.
    pub fn upload(&self, sum: &[f32]) -> Result<GradientsParams, LayoutError> {
        unflatten_gradients(&self.parameters, sum)
    }

    /// One AdamW update with gradients from [`LayoutModel::upload`], as a replica applies them.
    pub fn update(&mut self, grads: &GradientsParams, learning_rate: f64) -> UpdateReport {
        let parameters = std::mem::take(&mut self.parameters);
        let (parameters, report) = self.optimizer.step(parameters, grads, learning_rate);
        self.parameters = parameters;
        report
    }

    /// The parameters, a module in their own right.
    pub fn parameters(&self) -> &Vec<Param<Tensor<1>>> {
        &self.parameters
    }

    /// CRC-32 of the parameters ([`parameter_checksum`]).
    pub fn checksum(&self) -> u32 {
        parameter_checksum(&self.parameters)
    }
}

/// Elements of every float parameter of `config`'s model, in module order (the model is
/// built once on the CPU to read them).
pub fn layout_of(config: &XFactorConfig) -> Result<Vec<usize>, ConfigError> {
    Ok(tensor_sizes(&XFactor::new(config, 0, &Device::flex())?))
}

/// Elements of every float parameter of `module`, in module order.
fn tensor_sizes<M: Module>(module: &M) -> Vec<usize> {
    struct Sizes(Vec<usize>);
    impl ModuleVisitor for Sizes {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.push(param.val().shape().num_elements());
        }
    }
    let mut sizes = Sizes(Vec::new());
    module.visit(&mut sizes);
    sizes.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stand_in_has_its_models_layout_and_moves_when_applied() {
        let device = Device::flex();
        let config = XFactorConfig::tiny(16);
        let model = XFactor::new(&config, 0, &device).unwrap();
        let layout = layout_of(&config).unwrap();
        let mut standin = LayoutModel::scaled(&layout, 1.0, &device);
        assert_eq!(standin.parameter_count(), parameter_count(&model));
        let half = LayoutModel::scaled(&layout, 0.5, &device).parameter_count();
        let rounding = layout.len();
        assert!(
            half * 2 >= standin.parameter_count()
                && half * 2 <= standin.parameter_count() + 2 * rounding
        );
        let mut gradients = vec![0.0; standin.parameter_count()];
        standin
            .gradients_into(standin.backward(), &mut gradients)
            .unwrap();
        assert!(gradients.iter().any(|g| *g != 0.0));
        let before = standin.checksum();
        let grads = standin.upload(&gradients).unwrap();
        let report = standin.update(&grads, 1e-3);
        assert!(report.applied && report.grad_norm > 0.0);
        assert_ne!(
            standin.checksum(),
            before,
            "the update moved the parameters"
        );
        assert!(standin.upload(&gradients[1..]).is_err());
    }
}
