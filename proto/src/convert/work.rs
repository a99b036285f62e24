//! Assignments and failure reports between their wire forms and `settings::work`'s domain
//! types. Reading checks what the types promise (a rank inside the ring, a start that is one
//! thing, positive intervals, both ring secrets or neither), so a worker never acts on half
//! an assignment.

use settings::data::DataSpec;
use settings::evaluation::EvaluationSpec;
use settings::train::TrainConfig;
use settings::work::{
    Assignment, CheckpointToEvaluate, ChecksumEvery, EvaluateWork, FailureCause, GenerationFailure,
    RingSecrets, TrainStart, TrainWork, WireFormat, Work,
};
use settings::{DeviceSet, Phase};

use super::{ConvertError, device_from_wire, device_to_wire, phase_from_wire, phase_to_wire, size};
use crate::v1;

/// An empty string is the wire's "none".
fn non_empty(value: &str) -> Option<String> {
    (!value.is_empty()).then(|| value.to_string())
}

fn malformed(field: &'static str, reason: impl Into<String>) -> ConvertError {
    ConvertError::Malformed {
        field,
        reason: reason.into(),
    }
}

impl TryFrom<&v1::Assignment> for Assignment {
    type Error = ConvertError;

    fn try_from(wire: &v1::Assignment) -> Result<Self, ConvertError> {
        let work = match wire.work.as_ref().ok_or(ConvertError::Missing("work"))? {
            v1::assignment::Work::Train(train) => Work::Train(Box::new(train.try_into()?)),
            v1::assignment::Work::Evaluate(evaluate) => {
                Work::Evaluate(Box::new(evaluate.try_into()?))
            }
            v1::assignment::Work::Finish(_) => Work::Finish,
        };
        Ok(Self {
            generation: wire.generation,
            work,
        })
    }
}

impl From<&Assignment> for v1::Assignment {
    fn from(assignment: &Assignment) -> Self {
        let work = match &assignment.work {
            Work::Train(train) => v1::assignment::Work::Train(train.as_ref().into()),
            Work::Evaluate(evaluate) => v1::assignment::Work::Evaluate(evaluate.as_ref().into()),
            Work::Finish => v1::assignment::Work::Finish(v1::Finish {}),
        };
        Self {
            generation: assignment.generation,
            work: Some(work),
        }
    }
}

impl TryFrom<&v1::TrainAssignment> for TrainWork {
    type Error = ConvertError;

    fn try_from(wire: &v1::TrainAssignment) -> Result<Self, ConvertError> {
        let stage = phase_from_wire(wire.phase, "train.phase")?;
        if !matches!(stage, Phase::Stage1 | Phase::Stage2) {
            return Err(malformed("train.phase", format!("{stage} is not a stage")));
        }
        let world = wire.world_size as usize;
        if wire.peers.len() != world {
            return Err(malformed(
                "train.peers",
                format!("{} addresses for a world of {world}", wire.peers.len()),
            ));
        }
        let rank = wire.rank as usize;
        if rank >= world {
            return Err(malformed(
                "train.rank",
                format!("rank {rank} in a world of {world}"),
            ));
        }
        Ok(Self {
            stage,
            rank,
            peers: wire.peers.clone(),
            total_steps: wire.total_steps,
            start: start_from_wire(wire)?,
            checkpoint_prefix: non_empty(&wire.checkpoint_prefix)
                .ok_or(ConvertError::Missing("train.checkpoint_prefix"))?,
            checkpoint_every: positive(wire.checkpoint_every, "train.checkpoint_every")?,
            checksum_every: match wire.checksum_every {
                0 => ChecksumEvery::Auto,
                steps => ChecksumEvery::Steps(steps),
            },
            lpips_weights: non_empty(&wire.lpips_weights),
            device: device_from_wire(wire.device, "train.device")?,
            model: wire
                .model
                .as_ref()
                .ok_or(ConvertError::Missing("train.model"))?
                .into(),
            train: TrainConfig::try_from(
                wire.train
                    .as_ref()
                    .ok_or(ConvertError::Missing("train.train"))?,
            )?,
            data: DataSpec::try_from(
                wire.data
                    .as_ref()
                    .ok_or(ConvertError::Missing("train.data"))?,
            )?,
            ring: ring_from_wire(&wire.ring_secret, &wire.left_ring_secret)?,
            devices: devices_from_wire(wire.devices.as_ref())?,
            wire: wire_format_from_wire(wire.wire)?,
            lanes: lanes_from_wire(wire.ring_lanes)?,
        })
    }
}

