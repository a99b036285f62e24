//! The authors' optimiser: AdamW with decoupled, learning-rate-scaled weight decay on all but
//! norms, LayerScale, biases and `global_embed`; global-norm clipping; an optional skip of
//! updates whose gradient norm explodes; and the warm-up + cosine learning-rate schedule.
//!
//! Written out rather than taken from burn because burn's AdamW decays every parameter and
//! defaults to `eps = 1e-5`, while optax (the reference) uses `1e-8` and a decay mask.

use std::collections::HashMap;

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::Tensor;

use settings::optim::AdamWConfig;

use crate::flax::{FlaxError, FlaxTensors, HostTensor, flax_name};

/// Whether the parameter with this flax name is weight-decayed: every parameter except
/// LayerNorm, RMSNorm and LayerScale parameters, biases and `global_embed`.
pub fn is_decayed(flax_name: &str) -> bool {
    let mut parts = flax_name.rsplit('.');
    let leaf = parts.next().unwrap_or_default();
    let owner = parts.next().unwrap_or_default();
    let exempt_owner = ["LayerNorm_", "RMSNorm_", "LayerScale_"]
        .iter()
        .any(|prefix| owner.starts_with(prefix));
    !(leaf == "bias" || leaf == "global_embed" || exempt_owner)
}

/// What one call of [`AdamW::step`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UpdateReport {
    /// Global gradient norm before clipping.
    pub grad_norm: f64,
    /// False when the update was skipped for an exploding norm.
    pub applied: bool,
}

#[derive(Debug, Clone)]
struct Moments {
    first: Tensor<1>,
    second: Tensor<1>,
}

/// AdamW state: the update count and both moments of every parameter.
#[derive(Debug, Clone)]
pub struct AdamW {
    config: AdamWConfig,
    updates: u64,
    moments: HashMap<ParamId, Moments>,
}

impl AdamW {
    /// A fresh optimiser (zero moments).
    pub fn new(config: AdamWConfig) -> Self {
        Self {
            config,
            updates: 0,
            moments: HashMap::new(),
        }
    }

    /// Updates applied so far (the bias-correction step count).
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// Clips `grads`, then applies one AdamW update with learning rate `lr` to every parameter
    /// of `model` that has a gradient.
    pub fn step<M: Module>(
        &mut self,
        model: M,
        grads: &GradientsParams,
        lr: f64,
    ) -> (M, UpdateReport) {
        let grad_norm = global_norm(&model, grads);
        if self
            .config
            .skip_norm_above
            .is_some_and(|limit| grad_norm > limit || grad_norm.is_nan())
        {
            return (
                model,
                UpdateReport {
                    grad_norm,
                    applied: false,
                },
            );
        }
        let clip_scale = match self.config.clip_norm {
            Some(limit) if grad_norm > limit => limit / grad_norm,
            _ => 1.0,
        };
        self.updates += 1;
        let mut update = Update {
            optimizer: self,
            grads,
            lr,
            clip_scale,
            path: Vec::new(),
        };
        let model = model.map(&mut update);
        (
            model,
            UpdateReport {
                grad_norm,
                applied: true,
            },
        )
    }
}

impl AdamW {
    /// Both moments of every parameter, named `first.<flax name>` / `second.<flax name>`, so the
    /// state survives a rebuild of the model (which gives parameters new ids).
    pub fn export_moments<M: Module>(&self, model: &M) -> Vec<(String, HostTensor)> {
        let mut names = ParamNames::default();
        model.visit(&mut names);
        let mut out = Vec::new();
        for (id, name, shape) in names.params {
            if let Some(state) = self.moments.get(&id) {
                for (prefix, tensor) in [("first", &state.first), ("second", &state.second)] {
                    let mut host = HostTensor::from_tensor(tensor.clone());
                    host.shape = shape.clone();
                    out.push((format!("{prefix}.{name}"), host));
                }
            }
        }
        out
    }

    /// Restores moments written by [`AdamW::export_moments`] for `model`'s parameters, and the
    /// update count; a missing or misshapen moment is an error naming it.
    pub fn import_moments<M: Module>(
        &mut self,
        model: &M,
        tensors: &FlaxTensors,
        updates: u64,
    ) -> Result<(), FlaxError> {
        let mut names = ParamNames::default();
        model.visit(&mut names);
        let device = names.device.unwrap_or_default();
        self.moments.clear();
        self.updates = updates;
        if updates == 0 {
            return Ok(());
        }
        for (id, name, shape) in names.params {
            let fetch = |prefix: &str| -> Result<Tensor<1>, FlaxError> {
                let stored = tensors.expect(&format!("{prefix}.{name}"), &shape)?;
                let flat = HostTensor {
                    shape: vec![stored.values.len()],
                    values: stored.values.clone(),
                };
                Ok(flat.to_tensor::<1>(&device))
            };
            let first = fetch("first")?;
            let second = fetch("second")?;
            self.moments.insert(id, Moments { first, second });
        }
        Ok(())
    }
}

