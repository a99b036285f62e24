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

/// Every parameter's gradient written into `out` in module order, one host copy per
/// gradient: `grads` is taken whole, so a gradient no one else holds is read without a copy
/// where the backend allows it (burn's CPU backend hands its buffer over), then copied once
/// into place. A parameter without a gradient gets zeros (as JAX's dense gradients would),
/// so all processes agree on the layout. `out` must hold exactly [`parameter_count`] values:
/// the caller keeps it from one step to the next instead of allocating the model's size again.
pub fn flatten_gradients_into<M: Module>(
    module: &M,
    grads: GradientsParams,
    out: &mut [f32],
) -> Result<(), LayoutError> {
    let expected = parameter_count(module);
    if out.len() != expected {
        return Err(LayoutError {
            expected,
            found: out.len(),
        });
    }
    struct Flatten<'a> {
        grads: GradientsParams,
        out: &'a mut [f32],
        offset: usize,
    }
    impl ModuleVisitor for Flatten<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let elements = param.val().shape().num_elements();
            let target = &mut self.out[self.offset..self.offset + elements];
            self.offset += elements;
            match self.grads.remove::<D>(param.id) {
                Some(grad) => copy_values(&grad.into_data(), target),
                None => target.fill(0.0),
            }
        }
    }
    module.visit(&mut Flatten {
        grads,
        out,
        offset: 0,
    });
    Ok(())
}

/// `data`'s values into `target`: one `memcpy` when they are `f32` already (always, for the
/// float32 gradients the trainer keeps), else converted one by one.
fn copy_values(data: &TensorData, target: &mut [f32]) {
    match data.as_slice::<f32>() {
        Ok(values) => target.copy_from_slice(values),
        Err(_) => target
            .iter_mut()
            .zip(data.iter::<f32>())
            .for_each(|(slot, value)| *slot = value),
    }
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
///
/// The parameters are cut into as many runs of whole tensors as the host has cores (fewer
/// for a small model: one per [`BYTES_PER_HASHING_THREAD`]), about equal in bytes; each run
/// is read to the host one tensor at a time and hashed in bulk on a thread of its own (a lone
/// run on the caller's), and the runs' CRCs are joined with CRC-32's combination rule. That is
/// the same value as one CRC over the concatenated bytes, at memory speed (the paper model's
/// 1.22 GB took 2.6 s fed four bytes at a time; `benches/checksum.rs` measures both), holding
/// one tensor's host copy per thread at a time.
pub fn parameter_checksum<M: Module>(module: &M) -> u32 {
    struct Collect(Vec<Tensor<1>>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.push(param.val().reshape([-1]));
        }
    }
    let mut collect = Collect(Vec::new());
    module.visit(&mut collect);
    let bytes: usize = collect
        .0
        .iter()
        .map(|tensor| tensor.shape().num_elements() * std::mem::size_of::<f32>())
        .sum();
    let threads = host_cores().min(bytes.div_ceil(BYTES_PER_HASHING_THREAD));
    crc32_of_tensors(&collect.0, threads)
}

/// Bytes a hashing thread is given at least: CRC-32 takes about 2 ms for 16 MiB here, some
/// fifty times a thread's start, so a small model (the tiny one checks every step) is hashed
/// on the caller's thread alone.
const BYTES_PER_HASHING_THREAD: usize = 16 << 20;

/// The host's cores, asked once (the answer reads the cgroup's limits from files).
fn host_cores() -> usize {
    static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// CRC-32 of the bytes of `tensors` one after another, in `threads` runs of whole tensors
/// hashed side by side and combined in order.
fn crc32_of_tensors(tensors: &[Tensor<1>], threads: usize) -> u32 {
    let sizes: Vec<usize> = tensors.iter().map(|t| t.shape().num_elements()).collect();
    let hash = |run: &[Tensor<1>]| {
        let mut hasher = crc32fast::Hasher::new();
        for tensor in run {
            hasher.update(tensor.clone().into_data().as_bytes());
        }
        hasher
    };
    let runs = runs(&sizes, threads);
    if let [only] = runs.as_slice() {
        return hash(&tensors[only.clone()]).finalize();
    }
    let hashers: Vec<crc32fast::Hasher> = std::thread::scope(|scope| {
        let handles: Vec<_> = runs
            .into_iter()
            .map(|run| {
                let run = &tensors[run];
                scope.spawn(move || hash(run))
            })
            .collect();
        handles
            .into_iter()
            .map(|handle| match handle.join() {
                Ok(hasher) => hasher,
                Err(panic) => std::panic::resume_unwind(panic),
            })
            .collect()
    });
    let mut combined = crc32fast::Hasher::new();
    hashers.iter().for_each(|hasher| combined.combine(hasher));
    combined.finalize()
}

/// `sizes` cut into at most `parts` consecutive runs of about equal sum (each run closes
/// once it reaches its share), covering every index in order.
fn runs(sizes: &[usize], parts: usize) -> Vec<std::ops::Range<usize>> {
    let total: usize = sizes.iter().sum();
    let share = total.div_ceil(parts.max(1)).max(1);
    let mut runs = Vec::new();
    let (mut start, mut filled) = (0, 0);
    for (index, size) in sizes.iter().enumerate() {
        filled += size;
        if filled >= share {
            runs.push(start..index + 1);
            (start, filled) = (index + 1, 0);
        }
    }
    if start < sizes.len() {
        runs.push(start..sizes.len());
    }
    runs
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
        let mut back = vec![f32::NAN; count];
        flatten_gradients_into(&model, grads, &mut back).unwrap();
        assert_eq!(back, flat);
        let mut wrong = vec![0.0; count + 1];
        let grads = unflatten_gradients(&model, &flat).unwrap();
        let error = flatten_gradients_into(&model, grads, &mut wrong).unwrap_err();
        assert_eq!((error.expected, error.found), (count, count + 1));
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

    #[test]
    fn the_bulk_checksum_is_the_crc_of_every_value_in_module_order() {
        let model = XFactor::new(&XFactorConfig::tiny(16), 3, &Device::flex()).unwrap();
        let mut one_by_one = crc32fast::Hasher::new();
        for value in flatten_parameters(&model) {
            one_by_one.update(&value.to_le_bytes());
        }
        assert_eq!(parameter_checksum(&model), one_by_one.finalize());
    }

    #[test]
    fn runs_cover_every_tensor_in_order_and_hash_alike_however_many() {
        assert_eq!(runs(&[5, 1, 1, 5, 4], 2), [0..4, 4..5]);
        assert_eq!(runs(&[10, 1], 4), [0..1, 1..2]);
        assert_eq!(runs(&[], 3), Vec::<std::ops::Range<usize>>::new());
        let device = Device::flex();
        let tensors: Vec<Tensor<1>> = (0..7)
            .map(|i| {
                let values: Vec<f32> = (0..1000 * (i + 1))
                    .map(|v| v as f32 * 0.37 - i as f32)
                    .collect();
                Tensor::from_data(TensorData::new(values, [1000 * (i + 1)]), &device)
            })
            .collect();
        let mut whole = crc32fast::Hasher::new();
        tensors
            .iter()
            .for_each(|t| whole.update(t.clone().into_data().as_bytes()));
        let whole = whole.finalize();
        for threads in [1, 2, 3, 16] {
            assert_eq!(
                crc32_of_tensors(&tensors, threads),
                whole,
                "{threads} threads"
            );
        }
    }
}
