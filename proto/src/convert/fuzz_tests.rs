//! No message from the wire can panic a conversion: valid messages of every kind the processes
//! exchange are encoded, then mutated thousands of times (bytes flipped, replaced, cut, fields
//! duplicated with extreme values); whatever prost decodes from them goes through its
//! conversion, which must return a value or an error. Deterministic: the mutations come from
//! a fixed seed.

use std::panic::{AssertUnwindSafe, catch_unwind};

use prost::Message;
use settings::evaluation::EvaluationSpec;
use settings::work::{Assignment, FailureCause, GenerationFailure, Work};
use settings::{Backend, DeviceInUse, XFactorConfig};

use super::work_tests::every_kind_of_work;
use super::*;

/// Mutations tried per message.
const MUTATIONS: usize = 3000;

/// splitmix64: the mutations' random stream.
struct Draws(u64);

impl Draws {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, bound: usize) -> usize {
        (self.next() % bound.max(1) as u64) as usize
    }
}

/// A varint field `field` holding `value`, or a fixed64 one (doubles travel so).
fn extreme_field(draws: &mut Draws) -> Vec<u8> {
    let field = 1 + draws.below(24) as u64;
    let mut bytes = Vec::new();
    if draws.next().is_multiple_of(2) {
        let values = [
            u64::MAX,
            i64::MIN as u64,
            0,
            1 << 63,
            u32::MAX as u64,
            1 << 40,
        ];
        prost::encoding::encode_key(field as u32, prost::encoding::WireType::Varint, &mut bytes);
        prost::encoding::encode_varint(values[draws.below(values.len())], &mut bytes);
    } else {
        let values = [
            f64::INFINITY,
            f64::NAN,
            -1.0,
            1e300,
            -0.0,
            f64::MIN_POSITIVE,
        ];
        prost::encoding::encode_key(
            field as u32,
            prost::encoding::WireType::SixtyFourBit,
            &mut bytes,
        );
        bytes.extend_from_slice(&values[draws.below(values.len())].to_le_bytes());
    }
    bytes
}

/// One mutation of `bytes`.
fn mutate(bytes: &[u8], draws: &mut Draws) -> Vec<u8> {
    let mut out = bytes.to_vec();
    let at = draws.below(out.len());
    match draws.below(5) {
        0 if !out.is_empty() => out[at] ^= 1 << draws.below(8),
        1 if !out.is_empty() => out[at] = draws.next() as u8,
        2 => out.truncate(at),
        3 => out.extend(extreme_field(draws)),
        _ => {
            let insert = extreme_field(draws);
            let at = draws.below(out.len() + 1);
            out.splice(at..at, insert);
        }
    }
    out
}

/// Decodes every mutation of `message` as `M` and converts it with `convert`; a panic fails.
fn never_panics<M: Message + Default>(message: &M, seed: u64, convert: impl Fn(&M)) {
    let bytes = message.encode_to_vec();
    let mut draws = Draws(seed);
    let mut decoded = 0;
    for round in 0..MUTATIONS {
        let mut mutated = mutate(&bytes, &mut draws);
        for _ in 0..draws.below(3) {
            mutated = mutate(&mutated, &mut draws);
        }
        let Ok(wire) = M::decode(mutated.as_slice()) else {
            continue;
        };
        decoded += 1;
        let outcome = catch_unwind(AssertUnwindSafe(|| convert(&wire)));
        assert!(
            outcome.is_ok(),
            "mutation {round} of seed {seed} panicked: {mutated:02x?}"
        );
    }
    assert!(decoded > MUTATIONS / 10, "only {decoded} mutations decoded");
}

fn assignments() -> Vec<Assignment> {
    every_kind_of_work()
        .into_iter()
        .map(|work| Assignment {
            generation: 12,
            work,
        })
        .collect()
}

#[test]
fn no_mutated_assignment_panics_its_conversion() {
    for (seed, assignment) in assignments().iter().enumerate() {
        let wire = v1::Assignment::from(assignment);
        never_panics(&wire, seed as u64, |message| {
            let _ = Assignment::try_from(message);
        });
    }
}

#[test]
fn no_mutated_settings_panic_their_conversion() {
    let assignments = assignments();
    let Work::Train(work) = &assignments[0].work else {
        unreachable!("the first assignment trains");
    };
    never_panics(&v1::TrainSettings::from(&work.train), 10, |message| {
        let _ = TrainConfig::try_from(message);
    });
    never_panics(&v1::DataSettings::from(&work.data), 11, |message| {
        let _ = DataSpec::try_from(message);
    });
    never_panics(&v1::ModelConfig::from(&work.model), 12, |message| {
        let _ = XFactorConfig::from(message);
    });
    let spec = EvaluationSpec::default();
    never_panics(&v1::EvaluationSettings::from(&spec), 13, |message| {
        let _ = EvaluationSpec::try_from(message);
    });
}

#[test]
fn no_mutated_report_panics_its_conversion() {
    let failure = GenerationFailure {
        reason: "the store refused".into(),
        cause: FailureCause::CorruptCheckpoint {
            location: "s3://bucket/job/stage1/step-00000010-g2".into(),
        },
    };
    never_panics(&v1::GenerationFailure::from(&failure), 20, |message| {
        let _ = GenerationFailure::try_from(message);
    });
    let device = DeviceInUse {
        backend: Backend::Cuda,
        name: "NVIDIA H200".into(),
        replicas: 2,
    };
    never_panics(&device_in_use_to_wire(&device), 21, |message| {
        let _ = device_in_use_from_wire(message, "heartbeat.device");
    });
    never_panics(
        &v1::RegisterReply {
            heartbeat_interval_s: 0.5,
            ..v1::RegisterReply::default()
        },
        22,
        |message| {
            let _ = seconds_from_wire(message.heartbeat_interval_s, 0.0, "interval");
        },
    );
    let step = v1::StepReport {
        worker_id: 3,
        generation: 2,
        step: 40,
        loss: Some(v1::LossTerms {
            total: 0.25,
            lpips: f32::NAN,
            ..v1::LossTerms::default()
        }),
        checksum_computed: true,
        skipped_examples: vec!["re10k a.png: unreadable".into()],
        ..v1::StepReport::default()
    };
    never_panics(&step, 23, |message| {
        let _ = settings::work::StepReport::from(message);
    });
    never_panics(
        &v1::HeartbeatRequest {
            activity: v1::Activity::Allreduce as i32,
            ..v1::HeartbeatRequest::default()
        },
        24,
        |message| {
            let _ = activity_from_wire(message.activity, "heartbeat.activity");
        },
    );
}