/// Every float parameter's id, flax name and shape, in visiting order.
#[derive(Default)]
struct ParamNames {
    path: Vec<String>,
    params: Vec<(ParamId, String, Vec<usize>)>,
    device: Option<burn::tensor::Device>,
}

impl ModuleVisitor for ParamNames {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let value = param.val();
        if self.device.is_none() {
            let device = value.device();
            self.device = Some(if value.is_autodiff() {
                value.clone().inner().device()
            } else {
                device
            });
        }
        self.params
            .push((param.id, flax_name(&self.path), value.dims().to_vec()));
    }
}

/// Square root of the sum of all squared gradient entries.
pub fn global_norm<M: Module>(model: &M, grads: &GradientsParams) -> f64 {
    struct SquaredSum<'a> {
        grads: &'a GradientsParams,
        total: Option<Tensor<1>>,
    }
    impl ModuleVisitor for SquaredSum<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(grad) = self.grads.get::<D>(param.id) {
                let squares = grad.square().sum();
                self.total = Some(match self.total.take() {
                    Some(total) => total + squares,
                    None => squares,
                });
            }
        }
    }
    let mut sum = SquaredSum { grads, total: None };
    model.visit(&mut sum);
    sum.total
        .map_or(0.0, |total| total.into_scalar::<f64>().sqrt())
}

struct Update<'a> {
    optimizer: &'a mut AdamW,
    grads: &'a GradientsParams,
    lr: f64,
    clip_scale: f64,
    path: Vec<String>,
}

