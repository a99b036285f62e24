//! What both transports of the ring share, written once: the gRPC stream (`mod.rs`) and the
//! lanes (`lane.rs`) differ only in how bytes move. Here: who a rank's neighbours are, the
//! check of an arriving chunk's place against the chunk the schedule delivers next, the step
//! that takes a chunk in (add or keep it, round what this rank now owns, send it on), and
//! connecting with retries until a deadline. A third transport adds only what is its own.

use std::future::Future;

use tokio_util::sync::CancellationToken;

use super::schedule::{Delivery, Schedule};
use super::wire::Encoding;

/// The rank whose chunks `rank` receives, in a ring of `world`.
pub(super) fn left_of(rank: usize, world: usize) -> usize {
    (rank + world - 1) % world
}

/// The rank `rank` sends its chunks to, in a ring of `world`.
pub(super) fn right_of(rank: usize, world: usize) -> usize {
    (rank + 1) % world
}

/// Where an arriving chunk says it belongs, as either transport's header carries it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Place {
    /// Which all-reduce of the generation.
    pub(super) operation: u64,
    /// Its ring step.
    pub(super) ring_step: u64,
    /// Its segment.
    pub(super) segment: u64,
    /// Its first value's index.
    pub(super) offset: u64,
    /// Bytes of values it carries.
    pub(super) value_bytes: u64,
}

/// A chunk out of its place: the detail of a `BadChunk`, which blames the neighbour whose
/// authenticated connection delivered it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub(super) struct Misplaced(pub(super) String);

/// Why a chunk at `found` is not `delivery` of all-reduce `operation` under `encoding`.
pub(super) fn check_place(
    found: &Place,
    operation: u64,
    delivery: &Delivery,
    encoding: &Encoding,
) -> Result<(), Misplaced> {
    let expected = Place {
        operation,
        ring_step: delivery.step as u64,
        segment: delivery.segment as u64,
        offset: delivery.begin as u64,
        value_bytes: encoding.chunk_bytes(delivery.begin, delivery.end) as u64,
    };
    let where_of = |place: &Place| {
        format!(
            "operation {} ring step {} segment {} offset {}",
            place.operation, place.ring_step, place.segment, place.offset
        )
    };
    let same_place = |place: &Place| {
        (
            place.operation,
            place.ring_step,
            place.segment,
            place.offset,
        )
    };
    if same_place(found) != same_place(&expected) {
        return Err(Misplaced(format!(
            "{}, expected {}",
            where_of(found),
            where_of(&expected)
        )));
    }
    if found.value_bytes != expected.value_bytes {
        return Err(Misplaced(format!(
            "{} bytes for segment {} at offset {}, expected {} ({} values, {} on the wire)",
            found.value_bytes,
            delivery.segment,
            delivery.begin,
            expected.value_bytes,
            delivery.end - delivery.begin,
            encoding.wire.name()
        )));
    }
    Ok(())
}

/// Takes `delivery` in: adds or keeps `received` (the chunk's bytes; `None` when the
/// transport read them straight into `target`, the buffer's values of the chunk), rounds the
/// values to what the wire carries once this rank owns them, and says whether the chunk
/// travels on to the right neighbour.
pub(super) fn take_in(
    schedule: &Schedule,
    encoding: &Encoding,
    delivery: &Delivery,
    target: &mut [f32],
    received: Option<&[u8]>,
) -> bool {
    if let Some(bytes) = received {
        encoding.absorb(delivery.begin, target, bytes, schedule.adds(delivery.step));
    }
    if schedule.completes(delivery.step) {
        // This rank owns the chunk now: what it keeps is what the others get.
        encoding.round_owned(delivery.begin, target);
    }
    delivery.step + 1 < schedule.steps()
}

/// How one attempt to connect ended, when it did not connect.
pub(super) enum Attempt {
    /// Nothing answered (yet): worth another try until the deadline.
    Again(String),
    /// The other side said no, and why: final.
    Refused(String),
}

/// Why connecting with retries gave up.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum GaveUp {
    /// The generation was abandoned.
    Cancelled,
    /// The other side refused, or the deadline passed (with the last attempt's reason, or
    /// that nothing answered at all).
    Failed(String),
}

