//! Importing the authors' released checkpoints: a clu `MultihostCheckpoint` directory whose
//! `checkpoint` file names the latest `ckpt-N`, and `ckpt-N.flax` beside it holding the
//! release's `TrainState` as flax msgpack. No TensorFlow is needed: only the `.flax` file is read.
//!
//! [`read_clu`] recovers the model weights (and the model configuration from their shapes), the
//! AdamW moments and counts of the optax state, and the LPIPS weights that travel with every
//! checkpoint; [`ImportedCheckpoint::write`] writes them as this project's checkpoint directory
//! (what [`crate::trainer::Trainer::resume`] reads) plus `lpips.safetensors` in the layout
//! [`crate::lpips::Lpips`] reads.

pub mod flax_state;
pub mod msgpack;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use burn::tensor::Device;

use self::flax_state::{FlaxState, FlaxStateError};
use crate::checkpoint::{self, CheckpointError};
use crate::flax::{FlaxError, FlaxTensors, HostTensor, PARAMS_PREFIX, load_flax};
use crate::lpips::Lpips;
use crate::model::XFactor;
use crate::trainer::{TensorFileError, TrainerState, write_host_tensors};
use settings::Phase;
use settings::commit::{CommitFile, CommitManifest, MANIFEST_NAME};
use settings::model::{ConfigError, XFactorConfig};

/// Where the release keeps the LPIPS parameters inside its `TrainState`.
const LPIPS_PREFIX: &str = "lpips_params.params.";
/// Where the release keeps the optimiser state.
const OPT_PREFIX: &str = "opt_state.";
/// File names written into the output directory.
pub const MODEL_FILE: &str = "model.safetensors";
/// LPIPS weights in [`Lpips`]'s layout.
pub const LPIPS_FILE: &str = "lpips.safetensors";

