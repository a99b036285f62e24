//! The typed messages of the contract to and from the `settings` types both sides compute with.
//!
//! Writing is total; reading fails with the field at fault when a required sub-message is
//! absent or an enum holds a value this build does not know (a peer of another version).

use settings::Phase;
use settings::data::{
    DataSource, DataSpec, DatasetKind, DatasetSampling, ListingFingerprint, SamplerConfig,
    StoredDataset,
};
use settings::evaluation::{EvaluationSpec, OracleSpec, ProbeLoss, ProbeSpec, SequenceProtocol};
use settings::objective::{AugmentConfig, ObjectiveVariant, Stage1Config, Stage2Config};
use settings::optim::{AdamWConfig, Schedule};
use settings::train::{StageObjective, TrainConfig};

use crate::v1;

mod device;
mod model;
mod progress;
mod work;

pub use device::{
    device_from_wire, device_in_use_from_wire, device_in_use_to_wire, device_to_wire,
    reported_device, worker_line,
};
pub use progress::activity_from_wire;
pub use work::{devices_from_wire, devices_to_wire};

/// A message that cannot become its settings type.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConvertError {
    /// A required sub-message or oneof is absent.
    #[error("`{0}` is missing from the message")]
    Missing(&'static str),
    /// An enum field holds a value this build does not know.
    #[error("`{field}` holds {value}, which this build does not know (a peer of another version?)")]
    Unknown {
        /// The field.
        field: &'static str,
        /// The raw value.
        value: i32,
    },
    /// A field holds a value the message's meaning rules out (a rank outside the ring, an
    /// interval of 0, two starting points at once).
    #[error("`{field}` is malformed: {reason}")]
    Malformed {
        /// The field.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
}

fn required<T>(value: Option<T>, field: &'static str) -> Result<T, ConvertError> {
    value.ok_or(ConvertError::Missing(field))
}

/// The longest interval or timeout a message may carry: 30 days, the cluster YAML's bound.
pub const MAX_WIRE_SECONDS: f64 = 30.0 * 24.0 * 3600.0;

/// A duration the wire carries as seconds, checked before it becomes a `Duration` (whose
/// constructor panics on infinity, NaN or a negative number): finite, at least `least`, at
/// most [`MAX_WIRE_SECONDS`].
pub fn seconds_from_wire(
    seconds: f64,
    least: f64,
    field: &'static str,
) -> Result<std::time::Duration, ConvertError> {
    let malformed = |reason: String| ConvertError::Malformed { field, reason };
    if !(least..=MAX_WIRE_SECONDS).contains(&seconds) {
        return Err(malformed(format!(
            "{seconds} seconds is not within [{least}, {MAX_WIRE_SECONDS}]"
        )));
    }
    std::time::Duration::try_from_secs_f64(seconds).map_err(|error| malformed(error.to_string()))
}

/// Sizes travel as `u64`; this side's `usize` is at least that wide on every supported host.
fn size(value: u64) -> usize {
    value as usize
}

/// The wire form of a phase.
pub fn phase_to_wire(phase: Phase) -> v1::Phase {
    match phase {
        Phase::Stage1 => v1::Phase::Stage1,
        Phase::Stage2 => v1::Phase::Stage2,
        Phase::Evaluate => v1::Phase::Evaluate,
        Phase::Finished => v1::Phase::Finished,
    }
}

/// A phase from its wire value; `field` names it in the error.
pub fn phase_from_wire(value: i32, field: &'static str) -> Result<Phase, ConvertError> {
    match v1::Phase::try_from(value) {
        Ok(v1::Phase::Stage1) => Ok(Phase::Stage1),
        Ok(v1::Phase::Stage2) => Ok(Phase::Stage2),
        Ok(v1::Phase::Evaluate) => Ok(Phase::Evaluate),
        Ok(v1::Phase::Finished) => Ok(Phase::Finished),
        Ok(v1::Phase::Unspecified) | Err(_) => Err(ConvertError::Unknown { field, value }),
    }
}

/// What a job is doing, for status lines: its phase, whether its group is still forming, and
/// how long it has been waiting for the object store.
pub fn status_label(status: &v1::JobStatus) -> String {
    let label = phase_label(status);
    match status.store_failing_s {
        Some(seconds) if seconds.is_finite() && seconds >= 0.0 => {
            format!("{label}, waiting for the store since {seconds:.0} s ago")
        }
        _ => label,
    }
}

/// The phase part of [`status_label`].
fn phase_label(status: &v1::JobStatus) -> String {
    let phase = phase_from_wire(status.phase, "status.phase");
    match phase {
        Ok(Phase::Finished) => "finished".into(),
        Ok(phase) if status.group_running => phase.name().into(),
        Ok(Phase::Evaluate) => "evaluate (waiting for a worker)".into(),
        Ok(phase) => format!("{phase} (waiting for workers)"),
        Err(_) => format!("unknown phase {}", status.phase),
    }
}

fn kind_to_wire(kind: DatasetKind) -> i32 {
    (match kind {
        DatasetKind::Re10k => v1::DatasetKind::Re10k,
        DatasetKind::Dl3dv => v1::DatasetKind::Dl3dv,
        DatasetKind::Mvimgnet => v1::DatasetKind::Mvimgnet,
        DatasetKind::Co3dv2 => v1::DatasetKind::Co3dv2,
        DatasetKind::Arkitscenes => v1::DatasetKind::Arkitscenes,
        DatasetKind::Wildrgbd => v1::DatasetKind::Wildrgbd,
        DatasetKind::Acid => v1::DatasetKind::Acid,
    }) as i32
}

fn kind_from_wire(value: i32, field: &'static str) -> Result<DatasetKind, ConvertError> {
    match v1::DatasetKind::try_from(value) {
        Ok(v1::DatasetKind::Re10k) => Ok(DatasetKind::Re10k),
        Ok(v1::DatasetKind::Dl3dv) => Ok(DatasetKind::Dl3dv),
        Ok(v1::DatasetKind::Mvimgnet) => Ok(DatasetKind::Mvimgnet),
        Ok(v1::DatasetKind::Co3dv2) => Ok(DatasetKind::Co3dv2),
        Ok(v1::DatasetKind::Arkitscenes) => Ok(DatasetKind::Arkitscenes),
        Ok(v1::DatasetKind::Wildrgbd) => Ok(DatasetKind::Wildrgbd),
        Ok(v1::DatasetKind::Acid) => Ok(DatasetKind::Acid),
        Ok(v1::DatasetKind::Unspecified) | Err(_) => Err(ConvertError::Unknown { field, value }),
    }
}

fn augment_to_wire(a: &AugmentConfig) -> v1::AugmentSettings {
    v1::AugmentSettings {
        jitter_probability: a.jitter_probability,
        brightness: a.brightness,
        contrast: a.contrast,
        saturation: a.saturation,
        hue: a.hue,
        blur_probability: a.blur_probability,
        blur_sigma_min: a.blur_sigma_min,
        blur_sigma_max: a.blur_sigma_max,
        blur_kernel: a.blur_kernel as u64,
    }
}

fn augment_from_wire(a: &v1::AugmentSettings) -> AugmentConfig {
    AugmentConfig {
        jitter_probability: a.jitter_probability,
        brightness: a.brightness,
        contrast: a.contrast,
        saturation: a.saturation,
        hue: a.hue,
        blur_probability: a.blur_probability,
        blur_sigma_min: a.blur_sigma_min,
        blur_sigma_max: a.blur_sigma_max,
        blur_kernel: size(a.blur_kernel),
    }
}

fn common_to_wire(
    self_decode_probability: f64,
    unmasked_probability: f64,
    lpips_weight: f64,
    augment: &AugmentConfig,
    variant: ObjectiveVariant,
) -> Option<v1::ObjectiveSettings> {
    Some(v1::ObjectiveSettings {
        self_decode_probability,
        unmasked_probability,
        lpips_weight,
        augment: Some(augment_to_wire(augment)),
        variant: match variant {
            ObjectiveVariant::Transfer => v1::ObjectiveVariant::Transfer,
            ObjectiveVariant::Autoencode => v1::ObjectiveVariant::Autoencode,
            ObjectiveVariant::Se3Plucker => v1::ObjectiveVariant::Se3Plucker,
            ObjectiveVariant::ExtraViewDecoder => v1::ObjectiveVariant::ExtraViewDecoder,
            ObjectiveVariant::ExtraViewEncoderDecoder => {
                v1::ObjectiveVariant::ExtraViewEncoderDecoder
            }
        } as i32,
    })
}

fn variant_from_wire(value: i32) -> Result<ObjectiveVariant, ConvertError> {
    match v1::ObjectiveVariant::try_from(value) {
        Ok(v1::ObjectiveVariant::Transfer) => Ok(ObjectiveVariant::Transfer),
        Ok(v1::ObjectiveVariant::Autoencode) => Ok(ObjectiveVariant::Autoencode),
        Ok(v1::ObjectiveVariant::Se3Plucker) => Ok(ObjectiveVariant::Se3Plucker),
        Ok(v1::ObjectiveVariant::ExtraViewDecoder) => Ok(ObjectiveVariant::ExtraViewDecoder),
        Ok(v1::ObjectiveVariant::ExtraViewEncoderDecoder) => {
            Ok(ObjectiveVariant::ExtraViewEncoderDecoder)
        }
        Err(_) => Err(ConvertError::Unknown {
            field: "train.objective.common.variant",
            value,
        }),
    }
}

fn objective_to_wire(objective: &StageObjective) -> v1::train_settings::Objective {
    match objective {
        StageObjective::Stage1(o) => v1::train_settings::Objective::Stage1(v1::Stage1Objective {
            common: common_to_wire(
                o.self_decode_probability,
                o.unmasked_probability,
                o.lpips_weight,
                &o.augment,
                o.variant,
            ),
        }),
        StageObjective::Stage2(o) => v1::train_settings::Objective::Stage2(v1::Stage2Objective {
            common: common_to_wire(
                o.self_decode_probability,
                o.unmasked_probability,
                o.lpips_weight,
                &o.augment,
                o.variant,
            ),
            views: o.views as u64,
            render_from_stage1: o.render_from_stage1,
        }),
    }
}

fn objective_from_wire(
    objective: &v1::train_settings::Objective,
) -> Result<StageObjective, ConvertError> {
    let common = |common: &Option<v1::ObjectiveSettings>| {
        let common = required(common.as_ref(), "train.objective.common")?;
        let augment = required(common.augment.as_ref(), "train.objective.common.augment")?;
        Ok::<_, ConvertError>((*common, augment_from_wire(augment)))
    };
    Ok(match objective {
        v1::train_settings::Objective::Stage1(o) => {
            let (c, augment) = common(&o.common)?;
            StageObjective::Stage1(Stage1Config {
                self_decode_probability: c.self_decode_probability,
                unmasked_probability: c.unmasked_probability,
                lpips_weight: c.lpips_weight,
                augment,
                variant: variant_from_wire(c.variant)?,
            })
        }
        v1::train_settings::Objective::Stage2(o) => {
            let (c, augment) = common(&o.common)?;
            StageObjective::Stage2(Stage2Config {
                views: size(o.views),
                render_from_stage1: o.render_from_stage1,
                self_decode_probability: c.self_decode_probability,
                unmasked_probability: c.unmasked_probability,
                lpips_weight: c.lpips_weight,
                augment,
                variant: variant_from_wire(c.variant)?,
            })
        }
    })
}

impl From<&TrainConfig> for v1::TrainSettings {
    fn from(t: &TrainConfig) -> Self {
        let s = &t.schedule;
        let o = &t.optimizer;
        Self {
            seed: t.seed,
            objective: Some(objective_to_wire(&t.objective)),
            global_batch: t.global_batch as u64,
            micro_batch: t.micro_batch as u64,
            shards: t.shards as u64,
            schedule: Some(v1::ScheduleSettings {
                initial_lr: s.initial_lr,
                peak_lr: s.peak_lr,
                final_lr: s.final_lr,
                warmup_steps: s.warmup_steps,
                total_steps: s.total_steps,
            }),
            optimizer: Some(v1::AdamWSettings {
                beta1: o.beta1,
                beta2: o.beta2,
                epsilon: o.epsilon,
                weight_decay: o.weight_decay,
                clip_norm: o.clip_norm,
                skip_norm_above: o.skip_norm_above,
            }),
        }
    }
}

impl TryFrom<&v1::TrainSettings> for TrainConfig {
    type Error = ConvertError;

    fn try_from(t: &v1::TrainSettings) -> Result<Self, ConvertError> {
        let s = required(t.schedule.as_ref(), "train.schedule")?;
        let o = required(t.optimizer.as_ref(), "train.optimizer")?;
        Ok(Self {
            seed: t.seed,
            objective: objective_from_wire(required(t.objective.as_ref(), "train.objective")?)?,
            global_batch: size(t.global_batch),
            micro_batch: size(t.micro_batch),
            shards: size(t.shards),
            schedule: Schedule {
                initial_lr: s.initial_lr,
                peak_lr: s.peak_lr,
                final_lr: s.final_lr,
                warmup_steps: s.warmup_steps,
                total_steps: s.total_steps,
            },
            optimizer: AdamWConfig {
                beta1: o.beta1,
                beta2: o.beta2,
                epsilon: o.epsilon,
                weight_decay: o.weight_decay,
                clip_norm: o.clip_norm,
                skip_norm_above: o.skip_norm_above,
            },
        })
    }
}

impl From<&DataSpec> for v1::DataSettings {
    fn from(d: &DataSpec) -> Self {
        let source = match &d.source {
            DataSource::Generated {
                scenes,
                trajectories,
                frames,
            } => v1::data_settings::Source::Generated(v1::GeneratedData {
                scenes: *scenes,
                trajectories: *trajectories,
                frames: *frames as u64,
            }),
            DataSource::Stored(stored) => v1::data_settings::Source::Stored(v1::StoredDatasets {
                datasets: stored
                    .iter()
                    .map(|s| v1::StoredDataset {
                        kind: kind_to_wire(s.kind),
                        uri: s.uri.clone(),
                        fingerprint: Some(v1::ListingFingerprint {
                            objects: s.fingerprint.objects,
                            bytes: s.fingerprint.bytes,
                            newest: s.fingerprint.newest,
                            paths_crc: s.fingerprint.paths_crc,
                        }),
                        split_file: s.split_file.clone(),
                    })
                    .collect(),
            }),
        };
        let sampler = &d.sampler;
        Self {
            source: Some(source),
            sampler: Some(v1::SamplerSettings {
                frames: sampler.frames as u64,
                curriculum_steps: sampler.curriculum_steps,
                reverse_probability: sampler.reverse_probability,
                long_baseline: sampler.long_baseline,
                reference_band: sampler.reference_band,
                datasets: sampler
                    .datasets
                    .iter()
                    .map(|s| v1::DatasetSampling {
                        dataset: kind_to_wire(s.dataset),
                        weight: s.weight,
                        window_begin: s.window_begin as u64,
                        window_end: s.window_end as u64,
                    })
                    .collect(),
            }),
            image_size: d.image_size as u64,
            seed: d.seed,
            global_batch: d.global_batch as u64,
        }
    }
}

impl TryFrom<&v1::DataSettings> for DataSpec {
    type Error = ConvertError;

    fn try_from(d: &v1::DataSettings) -> Result<Self, ConvertError> {
        let source = match required(d.source.as_ref(), "data.source")? {
            v1::data_settings::Source::Generated(g) => DataSource::Generated {
                scenes: g.scenes,
                trajectories: g.trajectories,
                frames: size(g.frames),
            },
            v1::data_settings::Source::Stored(stored) => DataSource::Stored(
                stored
                    .datasets
                    .iter()
                    .map(|s| {
                        let f = required(s.fingerprint.as_ref(), "data.stored.fingerprint")?;
                        Ok(StoredDataset {
                            kind: kind_from_wire(s.kind, "data.stored.kind")?,
                            uri: s.uri.clone(),
                            fingerprint: ListingFingerprint {
                                objects: f.objects,
                                bytes: f.bytes,
                                newest: f.newest,
                                paths_crc: f.paths_crc,
                            },
                            split_file: s.split_file.clone(),
                        })
                    })
                    .collect::<Result<_, ConvertError>>()?,
            ),
        };
        let sampler = required(d.sampler.as_ref(), "data.sampler")?;
        Ok(Self {
            source,
            sampler: SamplerConfig {
                frames: size(sampler.frames),
                curriculum_steps: sampler.curriculum_steps,
                reverse_probability: sampler.reverse_probability,
                long_baseline: sampler.long_baseline,
                reference_band: sampler.reference_band,
                datasets: sampler
                    .datasets
                    .iter()
                    .map(|s| {
                        Ok(DatasetSampling {
                            dataset: kind_from_wire(s.dataset, "data.sampler.datasets.dataset")?,
                            weight: s.weight,
                            window_begin: size(s.window_begin),
                            window_end: size(s.window_end),
                        })
                    })
                    .collect::<Result<_, ConvertError>>()?,
            },
            image_size: size(d.image_size),
            seed: d.seed,
            global_batch: size(d.global_batch),
        })
    }
}

impl From<&EvaluationSpec> for v1::EvaluationSettings {
    fn from(e: &EvaluationSpec) -> Self {
        let oracle = match &e.oracle {
            OracleSpec::GroundTruth { subdivisions } => {
                v1::evaluation_settings::Oracle::GroundTruth(v1::GroundTruthOracle {
                    subdivisions: *subdivisions,
                })
            }
            OracleSpec::Classical => {
                v1::evaluation_settings::Oracle::Classical(v1::ClassicalOracle {})
            }
            OracleSpec::External { program, args } => {
                v1::evaluation_settings::Oracle::External(v1::ExternalOracle {
                    program: program.clone(),
                    args: args.clone(),
                })
            }
        };
        Self {
            seed: e.seed,
            scenes: e.scenes,
            trajectories: e.trajectories,
            frames: e.frames as u64,
            tps_pairs: e.tps_pairs as u64,
            tps_frames: e.tps_frames as u64,
            reconstruction_sequences: e.reconstruction_sequences as u64,
            probe: Some(v1::ProbeSettings {
                steps: e.probe.steps as u64,
                batch: e.probe.batch as u64,
                width: e.probe.width as u64,
                learning_rate: e.probe.learning_rate,
                test_scenes: e.probe.test_scenes,
                loss: match e.probe.loss {
                    ProbeLoss::Pairs => v1::ProbeLoss::Pairs,
                    ProbeLoss::Trajectories => v1::ProbeLoss::Trajectories,
                } as i32,
                rotation_from_identity: e.probe.rotation_from_identity,
            }),
            oracle: Some(oracle),
            lpips_weights: e
                .lpips_weights
                .as_ref()
                .map(|p| p.to_string_lossy().into_owned()),
            compare_untrained: e.compare_untrained,
            sequences: e
                .sequences
                .iter()
                .map(|p| v1::SequenceProtocol {
                    kind: kind_to_wire(p.kind),
                    uri: p.uri.clone(),
                    length: p.length as u64,
                    count: p.count as u64,
                })
                .collect(),
            notes: e.notes.clone(),
        }
    }
}

impl TryFrom<&v1::EvaluationSettings> for EvaluationSpec {
    type Error = ConvertError;

    fn try_from(e: &v1::EvaluationSettings) -> Result<Self, ConvertError> {
        let probe = required(e.probe.as_ref(), "evaluate.probe")?;
        let oracle = match required(e.oracle.as_ref(), "evaluate.oracle")? {
            v1::evaluation_settings::Oracle::GroundTruth(x) => OracleSpec::GroundTruth {
                subdivisions: x.subdivisions.max(1),
            },
            v1::evaluation_settings::Oracle::Classical(_) => OracleSpec::Classical,
            v1::evaluation_settings::Oracle::External(x) => OracleSpec::External {
                program: x.program.clone(),
                args: x.args.clone(),
            },
        };
        Ok(Self {
            seed: e.seed,
            scenes: e.scenes,
            trajectories: e.trajectories,
            frames: size(e.frames),
            tps_pairs: size(e.tps_pairs),
            tps_frames: size(e.tps_frames),
            reconstruction_sequences: size(e.reconstruction_sequences),
            probe: ProbeSpec {
                steps: size(probe.steps),
                batch: size(probe.batch),
                width: size(probe.width),
                learning_rate: probe.learning_rate,
                test_scenes: probe.test_scenes,
                rotation_from_identity: probe.rotation_from_identity,
                loss: match v1::ProbeLoss::try_from(probe.loss) {
                    Ok(v1::ProbeLoss::Pairs) => ProbeLoss::Pairs,
                    Ok(v1::ProbeLoss::Trajectories) => ProbeLoss::Trajectories,
                    Err(_) => {
                        return Err(ConvertError::Unknown {
                            field: "evaluate.probe.loss",
                            value: probe.loss,
                        });
                    }
                },
            },
            oracle,
            lpips_weights: e.lpips_weights.as_ref().map(Into::into),
            compare_untrained: e.compare_untrained,
            sequences: e
                .sequences
                .iter()
                .map(|p| {
                    Ok(SequenceProtocol {
                        kind: kind_from_wire(p.kind, "evaluate.sequences.kind")?,
                        uri: p.uri.clone(),
                        length: size(p.length),
                        count: size(p.count),
                    })
                })
                .collect::<Result<_, ConvertError>>()?,
            notes: e.notes.clone(),
        })
    }
}

#[cfg(test)]
mod fuzz_tests;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod work_tests;