impl ModuleMapper for Update<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let Some(grad) = self.grads.get::<D>(param.id) else {
            return param;
        };
        let config = &self.optimizer.config;
        let decay = if is_decayed(&flax_name(&self.path)) {
            config.weight_decay
        } else {
            0.0
        };
        let t = self.optimizer.updates as i32;
        let (beta1, beta2) = (config.beta1, config.beta2);
        let (epsilon, lr, clip_scale) = (config.epsilon, self.lr, self.clip_scale);
        let id = param.id;
        let moments = &mut self.optimizer.moments;
        param.map(|tensor| {
            let requires_grad = tensor.is_require_grad();
            let tracked = tensor.is_autodiff();
            // The device's gradient checkpointing rides on each tracked tensor; the updated
            // parameter must carry it on, or the next step mixes strategies.
            let strategy = if tracked {
                tensor.gradient_checkpointing_strategy()
            } else {
                None
            };
            let shape = tensor.dims();
            let count = shape.iter().product::<usize>();
            let value = if tracked { tensor.inner() } else { tensor }.reshape([count]);
            let grad = grad.reshape([count]) * clip_scale;
            let state = moments.entry(id).or_insert_with(|| Moments {
                first: value.zeros_like(),
                second: value.zeros_like(),
            });
            state.first = state.first.clone() * beta1 + grad.clone() * (1.0 - beta1);
            state.second = state.second.clone() * beta2 + grad.square() * (1.0 - beta2);
            let first_hat = state.first.clone() / (1.0 - beta1.powi(t));
            let second_hat = state.second.clone() / (1.0 - beta2.powi(t));
            let mut step = first_hat / (second_hat.sqrt() + epsilon);
            if decay != 0.0 {
                step = step + value.clone() * decay;
            }
            let updated = (value - step * lr).reshape(shape);
            if tracked {
                let tracked = Tensor::from_inner(updated);
                let tracked = match strategy {
                    Some(strategy) => tracked.with_gradient_checkpointing_strategy(strategy),
                    None => tracked,
                };
                tracked.set_require_grad(requires_grad)
            } else {
                updated
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Dense, LayerNorm, ParamInit};
    use crate::{XFactor, XFactorConfig};
    use burn::tensor::{Device, TensorData};

    #[test]
    fn decay_skips_norms_layerscale_biases_and_global_embed() {
        for name in [
            "PoseEnc.layers_0.Dense_0.kernel",
            "PoseEnc.PoseHead_0.MLP3_0.Dense_2.kernel",
            "Render.MLP2_1.Dense_0.kernel",
        ] {
            assert!(is_decayed(name), "{name}");
        }
        for name in [
            "PoseEnc.global_embed",
            "PoseEnc.layers_1.Dense_1.bias",
            "Render.layers_0.LayerNorm_0.scale",
            "Render.LayerNorm_0.bias",
            "PoseEnc.layers_0.RMSNorm_3.alpha",
            "Render.layers_1.LayerScale_1.alpha",
        ] {
            assert!(!is_decayed(name), "{name}");
        }
        // Over a whole model: only the Dense kernels decay.
        struct Names(Vec<String>, Vec<String>);
        impl ModuleVisitor for Names {
            fn enter_module(&mut self, name: &str, _: &str) {
                self.0.push(name.to_string());
            }
            fn exit_module(&mut self, _: &str, _: &str) {
                self.0.pop();
            }
            fn visit_float<const D: usize>(&mut self, _: &Param<Tensor<D>>) {
                self.1.push(flax_name(&self.0));
            }
        }
        let model = XFactor::new(&XFactorConfig::benchmark(), 0, &Device::flex()).unwrap();
        let mut names = Names(Vec::new(), Vec::new());
        model.visit(&mut names);
        let decayed: Vec<_> = names.1.iter().filter(|n| is_decayed(n)).collect();
        assert!(decayed.iter().all(|n| n.ends_with(".kernel")));
        let kernels = names.1.iter().filter(|n| n.ends_with(".kernel")).count();
        assert_eq!(decayed.len(), kernels);
    }

    #[derive(Module, Debug)]
    struct Probe {
        dense_0: Dense,
        out_norm: LayerNorm,
    }

    fn probe(device: &Device) -> Probe {
        let mut init = ParamInit::new(1, device);
        Probe {
            dense_0: Dense::new(&mut init, 2, 2, true),
            out_norm: LayerNorm::new(&mut init, 2, true),
        }
    }

    fn flat<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
        tensor.try_into_vec_as::<f32>().unwrap()
    }

    /// Loss `sum(kernel * c) + sum(scale * c)`, so each gradient is `c`.
    fn gradients(model: &Probe, coefficient: f32, device: &Device) -> GradientsParams {
        let c2 = Tensor::<2>::from_data(TensorData::new(vec![coefficient; 4], [2, 2]), device);
        let c1 = Tensor::<1>::from_data(TensorData::new(vec![coefficient; 2], [2]), device);
        let loss =
            (model.dense_0.kernel.val() * c2).sum() + (model.out_norm.scale.val() * c1).sum();
        GradientsParams::from_grads(loss.backward(), model)
    }

    #[test]
    fn first_update_is_sign_descent_plus_masked_decay() {
        let device = Device::flex().autodiff();
        let model = probe(&device);
        let kernel_before = flat(model.dense_0.kernel.val());
        let scale_before = flat(model.out_norm.scale.val());
        let grads = gradients(&model, 0.1, &device);
        let mut optimizer = AdamW::new(AdamWConfig::default());
        let lr = 0.01;
        let (model, report) = optimizer.step(model, &grads, lr);
        assert!(report.applied);
        assert!((report.grad_norm - (6.0f64 * 0.01).sqrt()).abs() < 1e-6);
        for (after, before) in flat(model.dense_0.kernel.val()).iter().zip(&kernel_before) {
            let expected = before - (lr as f32) * (0.1 / (0.1 + 1e-8) + 5e-3 * before);
            assert!((after - expected).abs() < 1e-7, "{after} vs {expected}");
        }
        for (after, before) in flat(model.out_norm.scale.val()).iter().zip(&scale_before) {
            let expected = before - (lr as f32) * (0.1 / (0.1 + 1e-8));
            assert!((after - expected).abs() < 1e-7, "{after} vs {expected}");
        }
        assert_eq!(optimizer.updates(), 1);
    }

    #[test]
    fn exploding_updates_are_skipped_and_large_ones_clipped() {
        let device = Device::flex().autodiff();
        let model = probe(&device);
        let kernel_before = flat(model.dense_0.kernel.val());
        let grads = gradients(&model, 10.0, &device);
        let mut skipping = AdamW::new(AdamWConfig {
            skip_norm_above: Some(5.0),
            ..AdamWConfig::default()
        });
        let (model, report) = skipping.step(model, &grads, 0.01);
        assert!(!report.applied && report.grad_norm > 5.0);
        assert_eq!(flat(model.dense_0.kernel.val()), kernel_before);
        assert_eq!(skipping.updates(), 0);

        // Clipped to norm 1 then two updates: the second-moment history makes the second
        // update depend on the clipped scale, so compare against an explicit computation.
        let mut clipped = AdamW::new(AdamWConfig::default());
        let (model, _) = clipped.step(model, &grads, 0.01);
        let small = gradients(&model, 0.1, &device);
        let before = flat(model.out_norm.scale.val());
        let (model, report) = clipped.step(model, &small, 0.01);
        assert!(report.applied);
        let g1 = 10.0f64 / (6.0f64 * 100.0).sqrt();
        let g2 = 0.1f64;
        let m = (0.9 * 0.1 * g1 + 0.1 * g2) / (1.0 - 0.9f64.powi(2));
        let v = (0.95 * 0.05 * g1 * g1 + 0.05 * g2 * g2) / (1.0 - 0.95f64.powi(2));
        let expected_step = 0.01 * m / (v.sqrt() + 1e-8);
        for (after, before) in flat(model.out_norm.scale.val()).iter().zip(&before) {
            assert!(((before - after) as f64 - expected_step).abs() < 1e-7);
        }
    }
}