impl From<&TrainWork> for v1::TrainAssignment {
    fn from(work: &TrainWork) -> Self {
        let (resume_from, init_weights_from) = match &work.start {
            TrainStart::Resume(location) => (location.clone(), String::new()),
            TrainStart::InitWeights(location) => (String::new(), location.clone()),
            TrainStart::Fresh => (String::new(), String::new()),
        };
        let (ring_secret, left_ring_secret) = work
            .ring
            .as_ref()
            .map(|ring| (ring.own.clone(), ring.left.clone()))
            .unwrap_or_default();
        Self {
            rank: work.rank as u32,
            world_size: work.world_size() as u32,
            peers: work.peers.clone(),
            phase: phase_to_wire(work.stage) as i32,
            total_steps: work.total_steps,
            resume_from,
            init_weights_from,
            checkpoint_prefix: work.checkpoint_prefix.clone(),
            checkpoint_every: work.checkpoint_every,
            checksum_every: match work.checksum_every {
                ChecksumEvery::Auto => 0,
                ChecksumEvery::Steps(steps) => steps,
            },
            lpips_weights: work.lpips_weights.clone().unwrap_or_default(),
            device: device_to_wire(work.device) as i32,
            model: Some((&work.model).into()),
            train: Some((&work.train).into()),
            data: Some((&work.data).into()),
            ring_secret,
            left_ring_secret,
            devices: Some(devices_to_wire(&work.devices)),
            wire: wire_format_to_wire(work.wire) as i32,
            ring_lanes: work.lanes as u32,
        }
    }
}

fn lanes_from_wire(lanes: u32) -> Result<usize, ConvertError> {
    let lanes = lanes as usize;
    if lanes > settings::work::MAX_RING_LANES {
        return Err(ConvertError::Malformed {
            field: "train.ring_lanes",
            reason: format!(
                "{lanes} lanes, more than the {} a ring may have",
                settings::work::MAX_RING_LANES
            ),
        });
    }
    Ok(lanes)
}

fn wire_format_from_wire(value: i32) -> Result<WireFormat, ConvertError> {
    match v1::WireFormat::try_from(value) {
        Ok(v1::WireFormat::F32) => Ok(WireFormat::F32),
        Ok(v1::WireFormat::Bf16) => Ok(WireFormat::Bf16),
        Err(_) => Err(ConvertError::Unknown {
            field: "train.wire",
            value,
        }),
    }
}

fn wire_format_to_wire(format: WireFormat) -> v1::WireFormat {
    match format {
        WireFormat::F32 => v1::WireFormat::F32,
        WireFormat::Bf16 => v1::WireFormat::Bf16,
    }
}

fn start_from_wire(wire: &v1::TrainAssignment) -> Result<TrainStart, ConvertError> {
    match (
        non_empty(&wire.resume_from),
        non_empty(&wire.init_weights_from),
    ) {
        (Some(_), Some(_)) => Err(malformed(
            "train.resume_from",
            "set together with train.init_weights_from; a stage starts from one of them",
        )),
        (Some(location), None) => Ok(TrainStart::Resume(location)),
        (None, Some(location)) => Ok(TrainStart::InitWeights(location)),
        (None, None) => Ok(TrainStart::Fresh),
    }
}

fn ring_from_wire(own: &str, left: &str) -> Result<Option<RingSecrets>, ConvertError> {
    match (non_empty(own), non_empty(left)) {
        (Some(own), Some(left)) => Ok(Some(RingSecrets { own, left })),
        (None, None) => Ok(None),
        (Some(_), None) => Err(malformed(
            "train.left_ring_secret",
            "empty while train.ring_secret is set",
        )),
        (None, Some(_)) => Err(malformed(
            "train.ring_secret",
            "empty while train.left_ring_secret is set",
        )),
    }
}

/// The wire form of a device set.
pub fn devices_to_wire(set: &DeviceSet) -> v1::DeviceSet {
    match set {
        DeviceSet::All => v1::DeviceSet::default(),
        DeviceSet::Count(count) => v1::DeviceSet {
            count: *count as u32,
            ids: Vec::new(),
        },
        DeviceSet::Ids(ids) => v1::DeviceSet {
            count: 0,
            ids: ids.iter().map(|&id| id as u32).collect(),
        },
    }
}

/// A device set from the wire; absent means every device.
pub fn devices_from_wire(wire: Option<&v1::DeviceSet>) -> Result<DeviceSet, ConvertError> {
    let Some(wire) = wire else {
        return Ok(DeviceSet::All);
    };
    match (wire.count, wire.ids.is_empty()) {
        (0, true) => Ok(DeviceSet::All),
        (count, true) => Ok(DeviceSet::Count(count as usize)),
        (0, false) => Ok(DeviceSet::Ids(
            wire.ids.iter().map(|&id| id as usize).collect(),
        )),
        (_, false) => Err(malformed(
            "train.devices",
            "a count and indices at once; a set is one of them",
        )),
    }
}