/// Why a release checkpoint could not be imported; every variant names the file or entry.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// Neither `DIR/checkpoint` nor `DIR/checkpoints-0/checkpoint` exists.
    #[error(
        "{dir} is not a clu checkpoint directory: no `checkpoint` file in it or in its checkpoints-0/"
    )]
    NotACheckpointDir {
        /// Directory given.
        dir: PathBuf,
    },
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// File at fault.
        path: PathBuf,
        /// Underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The `checkpoint` file names no `model_checkpoint_path`.
    #[error(
        "{path} names no model_checkpoint_path (expected a line `model_checkpoint_path: \"ckpt-N\"`)"
    )]
    NoLatest {
        /// The `checkpoint` file.
        path: PathBuf,
    },
    /// The `.flax` file is not a flax msgpack state.
    #[error("{path}: {source}")]
    State {
        /// The `.flax` file.
        path: PathBuf,
        /// What was wrong in it.
        #[source]
        source: FlaxStateError,
    },
    /// An entry the import needs is absent.
    #[error("{path}: `{name}` is missing ({needed_for})")]
    Missing {
        /// The `.flax` file.
        path: PathBuf,
        /// Dotted name of the entry.
        name: String,
        /// What it was needed for.
        needed_for: &'static str,
    },
    /// An entry has a shape the import cannot use.
    #[error("{path}: `{name}` has shape {found:?}, expected {expected}")]
    Shape {
        /// The `.flax` file.
        path: PathBuf,
        /// Dotted name of the entry.
        name: String,
        /// What was expected.
        expected: String,
        /// What is stored.
        found: Vec<usize>,
    },
    /// The shapes describe no buildable model.
    #[error("{path}: the weights describe an invalid model: {source}")]
    Config {
        /// The `.flax` file.
        path: PathBuf,
        /// The constraint that failed.
        #[source]
        source: ConfigError,
    },
    /// Weights, moments or LPIPS entries do not fit (each missing or misshapen tensor named).
    #[error("{path}: {source}")]
    Tensors {
        /// The `.flax` file.
        path: PathBuf,
        /// Every problem found.
        #[source]
        source: FlaxError,
    },
    /// Writing the model checkpoint failed.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// Writing the optimiser moments or the LPIPS weights failed.
    #[error(transparent)]
    TensorFile(#[from] TensorFileError),
    /// Writing `state.json` or `COMMIT.json` failed.
    #[error("cannot write {path}: {reason}")]
    Write {
        /// File at fault.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// What a release checkpoint holds, in this project's terms.
#[derive(Debug)]
pub struct ImportedCheckpoint {
    /// The `.flax` file that was read.
    pub source: PathBuf,
    /// The model configuration read off the weights' shapes (image size as given).
    pub config: XFactorConfig,
    /// Every model parameter under `params.<flax name>`.
    pub params: FlaxTensors,
    /// AdamW moments as `first.<flax name>` / `second.<flax name>`; empty when the checkpoint
    /// has no optimiser state.
    pub moments: Vec<(String, HostTensor)>,
    /// Adam's update count (its bias-correction step).
    pub updates: u64,
    /// The schedule's step: the learning rate of the next update is the schedule at this step.
    pub step: u64,
    /// LPIPS weights in [`Lpips`]'s names (`vgg.conv1_1.weight`, `lin.lin0`, ...); empty when the
    /// checkpoint carries none.
    pub lpips: Vec<(String, HostTensor)>,
}

/// The `.flax` file that `DIR/checkpoint` (or `DIR/checkpoints-0/checkpoint`) names as latest.
pub fn latest_flax(dir: &Path) -> Result<PathBuf, ImportError> {
    let index = [dir.to_path_buf(), dir.join("checkpoints-0")]
        .into_iter()
        .map(|d| d.join("checkpoint"))
        .find(|p| p.is_file())
        .ok_or_else(|| ImportError::NotACheckpointDir {
            dir: dir.to_path_buf(),
        })?;
    let text = std::fs::read_to_string(&index).map_err(|source| ImportError::Io {
        path: index.clone(),
        source,
    })?;
    let latest = text
        .lines()
        .filter_map(|line| line.trim().strip_prefix("model_checkpoint_path:"))
        .map(|value| value.trim().trim_matches('"'))
        .next_back()
        .filter(|value| !value.is_empty())
        .ok_or_else(|| ImportError::NoLatest {
            path: index.clone(),
        })?;
    // clu may record an absolute path; the file sits beside `checkpoint` either way.
    let name = Path::new(latest)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| latest.to_string());
    let parent = index.parent().unwrap_or(dir);
    Ok(parent.join(format!("{name}.flax")))
}

/// Reads the checkpoint `dir/checkpoint` names; `image_size` is the square input side the
/// model was trained at (the release's is 256), which no weight's shape records.
pub fn read_clu(dir: &Path, image_size: usize) -> Result<ImportedCheckpoint, ImportError> {
    let path = latest_flax(dir)?;
    let bytes = std::fs::read(&path).map_err(|source| ImportError::Io {
        path: path.clone(),
        source,
    })?;
    let state = FlaxState::parse(&bytes).map_err(|source| ImportError::State {
        path: path.clone(),
        source,
    })?;
    let config = infer_config(&state, &path, image_size)?;
    let params: FlaxTensors = state
        .tensors_under(PARAMS_PREFIX)
        .map(|(name, tensor)| (format!("{PARAMS_PREFIX}{name}"), tensor.clone()))
        .collect();
    let param_names: Vec<String> = state
        .tensors_under(PARAMS_PREFIX)
        .map(|(name, _)| name.to_string())
        .collect();
    let OptimizerState {
        moments,
        updates,
        step,
    } = optimizer_state(&state, &path, &param_names)?;
    let lpips = lpips_weights(&state);
    Ok(ImportedCheckpoint {
        source: path,
        config,
        params,
        moments,
        updates,
        step,
        lpips,
    })
}

fn require<'a>(
    state: &'a FlaxState,
    path: &Path,
    name: &str,
    rank: usize,
    needed_for: &'static str,
) -> Result<&'a HostTensor, ImportError> {
    let tensor = state.tensor(name).ok_or_else(|| ImportError::Missing {
        path: path.to_path_buf(),
        name: name.to_string(),
        needed_for,
    })?;
    if tensor.shape.len() != rank {
        return Err(ImportError::Shape {
            path: path.to_path_buf(),
            name: name.to_string(),
            expected: format!("a rank-{rank} array"),
            found: tensor.shape.clone(),
        });
    }
    Ok(tensor)
}