/// Runs `attempt` until it connects, is refused, the deadline passes or `cancel` fires,
/// pausing 100 ms between attempts that found nothing answering.
pub(super) async fn with_retries<T, F, Fut>(
    deadline: tokio::time::Instant,
    cancel: &CancellationToken,
    mut attempt: F,
) -> Result<T, GaveUp>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<T, Attempt>>,
{
    let waited = deadline.saturating_duration_since(tokio::time::Instant::now());
    let gave_up = |reason: Option<String>| {
        let silence = || format!("no answer within {:.0} s", waited.as_secs_f64());
        GaveUp::Failed(reason.unwrap_or_else(silence))
    };
    let mut last = None;
    loop {
        let outcome = tokio::select! {
            outcome = attempt() => outcome,
            () = cancel.cancelled() => return Err(GaveUp::Cancelled),
            () = tokio::time::sleep_until(deadline) => return Err(gave_up(last)),
        };
        match outcome {
            Ok(connected) => return Ok(connected),
            Err(Attempt::Refused(reason)) => return Err(GaveUp::Failed(reason)),
            Err(Attempt::Again(reason)) if tokio::time::Instant::now() >= deadline => {
                return Err(GaveUp::Failed(reason));
            }
            Err(Attempt::Again(reason)) => {
                last = Some(reason);
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use settings::work::WireFormat;

    const DELIVERY: Delivery = Delivery {
        step: 1,
        segment: 2,
        begin: 10,
        end: 14,
    };

    fn found(value_bytes: u64) -> Place {
        Place {
            operation: 3,
            ring_step: 1,
            segment: 2,
            offset: 10,
            value_bytes,
        }
    }

    #[test]
    fn a_chunk_in_its_place_passes_and_one_out_of_it_is_named() {
        let encoding = Encoding {
            wire: WireFormat::F32,
            exact_from: 100,
        };
        assert_eq!(check_place(&found(16), 3, &DELIVERY, &encoding), Ok(()));
        let elsewhere = Place {
            segment: 0,
            ..found(16)
        };
        let detail = check_place(&elsewhere, 3, &DELIVERY, &encoding)
            .unwrap_err()
            .0;
        assert!(
            detail.contains("segment 0") && detail.contains("expected"),
            "{detail}"
        );
        let bf16 = check_place(&found(8), 3, &DELIVERY, &encoding)
            .unwrap_err()
            .0;
        assert!(
            bf16.contains("8 bytes") && bf16.contains("expected 16"),
            "{bf16}"
        );
    }

    #[test]
    fn neighbours_wrap_around_the_ring() {
        assert_eq!((left_of(0, 3), right_of(0, 3)), (2, 1));
        assert_eq!((left_of(2, 3), right_of(2, 3)), (1, 0));
        assert_eq!((left_of(0, 1), right_of(0, 1)), (0, 0));
    }

    #[tokio::test]
    async fn retries_stop_at_a_refusal_the_deadline_or_a_cancel() {
        let cancel = CancellationToken::new();
        let soon = tokio::time::Instant::now() + std::time::Duration::from_millis(350);
        let mut tries = 0;
        let refused: Result<(), GaveUp> = with_retries(soon, &cancel, || {
            tries += 1;
            let outcome = if tries < 3 {
                Attempt::Again("nothing yet".into())
            } else {
                Attempt::Refused("no".into())
            };
            async move { Err(outcome) }
        })
        .await;
        assert_eq!((refused, tries), (Err(GaveUp::Failed("no".into())), 3));
        let timed_out: Result<(), GaveUp> = with_retries(soon, &cancel, || async {
            Err(Attempt::Again("still nothing".into()))
        })
        .await;
        assert_eq!(timed_out, Err(GaveUp::Failed("still nothing".into())));
        cancel.cancel();
        let later = tokio::time::Instant::now() + std::time::Duration::from_secs(60);
        let cancelled: Result<(), GaveUp> = with_retries(later, &cancel, || async {
            Err(Attempt::Again(String::new()))
        })
        .await;
        assert_eq!(cancelled, Err(GaveUp::Cancelled));
    }
}
