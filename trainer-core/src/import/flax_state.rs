//! A flax state as `flax.serialization.to_bytes` writes it, flattened to dotted names
//! (`params.PoseEnc.layers_0.Dense_0.kernel`). Arrays are msgpack extension 1 holding
//! `(shape, dtype name, raw little-endian bytes)`; numpy scalars are extension 3 holding
//! `(dtype name, bytes)`.

use std::collections::BTreeMap;

use super::msgpack::{MsgpackError, Value, decode};
use crate::flax::HostTensor;

/// flax's extension code for an n-dimensional array.
const EXT_NDARRAY: i8 = 1;
/// flax's extension code for a numpy scalar.
const EXT_NPSCALAR: i8 = 3;
/// The key flax uses for arrays too large for one msgpack value.
const CHUNKED_ARRAY: &str = "__msgpack_chunked_array__";

/// Why a flax state could not be read.
#[derive(Debug, thiserror::Error)]
pub enum FlaxStateError {
    /// The bytes are not MessagePack.
    #[error(transparent)]
    Msgpack(#[from] MsgpackError),
    /// An array's extension payload is not `(shape, dtype, bytes)`.
    #[error("`{name}`: malformed array ({reason})")]
    Array {
        /// Dotted name of the entry.
        name: String,
        /// What did not fit.
        reason: String,
    },
    /// A dtype the importer does not convert.
    #[error("`{name}` has dtype {dtype}, which cannot be converted to float32")]
    Dtype {
        /// Dotted name of the entry.
        name: String,
        /// The stored dtype name.
        dtype: String,
    },
    /// The top level is not a map.
    #[error("the state is not a map of named entries")]
    NotAMap,
}

/// One leaf of the state.
#[derive(Debug, Clone, PartialEq)]
pub enum Leaf {
    /// An array (also a 0-d one) converted to float32, with its stored dtype name.
    Array {
        /// Stored dtype (`float32`, `int32`, ...).
        dtype: String,
        /// Values as float32 (integers up to 2^24 convert exactly).
        tensor: HostTensor,
    },
    /// A plain msgpack integer.
    Int(i64),
    /// Anything else (strings, floats, booleans, empty maps): kept only as a name.
    Other,
}

impl Leaf {
    /// The value of a scalar leaf (a 0-d or one-element array, or an integer).
    pub fn scalar(&self) -> Option<f64> {
        match self {
            Self::Int(v) => Some(*v as f64),
            Self::Array { tensor, .. } if tensor.values.len() == 1 => {
                Some(f64::from(tensor.values[0]))
            }
            _ => None,
        }
    }
}

/// Every leaf of a flax state by dotted name.
#[derive(Debug, Default)]
pub struct FlaxState {
    /// Leaves in name order.
    pub leaves: BTreeMap<String, Leaf>,
}

impl FlaxState {
    /// Decodes `bytes` written by `flax.serialization.to_bytes`.
    pub fn parse(bytes: &[u8]) -> Result<Self, FlaxStateError> {
        let root = decode(bytes)?;
        if !matches!(root, Value::Map(_)) {
            return Err(FlaxStateError::NotAMap);
        }
        let mut state = Self::default();
        state.flatten(String::new(), &root)?;
        Ok(state)
    }

    /// The array stored under `name`.
    pub fn tensor(&self, name: &str) -> Option<&HostTensor> {
        match self.leaves.get(name) {
            Some(Leaf::Array { tensor, .. }) => Some(tensor),
            _ => None,
        }
    }

    /// Arrays whose name starts with `prefix`, with the prefix removed.
    pub fn tensors_under<'a>(
        &'a self,
        prefix: &'a str,
    ) -> impl Iterator<Item = (&'a str, &'a HostTensor)> + 'a {
        self.leaves.iter().filter_map(move |(name, leaf)| {
            let rest = name.strip_prefix(prefix)?;
            match leaf {
                Leaf::Array { tensor, .. } => Some((rest, tensor)),
                _ => None,
            }
        })
    }

    fn flatten(&mut self, name: String, value: &Value<'_>) -> Result<(), FlaxStateError> {
        match value {
            Value::Map(entries) => {
                for (key, child) in entries {
                    let key = match key {
                        Value::Str(s) => (*s).to_string(),
                        Value::Int(i) => i.to_string(),
                        other => format!("{other:?}"),
                    };
                    if key == CHUNKED_ARRAY {
                        return Err(FlaxStateError::Array {
                            name,
                            reason:
                                "stored in chunks (over 1 GiB), which this importer does not read"
                                    .to_string(),
                        });
                    }
                    let child_name = if name.is_empty() {
                        key
                    } else {
                        format!("{name}.{key}")
                    };
                    self.flatten(child_name, child)?;
                }
            }
            Value::Ext(EXT_NDARRAY, payload) => {
                let leaf = ndarray(&name, payload)?;
                self.leaves.insert(name, leaf);
            }
            Value::Ext(EXT_NPSCALAR, payload) => {
                let leaf = npscalar(&name, payload)?;
                self.leaves.insert(name, leaf);
            }
            Value::Int(v) => {
                self.leaves.insert(name, Leaf::Int(*v));
            }
            _ => {
                self.leaves.insert(name, Leaf::Other);
            }
        }
        Ok(())
    }
}

fn malformed(name: &str, reason: impl Into<String>) -> FlaxStateError {
    FlaxStateError::Array {
        name: name.to_string(),
        reason: reason.into(),
    }
}

