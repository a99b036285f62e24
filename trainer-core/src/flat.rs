//! Gradients and parameters as one flat `f32` vector in module order: the form a collective
//! exchanges between processes, and the bytes a parameter checksum covers.
//!
//! Module order is fixed by the model's structure, so every process that built the same
//! configuration agrees on which element is which without exchanging names.

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};

/// Elements of every float parameter of `module`, in module order.
pub fn parameter_count<M: Module>(module: &M) -> usize {
    struct Count(usize);
    impl ModuleVisitor for Count {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0 += param.val().shape().num_elements();
        }
    }
    let mut count = Count(0);
    module.visit(&mut count);
    count.0
}

/// Every parameter's gradient appended in module order; a parameter without a gradient
/// contributes zeros (as JAX's dense gradients would), so all processes agree on the layout.
pub fn flatten_gradients<M: Module>(module: &M, grads: &GradientsParams) -> Vec<f32> {
    struct Flatten<'a> {
        grads: &'a GradientsParams,
        out: Vec<f32>,
    }
    impl ModuleVisitor for Flatten<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let elements = param.val().shape().num_elements();
            match self.grads.get::<D>(param.id) {
                Some(grad) => self.out.extend(grad.into_data().iter::<f32>()),
                None => self.out.extend(std::iter::repeat_n(0.0, elements)),
            }
        }
    }
    let mut flatten = Flatten {
        grads,
        out: Vec::with_capacity(parameter_count(module)),
    };
    module.visit(&mut flatten);
    flatten.out
}

/// Why a flat vector does not fit a module.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("flat gradient of {found} values does not fit a model of {expected} parameters")]
pub struct LayoutError {
    /// Parameters of the model.
    pub expected: usize,
    /// Length of the vector.
    pub found: usize,
}

/// The inverse of [`flatten_gradients`]: gradients for every parameter of `module`, on the
/// device of the parameter's values (untracked, as backward passes produce them).
pub fn unflatten_gradients<M: Module>(
    module: &M,
    flat: &[f32],
) -> Result<GradientsParams, LayoutError> {
    let expected = parameter_count(module);
    if flat.len() != expected {
        return Err(LayoutError {
            expected,
            found: flat.len(),
        });
    }
    struct Unflatten<'a> {
        flat: &'a [f32],
        offset: usize,
        out: GradientsParams,
    }
    impl ModuleVisitor for Unflatten<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let value = param.val();
            let shape = value.shape();
            let device: Device = if value.is_autodiff() {
                value.inner().device()
            } else {
                value.device()
            };
            let elements = shape.num_elements();
            let values = self.flat[self.offset..self.offset + elements].to_vec();
            self.offset += elements;
            let tensor = Tensor::<D>::from_data(TensorData::new(values, shape), &device);
            self.out.register(param.id, tensor);
        }
    }
    let mut unflatten = Unflatten {
        flat,
        offset: 0,
        out: GradientsParams::new(),
    };
    module.visit(&mut unflatten);
    Ok(unflatten.out)
}

/// Every float parameter's values appended in module order: what two replicas compare to a
/// tolerance, where [`parameter_checksum`] tells only bitwise equality.
pub fn flatten_parameters<M: Module>(module: &M) -> Vec<f32> {
    struct Flatten(Vec<f32>);
    impl ModuleVisitor for Flatten {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.extend(param.val().into_data().iter::<f32>());
        }
    }
    let mut flatten = Flatten(Vec::with_capacity(parameter_count(module)));
    module.visit(&mut flatten);
    flatten.0
}

/// CRC-32 of every parameter's little-endian `f32` bytes in module order: equal on two
/// processes exactly when their parameters are bitwise equal (up to CRC collisions).
pub fn parameter_checksum<M: Module>(module: &M) -> u32 {
    struct Checksum(crc32fast::Hasher);
    impl ModuleVisitor for Checksum {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            for value in param.val().into_data().iter::<f32>() {
                self.0.update(&value.to_le_bytes());
            }
        }
    }
    let mut checksum = Checksum(crc32fast::Hasher::new());
    module.visit(&mut checksum);
    checksum.0.finalize()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{XFactor, XFactorConfig};

    #[test]
    fn gradients_round_trip_through_the_flat_layout() {
        let device = Device::flex();
        let model = XFactor::new(&XFactorConfig::tiny(16), 3, &device).unwrap();
        let count = parameter_count(&model);
        let flat: Vec<f32> = (0..count).map(|i| (i % 97) as f32 * 0.5 - 3.0).collect();
        let grads = unflatten_gradients(&model, &flat).unwrap();
        assert_eq!(flatten_gradients(&model, &grads), flat);
        let short = unflatten_gradients(&model, &flat[1..]).unwrap_err();
        assert_eq!(short.found, count - 1);
    }

    #[test]
    fn checksums_tell_models_apart() {
        let device = Device::flex();
        let config = XFactorConfig::tiny(16);
        let a = XFactor::new(&config, 3, &device).unwrap();
        let b = XFactor::new(&config, 3, &device).unwrap();
        let c = XFactor::new(&config, 4, &device).unwrap();
        assert_eq!(parameter_checksum(&a), parameter_checksum(&b));
        assert_ne!(parameter_checksum(&a), parameter_checksum(&c));
    }
}
