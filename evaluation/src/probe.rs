//! The pose probe: with PoseEnc frozen, a 3-layer MLP learns to read relative SE(3) poses from
//! its latents; its camera metrics on held-out scenes say how much camera geometry the latents
//! carry, independently of the renderer.
//!
//! Training regresses the raw 3x3 rotation entries and the translation (mean squared error on
//! standardised latents); evaluation projects the 3x3 output onto SO(3) with an SVD. Test
//! sequences are those of held-out scenes (every trajectory appears in every scene), so a probe
//! can only score there if the latents describe motion rather than appearance.

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::activation::gelu;
use burn::tensor::{Device, Tensor, TensorData};
use data::rng::Stream;
use data::scenes::CameraPose;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use settings::evaluation::ProbeSpec;

use crate::error::EvalError;
use crate::geometry::{pose, project_to_rotation, relative_to_reference};
use crate::inference::Latent;
use crate::metrics::{CameraMetrics, trajectory_errors};

/// Stream tag of the probe's batch draws.
const PROBE_TAG: u64 = 0x5052_4f42;
/// Outputs: 9 rotation entries and 3 translation components.
const OUTPUTS: usize = 12;

/// The MLP: `Cp -> width -> width -> 12`, GELU between.
#[derive(Module, Debug)]
struct Probe {
    input: Linear,
    hidden: Linear,
    output: Linear,
}

impl Probe {
    fn new(inputs: usize, width: usize, device: &Device) -> Self {
        Self {
            input: LinearConfig::new(inputs, width).init(device),
            hidden: LinearConfig::new(width, width).init(device),
            output: LinearConfig::new(width, OUTPUTS).init(device),
        }
    }

    fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        self.output
            .forward(gelu(self.hidden.forward(gelu(self.input.forward(x)))))
    }
}

/// One sequence's frames for the probe: the latent of every frame relative to frame 0 and the
/// world-to-camera poses.
#[derive(Debug, Clone)]
pub struct ProbeSequence {
    /// Latent of `(frame 0, frame i)` for every frame (frame 0's is zero).
    pub latents: Vec<Latent>,
    /// Ground-truth world-to-camera poses.
    pub poses: Vec<CameraPose>,
}

/// A held-out sequence's true and predicted poses relative to its first frame, for plots.
pub type ProbePath = (Vec<CameraPose>, Vec<CameraPose>);

/// What the probe achieved.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProbeReport {
    /// Training samples (frame pairs of training scenes).
    pub train_samples: usize,
    /// Held-out sequences scored.
    pub test_sequences: usize,
    /// Mean squared error of the last 10% of steps.
    pub final_loss: f64,
    /// Camera metrics over every frame pair of the held-out sequences.
    pub metrics: CameraMetrics,
}

fn target(relative: &CameraPose) -> [f32; OUTPUTS] {
    let r = relative.rotation;
    let t = relative.translation;
    [
        r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2], t[0],
        t[1], t[2],
    ]
    .map(|v| v as f32)
}

/// Per-dimension mean and standard deviation of the training latents.
fn standardiser(samples: &[&Latent]) -> (Vec<f32>, Vec<f32>) {
    let dims = samples.first().map_or(0, |s| s.len());
    let n = samples.len().max(1) as f32;
    let mean: Vec<f32> = (0..dims)
        .map(|d| samples.iter().map(|s| s[d]).sum::<f32>() / n)
        .collect();
    let std = (0..dims)
        .map(|d| {
            let var = samples
                .iter()
                .map(|s| (s[d] - mean[d]).powi(2))
                .sum::<f32>()
                / n;
            var.sqrt().max(1e-6)
        })
        .collect();
    (mean, std)
}

