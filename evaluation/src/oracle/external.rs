//! The external-command oracle: any program (VGGT on a GPU box, COLMAP behind a script) that
//! takes frame paths as its last arguments and prints the world-to-camera pose of each frame as
//! JSON on stdout: a list of 4x4 or 3x4 row-major matrices, bare or under a `"poses"` key.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicU64, Ordering};

use data::Image;
use data::scenes::CameraPose;
use serde::Deserialize;

use super::{OracleError, PoseOracle};
use crate::figures::save_png;

/// Numbers scratch directories so concurrent estimates never share one.
static SCRATCH: AtomicU64 = AtomicU64::new(0);

/// Runs a user-given program on the frames written as PNG files.
#[derive(Debug, Clone)]
pub struct ExternalOracle {
    program: String,
    args: Vec<String>,
    scratch_root: PathBuf,
}

/// The two stdout layouts accepted.
#[derive(Deserialize)]
#[serde(untagged)]
enum Printed {
    Bare(Vec<Vec<Vec<f64>>>),
    Keyed { poses: Vec<Vec<Vec<f64>>> },
}

impl ExternalOracle {
    /// `program args... frame_000.png frame_001.png ...`; frames are written under the system
    /// temporary directory and removed afterwards.
    pub fn new(program: &str, args: &[String]) -> Self {
        Self {
            program: program.to_string(),
            args: args.to_vec(),
            scratch_root: std::env::temp_dir(),
        }
    }

    fn failure(&self, reason: impl ToString) -> OracleError {
        OracleError::External {
            command: self.program.clone(),
            reason: reason.to_string(),
        }
    }

    fn run(&self, dir: &Path, frames: &[Image]) -> Result<Vec<CameraPose>, OracleError> {
        let mut paths = Vec::with_capacity(frames.len());
        for (index, frame) in frames.iter().enumerate() {
            let path = dir.join(format!("frame_{index:04}.png"));
            save_png(frame, &path).map_err(|e| self.failure(e))?;
            paths.push(path);
        }
        let output = Command::new(&self.program)
            .args(&self.args)
            .args(&paths)
            .output()
            .map_err(|e| self.failure(format!("cannot start: {e}")))?;
        if !output.status.success() {
            return Err(self.failure(format!(
                "exited with {}: {}",
                output.status,
                String::from_utf8_lossy(&output.stderr).trim()
            )));
        }
        let printed: Printed = serde_json::from_slice(&output.stdout)
            .map_err(|e| self.failure(format!("stdout is not a JSON list of matrices: {e}")))?;
        let matrices = match printed {
            Printed::Bare(m) | Printed::Keyed { poses: m } => m,
        };
        if matrices.len() != frames.len() {
            return Err(self.failure(format!(
                "printed {} poses for {} frames",
                matrices.len(),
                frames.len()
            )));
        }
        matrices
            .iter()
            .enumerate()
            .map(|(index, m)| {
                parse_matrix(m)
                    .ok_or_else(|| self.failure(format!("pose {index} is not a 3x4 or 4x4 matrix")))
            })
            .collect()
    }
}

/// A pose from the first three rows of a 3x4 or 4x4 row-major matrix.
fn parse_matrix(rows: &[Vec<f64>]) -> Option<CameraPose> {
    if !(rows.len() == 3 || rows.len() == 4) || rows[..3].iter().any(|r| r.len() != 4) {
        return None;
    }
    Some(CameraPose {
        rotation: std::array::from_fn(|i| std::array::from_fn(|j| rows[i][j])),
        translation: std::array::from_fn(|i| rows[i][3]),
    })
}

impl PoseOracle for ExternalOracle {
    fn name(&self) -> &'static str {
        "external"
    }

    fn estimate(&self, frames: &[Image]) -> Result<Vec<CameraPose>, OracleError> {
        let dir = self.scratch_root.join(format!(
            "xfactor-oracle-{}-{}",
            std::process::id(),
            SCRATCH.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir)
            .map_err(|e| self.failure(format!("scratch {}: {e}", dir.display())))?;
        let result = self.run(&dir, frames);
        if let Err(error) = std::fs::remove_dir_all(&dir) {
            tracing::warn!(dir = %dir.display(), %error, "could not remove the oracle's scratch frames");
        }
        result
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frames(count: usize) -> Vec<Image> {
        vec![
            Image {
                height: 4,
                width: 4,
                pixels: vec![0.0; 48],
            };
            count
        ]
    }

    #[test]
    fn poses_printed_by_a_script_are_read_back() {
        let script = r#"for f in "$@"; do test -s "$f" || exit 3; done
echo '{"poses": [[[1,0,0,0],[0,1,0,0],[0,0,1,0]], [[0,-1,0,0.5],[1,0,0,0],[0,0,1,2],[0,0,0,1]]]}'"#;
        let oracle = ExternalOracle::new("sh", &["-c".into(), script.into(), "oracle".into()]);
        let poses = oracle.estimate(&frames(2)).unwrap();
        assert_eq!(poses[0], CameraPose::identity());
        assert_eq!(
            poses[1].rotation,
            [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
        );
        assert_eq!(poses[1].translation, [0.5, 0.0, 2.0]);
        let error = oracle.estimate(&frames(3)).unwrap_err().to_string();
        assert!(error.contains("printed 2 poses for 3 frames"), "{error}");
        let failing = ExternalOracle::new("sh", &["-c".into(), "echo no >&2; exit 1".into()]);
        assert!(
            failing
                .estimate(&frames(1))
                .unwrap_err()
                .to_string()
                .contains("no")
        );
        let garbage = ExternalOracle::new("sh", &["-c".into(), "echo '[[1,2]]'".into()]);
        assert!(garbage.estimate(&frames(1)).is_err());
    }
}
