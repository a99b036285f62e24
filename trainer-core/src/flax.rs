//! Tensors stored under the authors' flax names, and the mapping between those names and this
//! crate's module paths.
//!
//! The same mapping imports the authors' released weights, loads parity fixtures and names
//! gradients, so there is exactly one place that knows how the two layouts correspond.

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Device, Gradients, Tensor, TensorData};
use safetensors::{Dtype, SafeTensors};

/// Prefix of model parameters in a flax-layout file.
pub const PARAMS_PREFIX: &str = "params.";
/// Prefix of parameter gradients in a parity fixture.
pub const GRADS_PREFIX: &str = "grads.";

/// Why a flax-layout file could not be read or applied.
#[derive(Debug, thiserror::Error)]
pub enum FlaxError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// File at fault.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The bytes are not a valid safetensors file.
    #[error("{path} is not a valid safetensors file: {reason}")]
    Format {
        /// File at fault.
        path: PathBuf,
        /// What the parser reported.
        reason: String,
    },
    /// A tensor's element type cannot be converted to float32.
    #[error("tensor `{name}` has unsupported dtype {dtype}")]
    Dtype {
        /// Tensor at fault.
        name: String,
        /// Its stored type.
        dtype: String,
    },
    /// A tensor the model needs is absent.
    #[error("tensor `{name}` is missing (the model expects shape {expected:?})")]
    Missing {
        /// Flax name looked up.
        name: String,
        /// Shape the model expects.
        expected: Vec<usize>,
    },
    /// A tensor exists with the wrong shape.
    #[error("tensor `{name}` has shape {found:?} but the model expects {expected:?}")]
    Shape {
        /// Flax name at fault.
        name: String,
        /// Shape the model expects.
        expected: Vec<usize>,
        /// Shape stored in the file.
        found: Vec<usize>,
    },
    /// The file holds parameters the model has no place for (a different architecture).
    #[error("the file holds parameters this model does not have: {names:?}")]
    Unexpected {
        /// Names left over after loading.
        names: Vec<String>,
    },
    /// Several problems at once, reported together so one run shows them all.
    #[error("{} problems loading weights:\n  {}", .0.len(), .0.iter().map(ToString::to_string).collect::<Vec<_>>().join("\n  "))]
    Many(Vec<FlaxError>),
}

/// A float32 tensor in host memory.
#[derive(Debug, Clone, PartialEq)]
pub struct HostTensor {
    /// Dimensions, outermost first.
    pub shape: Vec<usize>,
    /// Row-major values.
    pub values: Vec<f32>,
}

impl HostTensor {
    /// Uploads to `device` as a rank-`D` tensor; the caller guarantees the rank.
    pub fn to_tensor<const D: usize>(&self, device: &Device) -> Tensor<D> {
        Tensor::from_data(
            TensorData::new(self.values.clone(), self.shape.clone()),
            device,
        )
    }

    /// Downloads a device tensor.
    pub fn from_tensor<const D: usize>(tensor: Tensor<D>) -> Self {
        let shape = tensor.dims().to_vec();
        let values = tensor
            .into_data()
            .try_into_vec_as::<f32>()
            .expect("every float tensor converts to f32");
        Self { shape, values }
    }

    /// Largest absolute value.
    pub fn max_abs(&self) -> f32 {
        self.values.iter().fold(0.0, |m, v| m.max(v.abs()))
    }
}

/// Every tensor of a safetensors file, converted to float32 and keyed by name.
#[derive(Debug, Default)]
pub struct FlaxTensors {
    tensors: BTreeMap<String, HostTensor>,
}

impl FlaxTensors {
    /// Reads a whole file.
    pub fn read(path: &Path) -> Result<Self, FlaxError> {
        let bytes = std::fs::read(path).map_err(|source| FlaxError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&bytes, path)
    }

    /// Parses safetensors bytes; `origin` only names the source in errors.
    pub fn parse(bytes: &[u8], origin: &Path) -> Result<Self, FlaxError> {
        let file = SafeTensors::deserialize(bytes).map_err(|e| FlaxError::Format {
            path: origin.to_path_buf(),
            reason: e.to_string(),
        })?;
        let mut tensors = BTreeMap::new();
        for (name, view) in file.tensors() {
            let values = decode(&name, view.dtype(), view.data())?;
            let shape = view.shape().to_vec();
            tensors.insert(name, HostTensor { shape, values });
        }
        Ok(Self { tensors })
    }

