//! What the evaluation stage measures, small enough to travel in a job assignment: generated
//! scenes, TPS, the pose probe, and which pose oracle scores transfers.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::data::DatasetKind;

/// What to evaluate: small enough to travel as JSON in a job assignment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EvaluationSpec {
    /// Seed of the generated scenes, trajectories, TPS pairs and probe batches.
    pub seed: u64,
    /// Generated scenes (the last `probe.test_scenes` are held out from probe training).
    pub scenes: u64,
    /// Camera trajectories, each rendered in every scene.
    pub trajectories: u64,
    /// Frames per trajectory.
    pub frames: usize,
    /// Transfers scored by TPS.
    pub tps_pairs: usize,
    /// Equally spaced target frames per transfer (the paper: 5).
    pub tps_frames: usize,
    /// Sequences autoencoded for PSNR / SSIM / LPIPS.
    pub reconstruction_sequences: usize,
    /// The pose probe.
    pub probe: ProbeSpec,
    /// The pose oracle of TPS.
    pub oracle: OracleSpec,
    /// LPIPS weights (safetensors, `tools/convert_lpips_weights.py`); LPIPS is skipped without.
    pub lpips_weights: Option<PathBuf>,
    /// Also evaluate an untrained model of the same configuration, as the baseline.
    pub compare_untrained: bool,
    /// Real test sequences reconstructed under E-RayZer's protocol, one entry per dataset.
    pub sequences: Vec<SequenceProtocol>,
    /// What the evaluated training departs from the release in (a smaller model, a stage 2
    /// that keeps stage 1's Render, ...), in words: the report lists them beside the
    /// evaluation's own departures, so its figures are never read as the release's.
    pub notes: Vec<String>,
}

/// E-RayZer's evaluation protocol on one dataset's test split: every evaluated sequence has the
/// same length, its frames equally spaced over the video with the first and last always among
/// them; the first frame is the context and the model reconstructs the others.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SequenceProtocol {
    /// The dataset's layout.
    pub kind: DatasetKind,
    /// Its root: a path or an object-store URI.
    pub uri: String,
    /// Frames per evaluated sequence (E-RayZer fixes one per dataset); shorter sequences are
    /// skipped and counted.
    pub length: usize,
    /// Test sequences evaluated: the first ones of the test split, in manifest order, that are
    /// long enough.
    pub count: usize,
}

/// A limit of [`EvaluationSpec`] that a spec breaks, naming the key as a YAML reader writes it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EvaluationSpecError {
    /// A top-level or `probe.` key is out of its range.
    #[error("{key}: expected {expected}")]
    OutOfRange {
        /// The key, `probe.`-prefixed for the probe's.
        key: &'static str,
        /// The range it must lie in, and why.
        expected: &'static str,
    },
    /// A sequence protocol asks for fewer than two frames per sequence.
    #[error("sequences[{index}].length: expected at least 2 (a context frame and a target)")]
    SequenceTooShort {
        /// Position of the protocol in `sequences`.
        index: usize,
    },
    /// A sequence protocol asks for no sequences.
    #[error("sequences[{index}].count: expected at least 1")]
    NoSequences {
        /// Position of the protocol in `sequences`.
        index: usize,
    },
}

impl EvaluationSpec {
    /// Checks the limits the evaluation relies on, naming the key, so a cluster YAML is refused
    /// when it is read rather than after training.
    pub fn validate(&self) -> Result<(), EvaluationSpecError> {
        let checks = [
            (
                self.scenes < 2,
                "scenes",
                "at least 2 (TPS renders one scene along another's motion)",
            ),
            (
                self.trajectories < 2,
                "trajectories",
                "at least 2 (TPS compares against an unrelated one)",
            ),
            (self.frames < 2, "frames", "at least 2"),
            (self.tps_frames < 2, "tps_frames", "at least 2"),
            (self.tps_pairs == 0, "tps_pairs", "at least 1"),
            (self.probe.steps == 0, "probe.steps", "at least 1"),
            (self.probe.batch == 0, "probe.batch", "at least 1"),
            (self.probe.width == 0, "probe.width", "at least 1"),
            (
                matches!(self.oracle, OracleSpec::GroundTruth { subdivisions }
                    if subdivisions == 0 || subdivisions > MAX_ORACLE_SUBDIVISIONS),
                "oracle.subdivisions",
                "1 to 16",
            ),
            (
                self.probe.test_scenes == 0 || self.probe.test_scenes >= self.scenes,
                "probe.test_scenes",
                "at least 1 and fewer than `scenes` (the rest train the probe)",
            ),
        ];
        if let Some(&(_, key, expected)) = checks.iter().find(|(bad, _, _)| *bad) {
            return Err(EvaluationSpecError::OutOfRange { key, expected });
        }
        for (index, protocol) in self.sequences.iter().enumerate() {
            if protocol.length < 2 {
                return Err(EvaluationSpecError::SequenceTooShort { index });
            }
            if protocol.count == 0 {
                return Err(EvaluationSpecError::NoSequences { index });
            }
        }
        Ok(())
    }
}

impl Default for EvaluationSpec {
    /// 6 scenes x 8 trajectories x 8 frames, 32 TPS pairs of 5 frames, 8 reconstructed
    /// sequences, the default probe, the ground-truth oracle, an untrained baseline.
    fn default() -> Self {
        Self {
            seed: 0,
            scenes: 6,
            trajectories: 8,
            frames: 8,
            tps_pairs: 32,
            tps_frames: 5,
            reconstruction_sequences: 8,
            probe: ProbeSpec::default(),
            oracle: OracleSpec::default(),
            lpips_weights: None,
            compare_untrained: true,
            sequences: Vec::new(),
            notes: Vec::new(),
        }
    }
}

