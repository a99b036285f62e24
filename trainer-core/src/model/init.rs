//! Deterministic parameter initialisation as the authors train from scratch.

use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};

use data::rng::Stream;
use settings::model::Precision;

/// Hands out freshly initialised parameters, each drawn from its own stream keyed by
/// `(seed, parameter index)`, so a model built twice from one seed is bitwise identical on any
/// backend.
pub struct ParamInit<'a> {
    device: &'a Device,
    seed: u64,
    next_index: u64,
    compute: Precision,
}

impl<'a> ParamInit<'a> {
    /// Starts numbering parameters from zero.
    pub fn new(seed: u64, device: &'a Device) -> Self {
        Self {
            device,
            seed,
            next_index: 0,
            compute: Precision::F32,
        }
    }

    /// Layers built from here compute their products in `compute`'s type (`model.compute`).
    pub fn computing_in(self, compute: Precision) -> Self {
        Self { compute, ..self }
    }

    /// The type layers built from here compute their products in.
    pub fn compute(&self) -> Precision {
        self.compute
    }

    fn stream(&mut self) -> Stream {
        let stream = Stream::new(&[self.seed, self.next_index]);
        self.next_index += 1;
        stream
    }

    fn param<const D: usize>(&self, values: Vec<f32>, shape: [usize; D]) -> Param<Tensor<D>> {
        Param::from_tensor(Tensor::from_data(
            TensorData::new(values, shape),
            self.device,
        ))
    }

    /// Xavier-uniform kernel `(fan_in, fan_out)`: `U(-a, a)`, `a = sqrt(6 / (fan_in + fan_out))`.
    pub fn xavier_uniform(&mut self, fan_in: usize, fan_out: usize) -> Param<Tensor<2>> {
        let limit = (6.0 / (fan_in + fan_out) as f64).sqrt();
        let mut stream = self.stream();
        let values = (0..fan_in * fan_out)
            .map(|_| stream.uniform_in(-limit, limit) as f32)
            .collect();
        self.param(values, [fan_in, fan_out])
    }

    /// Gaussian values `N(0, std^2)` of any shape (biases, `global_embed`).
    pub fn normal<const D: usize>(&mut self, shape: [usize; D], std: f64) -> Param<Tensor<D>> {
        let mut stream = self.stream();
        let count = shape.iter().product();
        let values = (0..count).map(|_| (stream.normal() * std) as f32).collect();
        self.param(values, shape)
    }

    /// A constant parameter (norm scales `1`, LayerNorm biases `0`, LayerScale `0.01`).
    pub fn constant<const D: usize>(&mut self, shape: [usize; D], value: f32) -> Param<Tensor<D>> {
        self.next_index += 1;
        self.param(vec![value; shape.iter().product()], shape)
    }
}