    /// Looks a tensor up by its full name.
    pub fn get(&self, name: &str) -> Option<&HostTensor> {
        self.tensors.get(name)
    }

    /// The tensor `name`, or an error naming it.
    pub fn require(&self, name: &str) -> Result<&HostTensor, FlaxError> {
        self.get(name).ok_or_else(|| FlaxError::Missing {
            name: name.to_string(),
            expected: Vec::new(),
        })
    }

    /// The tensor `name`, which must have shape `expected`; an error names it and both shapes.
    pub fn expect(&self, name: &str, expected: &[usize]) -> Result<&HostTensor, FlaxError> {
        let stored = self.get(name).ok_or_else(|| FlaxError::Missing {
            name: name.to_string(),
            expected: expected.to_vec(),
        })?;
        if stored.shape != expected {
            return Err(FlaxError::Shape {
                name: name.to_string(),
                expected: expected.to_vec(),
                found: stored.shape.clone(),
            });
        }
        Ok(stored)
    }

    /// Names that start with `prefix`.
    pub fn names_with_prefix<'a>(&'a self, prefix: &'a str) -> impl Iterator<Item = &'a str> {
        self.tensors
            .keys()
            .filter(move |name| name.starts_with(prefix))
            .map(String::as_str)
    }
}

/// Tensors gathered elsewhere (an imported checkpoint, a test), keyed by full name.
impl FromIterator<(String, HostTensor)> for FlaxTensors {
    fn from_iter<I: IntoIterator<Item = (String, HostTensor)>>(iter: I) -> Self {
        Self {
            tensors: iter.into_iter().collect(),
        }
    }
}

fn decode(name: &str, dtype: Dtype, data: &[u8]) -> Result<Vec<f32>, FlaxError> {
    fn words<const N: usize>(data: &[u8]) -> impl Iterator<Item = [u8; N]> + '_ {
        data.chunks_exact(N)
            .map(|chunk| chunk.try_into().expect("chunks_exact yields N bytes"))
    }
    Ok(match dtype {
        Dtype::F32 => words::<4>(data).map(f32::from_le_bytes).collect(),
        Dtype::F64 => words::<8>(data)
            .map(|w| f64::from_le_bytes(w) as f32)
            .collect(),
        Dtype::BF16 => words::<2>(data)
            .map(|w| f32::from_bits((u16::from_le_bytes(w) as u32) << 16))
            .collect(),
        Dtype::I32 => words::<4>(data)
            .map(|w| i32::from_le_bytes(w) as f32)
            .collect(),
        Dtype::I64 => words::<8>(data)
            .map(|w| i64::from_le_bytes(w) as f32)
            .collect(),
        other => {
            return Err(FlaxError::Dtype {
                name: name.to_string(),
                dtype: format!("{other:?}"),
            });
        }
    })
}

/// The flax name (without prefix) of the parameter at a module path such as
/// `["pose_enc", "layers", "0", "qkv", "kernel"]` -> `PoseEnc.layers_0.Dense_0.kernel`.
pub fn flax_name(path: &[String]) -> String {
    let mut parts = Vec::with_capacity(path.len());
    let mut segments = path.iter().map(String::as_str);
    while let Some(segment) = segments.next() {
        if segment == "layers"
            && let Some(index) = segments.next()
        {
            parts.push(format!("layers_{index}"));
            continue;
        }
        parts.push(
            match segment {
                "pose_enc" => "PoseEnc",
                "render" => "Render",
                "patch_embed" => "Dense_0",
                "out_norm" | "attn_norm" => "LayerNorm_0",
                "pose_head" => "PoseHead_0.MLP3_0",
                "context_lift" | "mlp" => "MLP2_0",
                "target_lift" => "MLP2_1",
                "pixel_head" => "MLP3_0",
                "qkv" | "dense_0" => "Dense_0",
                "out_proj" | "dense_1" => "Dense_1",
                "dense_2" => "Dense_2",
                "q_norm" => "RMSNorm_0",
                "k_norm" => "RMSNorm_1",
                "qs_norm" => "RMSNorm_2",
                "ks_norm" => "RMSNorm_3",
                "attn_scale" => "LayerScale_0",
                "mlp_norm" => "LayerNorm_1",
                "mlp_scale" => "LayerScale_1",
                other => other,
            }
            .to_string(),
        );
    }
    parts.join(".")
}

