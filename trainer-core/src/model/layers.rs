//! The small building blocks shared by PoseEnc and Render: dense layers, norms, LayerScale and
//! the two MLP shapes.

use burn::module::{Module, Param};
use burn::tensor::Tensor;
use burn::tensor::activation::sigmoid;

use super::init::ParamInit;
use super::precision::linear_in;
use settings::model::Precision;

/// Standard deviation of freshly initialised biases.
const BIAS_STD: f64 = 1e-6;
/// LayerNorm epsilon used throughout the authors' release.
const LAYER_NORM_EPS: f64 = 1e-6;
/// RMSNorm epsilon used throughout the authors' release.
const RMS_NORM_EPS: f64 = 1e-5;
/// LayerScale's initial value.
const LAYER_SCALE_INIT: f32 = 0.01;

/// GELU with the tanh approximation, the variant the authors use everywhere.
///
/// Computed through the identity `0.5 x (1 + tanh(u)) = x * sigmoid(2u)`, which is exact and
/// avoids the scalar `tanh` that dominated the CPU profile.
pub fn gelu_tanh<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    const TWO_SQRT_2_OVER_PI: f64 = 2.0 * 0.797_884_560_802_865_4;
    let cubic = x.clone() * x.clone() * x.clone();
    let doubled_inner = (x.clone() + cubic * 0.044715) * TWO_SQRT_2_OVER_PI;
    x * sigmoid(doubled_inner)
}

/// Fully connected layer with an `in x out` kernel, the flax layout, so imported weights need
/// no transposition.
#[derive(Module, Debug)]
pub struct Dense {
    /// `(in, out)` kernel.
    pub kernel: Param<Tensor<2>>,
    /// Optional `(out)` bias.
    pub bias: Option<Param<Tensor<1>>>,
    /// The type the product computes in (`model.compute`).
    #[module(skip)]
    pub compute: Precision,
}

impl Dense {
    /// Xavier-uniform kernel, `N(0, 1e-6)` bias when `with_bias`.
    pub fn new(init: &mut ParamInit, fan_in: usize, fan_out: usize, with_bias: bool) -> Self {
        let kernel = init.xavier_uniform(fan_in, fan_out);
        let bias = with_bias.then(|| init.normal([fan_out], BIAS_STD));
        Self {
            kernel,
            bias,
            compute: init.compute(),
        }
    }

    /// Applies the layer over the last axis.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        linear_in(
            x,
            self.kernel.val(),
            self.bias.as_ref().map(Param::val),
            self.compute,
        )
    }
}

/// LayerNorm over the last axis, epsilon `1e-6`, learned scale and optional bias.
#[derive(Module, Debug)]
pub struct LayerNorm {
    /// Per-channel scale, initialised to one.
    pub scale: Param<Tensor<1>>,
    /// Per-channel bias, initialised to zero; absent in the pre-attention norm.
    pub bias: Option<Param<Tensor<1>>>,
}

impl LayerNorm {
    /// Scale one, bias zero when `with_bias`.
    pub fn new(init: &mut ParamInit, width: usize, with_bias: bool) -> Self {
        let scale = init.constant([width], 1.0);
        let bias = with_bias.then(|| init.constant([width], 0.0));
        Self { scale, bias }
    }

    /// Normalises over the last axis.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        burn::tensor::module::layer_norm(
            x,
            self.scale.val(),
            self.bias.as_ref().map(Param::val),
            LAYER_NORM_EPS,
        )
    }
}

/// Per-head RMSNorm scale for queries or keys; [`rms_normalize`] applies it (the layer
/// normalises its four query/key tensors in one pass).
#[derive(Module, Debug)]
pub struct RmsNorm {
    /// `(heads, head_dim)` scale, initialised to one.
    pub alpha: Param<Tensor<2>>,
}

impl RmsNorm {
    /// Scale one.
    pub fn new(init: &mut ParamInit, num_heads: usize, head_dim: usize) -> Self {
        Self {
            alpha: init.constant([num_heads, head_dim], 1.0),
        }
    }
}

/// RMSNorm over the last axis with scale `alpha` (broadcast against `x`), epsilon `1e-5`.
pub fn rms_normalize<const D: usize>(x: Tensor<D>, alpha: Tensor<D>) -> Tensor<D> {
    let inv_rms = (x.clone().square().mean_dim(D - 1) + RMS_NORM_EPS)
        .sqrt()
        .recip();
    x * inv_rms * alpha
}

/// Learned per-channel residual gate, initialised to `0.01` so fresh layers start near identity.
#[derive(Module, Debug)]
pub struct LayerScale {
    /// `(C)` gate.
    pub alpha: Param<Tensor<1>>,
}

impl LayerScale {
    /// Gate `0.01`.
    pub fn new(init: &mut ParamInit, width: usize) -> Self {
        Self {
            alpha: init.constant([width], LAYER_SCALE_INIT),
        }
    }

    /// Scales the last axis.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        x * self.alpha.val().unsqueeze::<D>()
    }
}

/// `Dense(hidden) -> GELU -> Dense(out)`.
#[derive(Module, Debug)]
pub struct Mlp2 {
    /// Expansion layer.
    pub dense_0: Dense,
    /// Projection to the output size.
    pub dense_1: Dense,
}

impl Mlp2 {
    /// `input -> hidden -> output`, biases on both layers.
    pub fn new(init: &mut ParamInit, input: usize, hidden: usize, output: usize) -> Self {
        Self {
            dense_0: Dense::new(init, input, hidden, true),
            dense_1: Dense::new(init, hidden, output, true),
        }
    }

    /// Applies the MLP over the last axis.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        self.dense_1.forward(gelu_tanh(self.dense_0.forward(x)))
    }
}

/// `Dense(hidden) -> GELU -> Dense(width) -> GELU -> Dense(out)`.
#[derive(Module, Debug)]
pub struct Mlp3 {
    /// Expansion layer.
    pub dense_0: Dense,
    /// Back to the model width.
    pub dense_1: Dense,
    /// Projection to the output size.
    pub dense_2: Dense,
}

impl Mlp3 {
    /// `input -> hidden -> width -> output`, biases on all layers.
    pub fn new(
        init: &mut ParamInit,
        input: usize,
        hidden: usize,
        width: usize,
        output: usize,
    ) -> Self {
        Self {
            dense_0: Dense::new(init, input, hidden, true),
            dense_1: Dense::new(init, hidden, width, true),
            dense_2: Dense::new(init, width, output, true),
        }
    }

    /// Applies the MLP over the last axis.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let hidden = gelu_tanh(self.dense_0.forward(x));
        self.dense_2
            .forward(gelu_tanh(self.dense_1.forward(hidden)))
    }
}
