//! The project's own weight files: safetensors written by burn-store, with the model
//! configuration as JSON beside them so a checkpoint is always self-describing.

use std::path::{Path, PathBuf};

use burn::store::{ModuleSnapshot, SafetensorsStore};
use burn::tensor::Device;

use crate::model::XFactor;
use settings::model::{ConfigError, XFactorConfig};

/// Why a checkpoint could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// The configuration file could not be read or written.
    #[error("checkpoint config {path}: {source}")]
    Io {
        /// File at fault.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The configuration file is not valid JSON for [`XFactorConfig`].
    #[error("checkpoint config {path} is invalid: {source}")]
    Json {
        /// File at fault.
        path: PathBuf,
        /// Parser error, with line and column.
        source: serde_json::Error,
    },
    /// The configuration describes no buildable model.
    #[error("checkpoint config {path}: {source}")]
    Config {
        /// File at fault.
        path: PathBuf,
        /// The constraint that failed.
        source: ConfigError,
    },
    /// burn-store could not read or write the weights.
    #[error("checkpoint weights {path}: {reason}")]
    Store {
        /// File at fault.
        path: PathBuf,
        /// What the store reported.
        reason: String,
    },
    /// The weights do not fit the configured model.
    #[error("checkpoint weights {path} do not fit the model: {problems:?}")]
    Mismatch {
        /// File at fault.
        path: PathBuf,
        /// Every missing, unused or misshapen tensor, by name and shapes.
        problems: Vec<String>,
    },
}

/// Path of the configuration JSON written beside `weights`.
pub fn config_path(weights: &Path) -> PathBuf {
    weights.with_extension("json")
}

/// Writes `weights` (safetensors) and its configuration beside it.
pub fn save(
    model: &XFactor,
    config: &XFactorConfig,
    weights: &Path,
) -> Result<(), CheckpointError> {
    let config_file = config_path(weights);
    let json = serde_json::to_string_pretty(config).map_err(|source| CheckpointError::Json {
        path: config_file.clone(),
        source,
    })?;
    std::fs::write(&config_file, json).map_err(|source| CheckpointError::Io {
        path: config_file,
        source,
    })?;
    let mut store = SafetensorsStore::from_file(weights).overwrite(true);
    model
        .save_into(&mut store)
        .map_err(|e| CheckpointError::Store {
            path: weights.to_path_buf(),
            reason: e.to_string(),
        })
}

/// Reads the configuration written beside `weights`.
pub fn read_config(weights: &Path) -> Result<XFactorConfig, CheckpointError> {
    let path = config_path(weights);
    let text = std::fs::read_to_string(&path).map_err(|source| CheckpointError::Io {
        path: path.clone(),
        source,
    })?;
    let config: XFactorConfig =
        serde_json::from_str(&text).map_err(|source| CheckpointError::Json {
            path: path.clone(),
            source,
        })?;
    config
        .validate()
        .map_err(|source| CheckpointError::Config { path, source })?;
    Ok(config)
}

/// Rebuilds the model described beside `weights` on `device` and loads its parameters.
pub fn load(weights: &Path, device: &Device) -> Result<(XFactor, XFactorConfig), CheckpointError> {
    let config = read_config(weights)?;
    let mut model = XFactor::new(&config, 0, device).map_err(|source| CheckpointError::Config {
        path: config_path(weights),
        source,
    })?;
    let mut store = SafetensorsStore::from_file(weights).validate(true);
    let result = model
        .load_from(&mut store)
        .map_err(|e| CheckpointError::Store {
            path: weights.to_path_buf(),
            reason: e.to_string(),
        })?;
    let problems: Vec<String> = result
        .errors
        .iter()
        .map(ToString::to_string)
        .chain(
            result
                .missing
                .iter()
                .map(|(name, _)| format!("missing `{name}`")),
        )
        .chain(result.unused.iter().map(|name| format!("unused `{name}`")))
        .collect();
    if !problems.is_empty() {
        return Err(CheckpointError::Mismatch {
            path: weights.to_path_buf(),
            problems,
        });
    }
    Ok((model, config))
}