/// Replaces every parameter of `module` by the tensor stored under `prefix` + its flax name.
///
/// All missing, misshapen and left-over tensors are reported together; on any error the module
/// is not returned, so a half-loaded model can never be used.
pub fn load_flax<M: Module>(module: M, source: &FlaxTensors, prefix: &str) -> Result<M, FlaxError> {
    let mut loader = Loader {
        source,
        prefix,
        path: Vec::new(),
        used: HashSet::new(),
        errors: Vec::new(),
    };
    let module = module.map(&mut loader);
    let unexpected: Vec<String> = source
        .names_with_prefix(prefix)
        .filter(|name| !loader.used.contains(*name))
        .map(str::to_string)
        .collect();
    let mut errors = loader.errors;
    if !unexpected.is_empty() {
        errors.push(FlaxError::Unexpected { names: unexpected });
    }
    match errors.len() {
        0 => Ok(module),
        1 => Err(errors.remove(0)),
        _ => Err(FlaxError::Many(errors)),
    }
}

struct Loader<'a> {
    source: &'a FlaxTensors,
    prefix: &'a str,
    path: Vec<String>,
    used: HashSet<String>,
    errors: Vec<FlaxError>,
}

impl ModuleMapper for Loader<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let name = format!("{}{}", self.prefix, flax_name(&self.path));
        let expected = param.lazy_shape().to_vec();
        let Some(stored) = self.source.get(&name) else {
            self.errors.push(FlaxError::Missing { name, expected });
            return param;
        };
        self.used.insert(name.clone());
        if stored.shape != expected {
            self.errors.push(FlaxError::Shape {
                name,
                expected,
                found: stored.shape.clone(),
            });
            return param;
        }
        let device = param.lazy_device();
        param.map(|old| {
            let requires_grad = old.is_require_grad();
            stored
                .to_tensor::<D>(&device)
                .set_require_grad(requires_grad)
        })
    }
}

/// Every parameter of `module`, keyed by flax name (without prefix): what an imported or
/// trained model holds, in the layout the authors' files use.
pub fn named_parameters<M: Module>(module: &M) -> BTreeMap<String, HostTensor> {
    struct Collector {
        path: Vec<String>,
        found: BTreeMap<String, HostTensor>,
    }
    impl ModuleVisitor for Collector {
        fn enter_module(&mut self, name: &str, _container_type: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _name: &str, _container_type: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.found
                .insert(flax_name(&self.path), HostTensor::from_tensor(param.val()));
        }
    }
    let mut collector = Collector {
        path: Vec::new(),
        found: BTreeMap::new(),
    };
    module.visit(&mut collector);
    collector.found
}

/// The gradient of every parameter of `module`, keyed by flax name (without prefix).
pub fn named_gradients<M: Module>(module: &M, grads: &Gradients) -> BTreeMap<String, HostTensor> {
    let mut collector = GradientCollector {
        grads,
        path: Vec::new(),
        found: BTreeMap::new(),
    };
    module.visit(&mut collector);
    collector.found
}

struct GradientCollector<'a> {
    grads: &'a Gradients,
    path: Vec<String>,
    found: BTreeMap<String, HostTensor>,
}

impl ModuleVisitor for GradientCollector<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(grad) = param.val().grad(self.grads) {
            self.found
                .insert(flax_name(&self.path), HostTensor::from_tensor(grad));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(parts: &[&str]) -> Vec<String> {
        parts.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn module_paths_map_to_flax_names() {
        assert_eq!(
            flax_name(&path(&["pose_enc", "layers", "3", "qkv", "kernel"])),
            "PoseEnc.layers_3.Dense_0.kernel"
        );
        assert_eq!(
            flax_name(&path(&["pose_enc", "pose_head", "dense_2", "bias"])),
            "PoseEnc.PoseHead_0.MLP3_0.Dense_2.bias"
        );
        assert_eq!(
            flax_name(&path(&[
                "render", "layers", "0", "mlp", "dense_1", "kernel"
            ])),
            "Render.layers_0.MLP2_0.Dense_1.kernel"
        );
        assert_eq!(
            flax_name(&path(&["render", "target_lift", "dense_0", "kernel"])),
            "Render.MLP2_1.Dense_0.kernel"
        );
    }
}