/// How the probe is trained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProbeSpec {
    /// Optimiser steps (the paper: 10k).
    pub steps: usize,
    /// Samples per step (the paper: 64).
    pub batch: usize,
    /// `features` of the probe's MLP3 (hidden layers `4 * features` and `features`; the
    /// paper's appendix: 256, the release's code: 64).
    pub width: usize,
    /// AdamW learning rate.
    pub learning_rate: f64,
    /// Scenes held out for testing (the last ones).
    pub test_scenes: u64,
    /// What one training sample is, and so how translation scale is treated.
    pub loss: ProbeLoss,
    /// Not the release's: the probe's 3x3 output is read as an offset from the identity
    /// (`I + M` is projected onto SO(3)), so an untrained probe starts at "no rotation"
    /// instead of at a random rotation. On small generated scenes, whose cameras barely rotate,
    /// the release's start sometimes settles 180 degrees away; the local demo job sets it.
    pub rotation_from_identity: bool,
}

/// The release's two probe losses (`nn/losses.py`): both are `mean |R - R_gt| +
/// mean |t - t_gt|`; they differ in what a sample is and whether translation scale counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProbeLoss {
    /// `camera_loss`: a sample is one frame pair `(frame 0, frame i)`, translations compared
    /// as they are.
    #[default]
    Pairs,
    /// `camera_seq_loss`: a sample is a whole sequence's pairs, whose predicted translations
    /// are first scaled onto the ground truth by `<t_gt, t> / <t, t>` (one factor per
    /// sequence, gradients flowing through it), so only the trajectory's shape counts.
    Trajectories,
}

impl ProbeSpec {
    /// The probe's budget and protocol in words, printed beside its figures: `MLP3 of width
    /// 64, 1000 steps of 64, loss pairs`, and `rotation from identity` when set.
    pub fn budget(&self) -> String {
        let loss = match self.loss {
            ProbeLoss::Pairs => "pairs (frame pairs, translations as they are)",
            ProbeLoss::Trajectories => "trajectories (whole sequences, translation scale-free)",
        };
        let start = if self.rotation_from_identity {
            ", rotation from identity"
        } else {
            ""
        };
        format!(
            "MLP3 of width {}, {} steps of {}, loss {loss}{start}",
            self.width, self.steps, self.batch
        )
    }
}

impl Default for ProbeSpec {
    /// The paper's probe (its appendix: "a three-layer MLP with a feature dimension of 256
    /// ... trained for 10,000 iterations with a batch size of 64"), learning rate `1e-3`, two
    /// held-out scenes: what a report meant to be read against the paper runs.
    fn default() -> Self {
        Self {
            steps: 10_000,
            batch: 64,
            width: 256,
            learning_rate: 1e-3,
            test_scenes: 2,
            loss: ProbeLoss::Pairs,
            rotation_from_identity: false,
        }
    }
}

/// Which oracle an evaluation uses, in serialisable form so it can travel in a job spec.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum OracleSpec {
    /// Render-and-compare against the generated frames of known pose.
    GroundTruth {
        /// Candidate views per gap between consecutive generated frames: 1 compares with the
        /// generated frames alone, so a render between two frames snaps to one of them; `k`
        /// also renders every path at `k - 1` poses in between, so such a render reads the
        /// motion it has to a `k`-th of a frame.
        #[serde(default = "one_subdivision")]
        subdivisions: u32,
    },
    /// Feature matching and essential matrices at the generated scenes' field of view.
    Classical,
    /// Any program that reads frame paths and prints poses as JSON.
    External {
        /// Program to run.
        program: String,
        /// Arguments placed before the frame paths.
        #[serde(default)]
        args: Vec<String>,
    },
}

impl Default for OracleSpec {
    /// The ground-truth oracle on the generated frames alone.
    fn default() -> Self {
        Self::GroundTruth {
            subdivisions: one_subdivision(),
        }
    }
}

/// The ground-truth oracle's default: the generated frames alone.
fn one_subdivision() -> u32 {
    1
}

/// The most candidate views per gap an evaluation may ask for (the candidates are rendered and
/// searched for every render scored).
pub const MAX_ORACLE_SUBDIVISIONS: u32 = 16;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn oracle_subdivisions_out_of_range_are_refused_by_key() {
        for (subdivisions, valid) in [(0, false), (1, true), (16, true), (17, false)] {
            let spec = EvaluationSpec {
                oracle: OracleSpec::GroundTruth { subdivisions },
                ..EvaluationSpec::default()
            };
            match spec.validate() {
                Ok(()) => assert!(valid, "{subdivisions} accepted"),
                Err(error) => {
                    assert!(!valid, "{subdivisions} refused: {error}");
                    assert!(error.to_string().contains("oracle.subdivisions"), "{error}");
                }
            }
        }
        let old: OracleSpec = serde_json::from_str(r#"{"kind": "ground_truth"}"#).unwrap();
        assert_eq!(old, OracleSpec::default());
    }

    #[test]
    fn the_probe_budget_names_width_steps_batch_and_protocol() {
        let paper = ProbeSpec {
            width: 256,
            ..ProbeSpec::default()
        };
        assert_eq!(
            paper.budget(),
            "MLP3 of width 256, 10000 steps of 64, loss pairs (frame pairs, translations as they are)"
        );
        let demo = ProbeSpec {
            steps: 1000,
            width: 64,
            loss: ProbeLoss::Trajectories,
            rotation_from_identity: true,
            ..ProbeSpec::default()
        };
        assert_eq!(
            demo.budget(),
            "MLP3 of width 64, 1000 steps of 64, loss trajectories (whole sequences, translation scale-free), rotation from identity"
        );
    }
}