fn positive(value: u64, field: &'static str) -> Result<u64, ConvertError> {
    if value == 0 {
        Err(malformed(field, "0; it must be at least 1"))
    } else {
        Ok(value)
    }
}

impl TryFrom<&v1::EvaluateAssignment> for EvaluateWork {
    type Error = ConvertError;

    fn try_from(wire: &v1::EvaluateAssignment) -> Result<Self, ConvertError> {
        if wire.checkpoints.is_empty() {
            return Err(ConvertError::Missing("evaluate.checkpoints"));
        }
        Ok(Self {
            checkpoints: wire
                .checkpoints
                .iter()
                .map(CheckpointToEvaluate::try_from)
                .collect::<Result<_, _>>()?,
            report_prefix: non_empty(&wire.report_prefix)
                .ok_or(ConvertError::Missing("evaluate.report_prefix"))?,
            device: device_from_wire(wire.device, "evaluate.device")?,
            model: wire
                .model
                .as_ref()
                .ok_or(ConvertError::Missing("evaluate.model"))?
                .into(),
            spec: EvaluationSpec::try_from(
                wire.spec
                    .as_ref()
                    .ok_or(ConvertError::Missing("evaluate.spec"))?,
            )?,
        })
    }
}

impl From<&EvaluateWork> for v1::EvaluateAssignment {
    fn from(work: &EvaluateWork) -> Self {
        Self {
            checkpoints: work.checkpoints.iter().map(Into::into).collect(),
            report_prefix: work.report_prefix.clone(),
            device: device_to_wire(work.device) as i32,
            model: Some((&work.model).into()),
            spec: Some((&work.spec).into()),
        }
    }
}

impl TryFrom<&v1::CheckpointToEvaluate> for CheckpointToEvaluate {
    type Error = ConvertError;

    fn try_from(wire: &v1::CheckpointToEvaluate) -> Result<Self, ConvertError> {
        Ok(Self {
            stage: phase_from_wire(wire.stage, "evaluate.checkpoints.stage")?,
            weights: non_empty(&wire.weights)
                .ok_or(ConvertError::Missing("evaluate.checkpoints.weights"))?,
            step: wire.step,
            context_views: size(positive(
                wire.context_views,
                "evaluate.checkpoints.context_views",
            )?),
        })
    }
}

impl From<&CheckpointToEvaluate> for v1::CheckpointToEvaluate {
    fn from(checkpoint: &CheckpointToEvaluate) -> Self {
        Self {
            stage: phase_to_wire(checkpoint.stage) as i32,
            weights: checkpoint.weights.clone(),
            step: checkpoint.step,
            context_views: checkpoint.context_views as u64,
        }
    }
}

impl TryFrom<&v1::GenerationFailure> for GenerationFailure {
    type Error = ConvertError;

    fn try_from(wire: &v1::GenerationFailure) -> Result<Self, ConvertError> {
        let cause = match v1::FailureKind::try_from(wire.kind) {
            Ok(v1::FailureKind::Worker) => FailureCause::Worker,
            Ok(v1::FailureKind::Peer) => FailureCause::Peer {
                rank: wire
                    .suspect_rank
                    .ok_or(ConvertError::Missing("failure.suspect_rank"))?
                    as usize,
            },
            Ok(v1::FailureKind::Store) => FailureCause::Store,
            Ok(v1::FailureKind::CorruptCheckpoint) => FailureCause::CorruptCheckpoint {
                location: non_empty(&wire.corrupt_checkpoint)
                    .ok_or(ConvertError::Missing("failure.corrupt_checkpoint"))?,
            },
            Ok(v1::FailureKind::Unspecified) | Err(_) => {
                return Err(ConvertError::Unknown {
                    field: "failure.kind",
                    value: wire.kind,
                });
            }
        };
        Ok(Self {
            reason: wire.reason.clone(),
            cause,
        })
    }
}

impl From<&GenerationFailure> for v1::GenerationFailure {
    fn from(failure: &GenerationFailure) -> Self {
        let (kind, suspect_rank, corrupt_checkpoint) = match &failure.cause {
            FailureCause::Worker => (v1::FailureKind::Worker, None, String::new()),
            FailureCause::Peer { rank } => {
                (v1::FailureKind::Peer, Some(*rank as u32), String::new())
            }
            FailureCause::Store => (v1::FailureKind::Store, None, String::new()),
            FailureCause::CorruptCheckpoint { location } => {
                (v1::FailureKind::CorruptCheckpoint, None, location.clone())
            }
        };
        Self {
            reason: failure.reason.clone(),
            suspect_rank,
            corrupt_checkpoint,
            kind: kind as i32,
        }
    }
}