/// Trains a probe on `train` and scores it on `test`, on `device` (which must support
/// autodiff); also returns each test sequence's true and predicted path.
pub fn run_probe(
    train: &[ProbeSequence],
    test: &[ProbeSequence],
    spec: &ProbeSpec,
    seed: u64,
    device: &Device,
) -> Result<(ProbeReport, Vec<ProbePath>), EvalError> {
    let mut inputs: Vec<&Latent> = Vec::new();
    let mut targets: Vec<[f32; OUTPUTS]> = Vec::new();
    for sequence in train {
        let relative = relative_to_reference(&sequence.poses, 0);
        for (latent, pose) in sequence.latents.iter().zip(&relative).skip(1) {
            inputs.push(latent);
            targets.push(target(pose));
        }
    }
    let dims = inputs.first().map(|l| l.len()).ok_or_else(|| {
        EvalError::Invalid(
            "the probe has no training samples (need >= 2 frames and a training scene)".to_string(),
        )
    })?;
    if spec.batch == 0 || spec.width == 0 {
        return Err(EvalError::Invalid(
            "probe batch and width must be positive".to_string(),
        ));
    }
    let (mean, std) = standardiser(&inputs);
    let normalise = |l: &Latent| -> Vec<f32> {
        l.iter()
            .zip(&mean)
            .zip(&std)
            .map(|((v, m), s)| (v - m) / s)
            .collect()
    };
    let normalised: Vec<Vec<f32>> = inputs.iter().map(|l| normalise(l)).collect();

    // burn's initialisers draw from the device's generator: seed it so the probe, like every
    // other draw here, follows from the evaluation seed.
    device.seed(seed ^ PROBE_TAG);
    let mut probe = Probe::new(dims, spec.width, device);
    let mut optimiser = AdamWConfig::new().with_weight_decay(0.0).init();
    let mut stream = Stream::new(&[seed, PROBE_TAG]);
    let mut losses = Vec::with_capacity(spec.steps);
    for _ in 0..spec.steps {
        let picks: Vec<usize> = (0..spec.batch)
            .map(|_| stream.below(normalised.len() as u64) as usize)
            .collect();
        let x: Vec<f32> = picks
            .iter()
            .flat_map(|&i| normalised[i].iter().copied())
            .collect();
        let y: Vec<f32> = picks.iter().flat_map(|&i| targets[i]).collect();
        let x = Tensor::<2>::from_data(TensorData::new(x, [spec.batch, dims]), device);
        let y = Tensor::<2>::from_data(TensorData::new(y, [spec.batch, OUTPUTS]), device);
        let loss = (probe.forward(x) - y).square().mean();
        let grads = GradientsParams::from_grads(loss.backward(), &probe);
        losses.push(f64::from(loss.into_scalar::<f32>()));
        probe = optimiser.step(spec.learning_rate, probe, grads);
    }
    let tail = losses.len().div_ceil(10).max(1);
    let final_loss =
        losses.iter().rev().take(tail).sum::<f64>() / tail.min(losses.len()).max(1) as f64;

    let mut errors = Vec::new();
    let mut paths = Vec::with_capacity(test.len());
    for sequence in test {
        let x: Vec<f32> = sequence.latents.iter().flat_map(normalise).collect();
        let x = Tensor::<2>::from_data(TensorData::new(x, [sequence.latents.len(), dims]), device);
        let out = probe
            .forward(x)
            .try_into_vec_as::<f32>()
            .map_err(|e| EvalError::Tensor(format!("{e:?}")))?;
        let predicted: Vec<CameraPose> = out
            .chunks_exact(OUTPUTS)
            .enumerate()
            .map(|(i, o)| {
                if i == 0 {
                    return CameraPose::identity();
                }
                let o: Vec<f64> = o.iter().map(|&v| f64::from(v)).collect();
                let r = Matrix3::new(o[0], o[1], o[2], o[3], o[4], o[5], o[6], o[7], o[8]);
                pose(&project_to_rotation(&r), &Vector3::new(o[9], o[10], o[11]))
            })
            .collect();
        let reference = relative_to_reference(&sequence.poses, 0);
        errors.extend(trajectory_errors(&reference, &predicted));
        paths.push((reference, predicted));
    }
    Ok((
        ProbeReport {
            train_samples: inputs.len(),
            test_sequences: test.len(),
            final_loss,
            metrics: CameraMetrics::from_errors(&errors),
        },
        paths,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use data::scenes::Trajectory;

    /// Latents that encode the true relative pose exactly: the probe must learn to read them.
    fn sequences(range: std::ops::Range<u64>) -> Vec<ProbeSequence> {
        range
            .map(|index| {
                let poses = Trajectory::random(4, index, 5).poses;
                let latents = relative_to_reference(&poses, 0)
                    .iter()
                    .map(|p| target(p).to_vec())
                    .collect();
                ProbeSequence { latents, poses }
            })
            .collect()
    }

    #[test]
    fn probe_reads_informative_latents() {
        let spec = ProbeSpec {
            steps: 300,
            batch: 32,
            width: 64,
            ..ProbeSpec::default()
        };
        let (report, paths) = run_probe(
            &sequences(0..40),
            &sequences(40..48),
            &spec,
            0,
            &Device::flex().autodiff(),
        )
        .unwrap();
        assert_eq!(report.train_samples, 160);
        assert_eq!(paths.len(), 8);
        assert!(
            report.metrics.at(10).unwrap().rotation_accuracy > 0.8,
            "{report:?}"
        );
    }
}