/// The model sizes from the shapes of a few parameters.
fn infer_config(
    state: &FlaxState,
    path: &Path,
    image_size: usize,
) -> Result<XFactorConfig, ImportError> {
    let sizes = "the model's sizes";
    let embed = require(state, path, "params.PoseEnc.Dense_0.kernel", 2, sizes)?;
    let patch_values = embed.shape[0] / 3;
    let patch_size = (patch_values as f64).sqrt().round() as usize;
    if embed.shape[0] % 3 != 0 || patch_size * patch_size != patch_values {
        return Err(ImportError::Shape {
            path: path.to_path_buf(),
            name: "params.PoseEnc.Dense_0.kernel".to_string(),
            expected: "(3 p^2, C) for a patch side p".to_string(),
            found: embed.shape.clone(),
        });
    }
    let width = embed.shape[1];
    let heads = require(
        state,
        path,
        "params.PoseEnc.layers_0.RMSNorm_0.alpha",
        2,
        sizes,
    )?;
    let head = require(
        state,
        path,
        "params.PoseEnc.PoseHead_0.MLP3_0.Dense_2.kernel",
        2,
        sizes,
    )?;
    let global = require(state, path, "params.PoseEnc.global_embed", 2, sizes)?;
    let layers = |network: &str| -> usize {
        let prefix = format!("params.{network}.layers_");
        state
            .leaves
            .keys()
            .filter_map(|name| name.strip_prefix(&prefix)?.split('.').next())
            .collect::<BTreeSet<_>>()
            .len()
    };
    let config = XFactorConfig {
        image_size,
        patch_size,
        width,
        num_heads: heads.shape[0],
        pose_layers: layers("PoseEnc"),
        render_layers: layers("Render"),
        pose_dim: head.shape[1],
        global_tokens: global.shape[0],
        round_qkv_bf16: false,
        pose_conditioning: settings::model::PoseConditioning::Latent,
        precision: settings::model::Precision::F32,
        compute: settings::model::Precision::F32,
    };
    config.validate().map_err(|source| ImportError::Config {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(config)
}

/// What the optax state maps to: our moments, Adam's count, the schedule's count.
struct OptimizerState {
    moments: Vec<(String, HostTensor)>,
    updates: u64,
    step: u64,
}

/// Adam's `mu`/`nu` for every parameter, its count, and the schedule's count. The release's
/// state is `MultiSteps(chain(clip_by_global_norm, adamw))`: the Adam state sits at some
/// `...mu.<param>` / `...nu.<param>` / `...count`, the schedule's count beside it.
fn optimizer_state(
    state: &FlaxState,
    path: &Path,
    param_names: &[String],
) -> Result<OptimizerState, ImportError> {
    let none = OptimizerState {
        moments: Vec::new(),
        updates: 0,
        step: 0,
    };
    let Some(probe) = param_names.first() else {
        return Ok(none);
    };
    let suffix = format!(".mu.{probe}");
    let Some(adam) = state
        .leaves
        .keys()
        .filter(|name| name.starts_with(OPT_PREFIX))
        .find_map(|name| name.strip_suffix(&suffix))
        .map(|prefix| format!("{prefix}."))
    else {
        tracing::warn!(file = %path.display(), "no optimiser state: training restarts AdamW from zero moments");
        return Ok(none);
    };
    let adam_count = format!("{adam}count");
    let updates = optimizer_count(state, path, &adam_count)?;
    let chain = adam
        .trim_end_matches('.')
        .rsplit_once('.')
        .map_or(String::new(), |(parent, _)| format!("{parent}."));
    let schedule_count = state
        .leaves
        .keys()
        .find(|name| name.starts_with(&chain) && name.ends_with(".count") && **name != adam_count)
        .cloned();
    let step = match schedule_count {
        Some(name) => optimizer_count(state, path, &name)?,
        None => updates,
    };
    if state
        .leaves
        .get("opt_state.mini_step")
        .and_then(|leaf| leaf.scalar())
        .is_some_and(|v| v != 0.0)
    {
        tracing::warn!(file = %path.display(), "the checkpoint was saved mid gradient accumulation; the partial sum is dropped");
    }
    let moments = adam_moments(state, path, &adam, param_names)?;
    Ok(OptimizerState {
        moments,
        updates,
        step,
    })
}

/// A count leaf of the optax state (`name`, dotted) as a step number: it must be present and
/// a non-negative scalar, else the error names it.
fn optimizer_count(state: &FlaxState, path: &Path, name: &str) -> Result<u64, ImportError> {
    let leaf = state.leaves.get(name).ok_or_else(|| ImportError::Missing {
        path: path.to_path_buf(),
        name: name.to_string(),
        needed_for: "the optimiser's step count",
    })?;
    leaf.scalar()
        .filter(|v| *v >= 0.0)
        .map(|v| v as u64)
        .ok_or_else(|| ImportError::Shape {
            path: path.to_path_buf(),
            name: name.to_string(),
            expected: "a non-negative scalar".to_string(),
            found: Vec::new(),
        })
}

/// Adam's `<adam>mu.<param>` / `<adam>nu.<param>` for every parameter, renamed
/// `first.<param>` / `second.<param>` in that order; each must have its parameter's shape.
fn adam_moments(
    state: &FlaxState,
    path: &Path,
    adam: &str,
    param_names: &[String],
) -> Result<Vec<(String, HostTensor)>, ImportError> {
    let mut moments = Vec::with_capacity(2 * param_names.len());
    for name in param_names {
        let param_shape = state
            .tensor(&format!("{PARAMS_PREFIX}{name}"))
            .map(|t| t.shape.clone())
            .unwrap_or_default();
        for (ours, theirs) in [("first", "mu"), ("second", "nu")] {
            let entry = format!("{adam}{theirs}.{name}");
            let tensor = state.tensor(&entry).ok_or_else(|| ImportError::Missing {
                path: path.to_path_buf(),
                name: entry.clone(),
                needed_for: "the optimiser's moments",
            })?;
            if tensor.shape != param_shape {
                return Err(ImportError::Shape {
                    path: path.to_path_buf(),
                    name: entry,
                    expected: format!("{param_shape:?}, the parameter's shape"),
                    found: tensor.shape.clone(),
                });
            }
            moments.push((format!("{ours}.{name}"), tensor.clone()));
        }
    }
    Ok(moments)
}

/// The release's LPIPS parameters renamed to [`Lpips`]'s names: `vgg.convB_L.kernel` ->
/// `vgg.convB_L.weight`, `lins_i.layer.kernel` -> `lin.lin{i}`.
fn lpips_weights(state: &FlaxState) -> Vec<(String, HostTensor)> {
    state
        .tensors_under(LPIPS_PREFIX)
        .filter_map(|(name, tensor)| {
            let renamed = if let Some(conv) = name.strip_prefix("vgg.") {
                format!("vgg.{}", conv.replace(".kernel", ".weight"))
            } else {
                let index = name.strip_prefix("lins_")?.strip_suffix(".layer.kernel")?;
                format!("lin.lin{index}")
            };
            Some((renamed, tensor.clone()))
        })
        .collect()
}

impl ImportedCheckpoint {
    /// The model with the imported weights on `device`; every missing or misshapen parameter is
    /// named.
    pub fn model(&self, device: &Device) -> Result<XFactor, ImportError> {
        let tensors = |source| ImportError::Tensors {
            path: self.source.clone(),
            source,
        };
        let fresh =
            XFactor::new(&self.config, 0, device).map_err(|source| ImportError::Config {
                path: self.source.clone(),
                source,
            })?;
        load_flax(fresh, &self.params, PARAMS_PREFIX).map_err(tensors)
    }

    /// Writes `out/model.safetensors` (+ `model.json`), `out/optimizer.safetensors`,
    /// `out/state.json` and, when the checkpoint carries LPIPS weights, `out/lpips.safetensors`
    /// (checked by building the LPIPS network from them first), then `COMMIT.json` listing
    /// them with their CRC-32, so the directory is a committed checkpoint that a job's
    /// `init_weights:` downloads and verifies like any other.
    pub fn write(&self, out: &Path, device: &Device) -> Result<(), ImportError> {
        let model = self.model(device)?;
        if !self.lpips.is_empty() {
            let tensors: FlaxTensors = self.lpips.iter().cloned().collect();
            Lpips::from_tensors(&tensors, device).map_err(|source| ImportError::Tensors {
                path: self.source.clone(),
                source,
            })?;
        }
        std::fs::create_dir_all(out).map_err(|source| ImportError::Io {
            path: out.to_path_buf(),
            source,
        })?;
        checkpoint::save(&model, &self.config, &out.join(MODEL_FILE))?;
        let write = |name: &str, tensors: &[(String, HostTensor)]| {
            write_host_tensors(&out.join(name), tensors)
        };
        write("optimizer.safetensors", &self.moments)?;
        if !self.lpips.is_empty() {
            write(LPIPS_FILE, &self.lpips)?;
        }
        let state = TrainerState {
            step: self.step,
            updates: self.updates,
            seed: 0,
        };
        let path = out.join("state.json");
        let json = serde_json::to_string_pretty(&state).map_err(|e| ImportError::Write {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        std::fs::write(&path, json).map_err(|source| ImportError::Io { path, source })?;
        let config = checkpoint::config_path(&out.join(MODEL_FILE));
        let mut names = vec![MODEL_FILE.to_string(), "optimizer.safetensors".to_string()];
        names.extend(config.file_name().map(|n| n.to_string_lossy().into_owned()));
        names.push("state.json".to_string());
        if !self.lpips.is_empty() {
            names.push(LPIPS_FILE.to_string());
        }
        write_commit_manifest(out, &names, self.step)
    }
}

/// Writes `dir/COMMIT.json` for the files `names` of `dir` (sizes and CRC-32), as a stage-1
/// commit at `step`.
fn write_commit_manifest(dir: &Path, names: &[String], step: u64) -> Result<(), ImportError> {
    let mut files = Vec::with_capacity(names.len());
    for name in names {
        let path = dir.join(name);
        let bytes = std::fs::read(&path).map_err(|source| ImportError::Io { path, source })?;
        files.push(CommitFile {
            name: name.clone(),
            bytes: bytes.len() as u64,
            crc32: Some(crc32fast::hash(&bytes)),
        });
    }
    let manifest = CommitManifest {
        phase: Phase::Stage1,
        step,
        files,
    };
    let path = dir.join(MANIFEST_NAME);
    let json = serde_json::to_vec_pretty(&manifest).map_err(|e| ImportError::Write {
        path: path.clone(),
        reason: e.to_string(),
    })?;
    std::fs::write(&path, json).map_err(|source| ImportError::Io { path, source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_checkpoint_file_names_the_latest_flax_file() {
        let dir = tempfile::tempdir().unwrap();
        let inner = dir.path().join("checkpoints-0");
        std::fs::create_dir_all(&inner).unwrap();
        assert!(matches!(
            latest_flax(dir.path()),
            Err(ImportError::NotACheckpointDir { .. })
        ));
        std::fs::write(
            inner.join("checkpoint"),
            "model_checkpoint_path: \"/abs/run/ckpt-7\"\nall_model_checkpoint_paths: \"ckpt-6\"\n",
        )
        .unwrap();
        assert_eq!(latest_flax(dir.path()).unwrap(), inner.join("ckpt-7.flax"));
        std::fs::write(
            inner.join("checkpoint"),
            "all_model_checkpoint_paths: \"ckpt-6\"\n",
        )
        .unwrap();
        let error = latest_flax(&inner).unwrap_err();
        assert!(
            error.to_string().contains("model_checkpoint_path"),
            "{error}"
        );
    }
}