fn ndarray(name: &str, payload: &[u8]) -> Result<Leaf, FlaxStateError> {
    let Value::Array(parts) = decode(payload)? else {
        return Err(malformed(name, "payload is not a list"));
    };
    let [Value::Array(dims), Value::Str(dtype), Value::Bin(data)] = parts.as_slice() else {
        return Err(malformed(name, "payload is not (shape, dtype, bytes)"));
    };
    let shape = dims
        .iter()
        .map(|d| match d {
            Value::Int(n) if *n >= 0 => Ok(*n as usize),
            other => Err(malformed(name, format!("dimension {other:?}"))),
        })
        .collect::<Result<Vec<usize>, _>>()?;
    let values = to_f32(name, dtype, data)?;
    if values.len() != shape.iter().product::<usize>() {
        return Err(malformed(
            name,
            format!("{} values for shape {shape:?}", values.len()),
        ));
    }
    Ok(Leaf::Array {
        dtype: (*dtype).to_string(),
        tensor: HostTensor { shape, values },
    })
}

fn npscalar(name: &str, payload: &[u8]) -> Result<Leaf, FlaxStateError> {
    let Value::Array(parts) = decode(payload)? else {
        return Err(malformed(name, "scalar payload is not a list"));
    };
    let [Value::Str(dtype), Value::Bin(data)] = parts.as_slice() else {
        return Err(malformed(name, "scalar payload is not (dtype, bytes)"));
    };
    let values = to_f32(name, dtype, data)?;
    Ok(Leaf::Array {
        dtype: (*dtype).to_string(),
        tensor: HostTensor {
            shape: Vec::new(),
            values,
        },
    })
}

fn to_f32(name: &str, dtype: &str, data: &[u8]) -> Result<Vec<f32>, FlaxStateError> {
    fn words<const N: usize>(data: &[u8]) -> impl Iterator<Item = [u8; N]> + '_ {
        data.chunks_exact(N).map(|c| {
            let mut word = [0u8; N];
            word.copy_from_slice(c);
            word
        })
    }
    let width = match dtype {
        "float32" | "int32" | "uint32" => 4,
        "float64" | "int64" | "uint64" => 8,
        "bfloat16" | "float16" | "int16" | "uint16" => 2,
        "int8" | "uint8" | "bool" => 1,
        _ => 0,
    };
    if width == 0 {
        return Err(FlaxStateError::Dtype {
            name: name.to_string(),
            dtype: dtype.to_string(),
        });
    }
    if !data.len().is_multiple_of(width) {
        return Err(malformed(
            name,
            format!("{} bytes are not whole {dtype} values", data.len()),
        ));
    }
    Ok(match dtype {
        "float32" => words::<4>(data).map(f32::from_le_bytes).collect(),
        "int32" => words::<4>(data)
            .map(|w| i32::from_le_bytes(w) as f32)
            .collect(),
        "uint32" => words::<4>(data)
            .map(|w| u32::from_le_bytes(w) as f32)
            .collect(),
        "float64" => words::<8>(data)
            .map(|w| f64::from_le_bytes(w) as f32)
            .collect(),
        "int64" => words::<8>(data)
            .map(|w| i64::from_le_bytes(w) as f32)
            .collect(),
        "uint64" => words::<8>(data)
            .map(|w| u64::from_le_bytes(w) as f32)
            .collect(),
        "bfloat16" => words::<2>(data)
            .map(|w| f32::from_bits(u32::from(u16::from_le_bytes(w)) << 16))
            .collect(),
        "float16" => words::<2>(data)
            .map(|w| half_to_f32(u16::from_le_bytes(w)))
            .collect(),
        "int16" => words::<2>(data)
            .map(|w| f32::from(i16::from_le_bytes(w)))
            .collect(),
        "uint16" => words::<2>(data)
            .map(|w| f32::from(u16::from_le_bytes(w)))
            .collect(),
        "int8" => data.iter().map(|&b| f32::from(b as i8)).collect(),
        _ => data.iter().map(|&b| f32::from(b)).collect(),
    })
}

/// IEEE half precision to single (exact: every half value is a float32).
fn half_to_f32(bits: u16) -> f32 {
    let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = i32::from((bits >> 10) & 0x1f);
    let mantissa = f32::from(bits & 0x3ff);
    sign * match exponent {
        0 => mantissa * 2f32.powi(-24),
        31 if mantissa == 0.0 => f32::INFINITY,
        31 => f32::NAN,
        _ => (1.0 + mantissa / 1024.0) * 2f32.powi(exponent - 15),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// msgpack of `{"w": ext1((2,), "float32", bytes)}` built by hand.
    fn state_bytes(dtype: &str, data: &[u8]) -> Vec<u8> {
        let mut payload = vec![0x93, 0x91, 0x02, 0xa0 | dtype.len() as u8];
        payload.extend_from_slice(dtype.as_bytes());
        payload.extend_from_slice(&[0xc4, data.len() as u8]);
        payload.extend_from_slice(data);
        let mut bytes = vec![0x81, 0xa1, b'w', 0xc7, payload.len() as u8, 0x01];
        bytes.extend(payload);
        bytes
    }

    #[test]
    fn arrays_convert_and_wrong_sizes_name_the_entry() {
        let data: Vec<u8> = [1.5f32, -2.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let state = FlaxState::parse(&state_bytes("float32", &data)).unwrap();
        assert_eq!(state.tensor("w").unwrap().values, vec![1.5, -2.0]);
        let error = FlaxState::parse(&state_bytes("float32", &data[..4])).unwrap_err();
        assert!(error.to_string().contains("`w`"), "{error}");
        let error = FlaxState::parse(&state_bytes("complex64", &data)).unwrap_err();
        assert!(matches!(error, FlaxStateError::Dtype { .. }), "{error}");
        assert_eq!(half_to_f32(0x3c00), 1.0);
        assert_eq!(half_to_f32(0xc000), -2.0);
    }
}
