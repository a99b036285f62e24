//! Whose fault a failed generation was, read from the typed errors in its chain, so the
//! coordinator can blame the right worker, or none: a peer the collective names (it timed out,
//! its stream broke, it sent a bad chunk), the object store (an upload or download that kept
//! failing), a committed checkpoint that does not verify, or else this worker itself.

use data::store::StoreError;
use settings::work::{FailureCause, GenerationFailure};

use crate::checkpoints::{CorruptCheckpoint, TransferError};
use crate::collective::CollectiveError;
use crate::commits::CommitError;
use crate::context::GenerationEnded;
use crate::device::DeviceMissing;

/// The report of a failed generation: the whole error chain as its reason, and its cause.
pub fn report(error: &anyhow::Error) -> GenerationFailure {
    GenerationFailure {
        reason: format!("{error:#}"),
        cause: cause(error),
    }
}

/// Whether the coordinator ended the generation under this worker (a cancelled all-reduce, a
/// step it no longer acknowledged, a commit it refused: a stale generation, or checksums that
/// did not verify, for which it rolls the group back itself): then nothing in the chain is
/// this worker's fault.
pub fn ended_by_coordinator(error: &anyhow::Error) -> bool {
    error.chain().any(|link| {
        link.downcast_ref::<GenerationEnded>().is_some()
            || matches!(
                link.downcast_ref::<CollectiveError>(),
                Some(CollectiveError::Cancelled)
            )
            || matches!(
                link.downcast_ref::<CommitError>(),
                Some(CommitError::Refused { .. })
            )
    })
}

/// Whether `error` says this worker can never do the work asked: the job's device is not in
/// this build or not on this host. Retrying cannot help, unlike every other failure.
pub fn cannot_run_here(error: &anyhow::Error) -> bool {
    error
        .chain()
        .any(|link| link.downcast_ref::<DeviceMissing>().is_some())
}

/// The first cause in `error`'s chain that names a culprit other than this worker;
/// [`FailureCause::Worker`] when none does.
pub fn cause(error: &anyhow::Error) -> FailureCause {
    error
        .chain()
        .find_map(|link| {
            if let Some(collective) = link.downcast_ref::<CollectiveError>() {
                return Some(collective_cause(collective));
            }
            if let Some(transfer) = link.downcast_ref::<TransferError>() {
                return transfer_cause(transfer);
            }
            if let Some(corrupt) = link.downcast_ref::<CorruptCheckpoint>() {
                return Some(corrupt_cause(corrupt));
            }
            link.downcast_ref::<StoreError>()
                .map(|_| FailureCause::Store)
        })
        .unwrap_or(FailureCause::Worker)
}

/// The peer a collective error points at; its own cancellation, a task that died or a TLS
/// setting of this worker are this worker's.
fn collective_cause(error: &CollectiveError) -> FailureCause {
    match error {
        CollectiveError::Connect { rank, .. }
        | CollectiveError::PeerGone { rank }
        | CollectiveError::InboundBroken { rank, .. }
        | CollectiveError::Timeout { rank, .. }
        | CollectiveError::BadChunk { rank, .. } => FailureCause::Peer { rank: *rank },
        CollectiveError::Cancelled | CollectiveError::Aborted(_) | CollectiveError::Tls(_) => {
            FailureCause::Worker
        }
    }
}

fn transfer_cause(error: &TransferError) -> Option<FailureCause> {
    match error {
        TransferError::Store(_) => Some(FailureCause::Store),
        TransferError::Corrupt(corrupt) => Some(corrupt_cause(corrupt)),
        TransferError::Manifest(_) | TransferError::Local { .. } => None,
    }
}

fn corrupt_cause(corrupt: &CorruptCheckpoint) -> FailureCause {
    FailureCause::CorruptCheckpoint {
        location: corrupt.location.clone(),
    }
}

#[cfg(test)]
mod tests {
    use anyhow::Context;

    use super::*;

    fn store_error() -> StoreError {
        StoreError::NotFound {
            uri: "s3://bucket".into(),
            path: "job/stage1".into(),
        }
    }

    #[test]
    fn a_peer_that_timed_out_or_sent_a_bad_chunk_is_the_suspect() {
        let timeout = anyhow::Error::new(CollectiveError::Timeout {
            rank: 2,
            seconds: 30.0,
        })
        .context("all-reduce of step 7");
        assert_eq!(cause(&timeout), FailureCause::Peer { rank: 2 });
        let bad = anyhow::Error::new(CollectiveError::BadChunk {
            rank: 1,
            detail: "12 values, expected 16".into(),
        });
        assert_eq!(cause(&bad), FailureCause::Peer { rank: 1 });
        let gone = anyhow::Error::new(CollectiveError::PeerGone { rank: 3 });
        assert_eq!(cause(&gone), FailureCause::Peer { rank: 3 });
    }

    #[test]
    fn a_cancelled_all_reduce_is_this_workers_own() {
        let cancelled = anyhow::Error::new(CollectiveError::Cancelled);
        assert_eq!(cause(&cancelled), FailureCause::Worker);
    }

    #[test]
    fn a_generation_the_coordinator_ended_is_told_apart_from_a_failure() {
        let cancelled = anyhow::Error::new(CollectiveError::Cancelled).context("all-reduce");
        assert!(ended_by_coordinator(&cancelled));
        let ended = anyhow::Error::new(GenerationEnded { generation: 4 }).context("step 9");
        assert!(ended_by_coordinator(&ended));
        let own = anyhow::anyhow!("the device is gone");
        assert!(!ended_by_coordinator(&own));
        let peer = anyhow::Error::new(CollectiveError::PeerGone { rank: 1 });
        assert!(!ended_by_coordinator(&peer));
        let refused = anyhow::Error::new(CommitError::Refused {
            location: "s3://bucket/job/stage1/step-00000008-g1".into(),
            reason: "commit of stage 1 step 8 refused: the replicas' checksums differ".into(),
        })
        .context("checkpoint of step 8");
        assert!(
            ended_by_coordinator(&refused),
            "the coordinator rolls back itself"
        );
    }

    #[test]
    fn an_upload_the_store_refused_blames_no_worker() {
        let upload = anyhow::Error::new(CommitError::Upload {
            location: "s3://bucket/job/stage1/step-00000002-g1".into(),
            attempts: 3,
            source: TransferError::Store(store_error()),
        });
        assert_eq!(cause(&upload), FailureCause::Store);
        let read = anyhow::Error::new(store_error()).context("the data shard");
        assert_eq!(cause(&read), FailureCause::Store);
    }

    #[test]
    fn a_full_scratch_disk_is_this_workers_own() {
        let local = anyhow::Error::new(CommitError::Upload {
            location: "s3://bucket/x".into(),
            attempts: 0,
            source: TransferError::Local {
                action: "read",
                path: "/scratch/save".into(),
                source: std::io::Error::other("disk full"),
            },
        });
        assert_eq!(cause(&local), FailureCause::Worker);
        let plain: anyhow::Result<()> = Err(anyhow::anyhow!("NaN in the loss"));
        assert_eq!(
            cause(&plain.context("step 3").unwrap_err()),
            FailureCause::Worker
        );
    }

    #[test]
    fn only_a_device_missing_here_cannot_be_retried() {
        let missing = anyhow::Error::new(DeviceMissing::NotInThisBuild {
            backend: settings::Backend::Cuda,
            feature: "cuda",
        })
        .context("generation 3");
        assert!(cannot_run_here(&missing));
        assert_eq!(cause(&missing), FailureCause::Worker);
        let no_adapter = anyhow::Error::new(DeviceMissing::NoAdapter);
        assert!(cannot_run_here(&no_adapter));
        for retried in [
            anyhow::anyhow!("NaN in the loss"),
            anyhow::Error::new(CollectiveError::PeerGone { rank: 1 }),
            anyhow::Error::new(store_error()),
        ] {
            assert!(!cannot_run_here(&retried), "{retried:#}");
        }
    }

    #[test]
    fn a_corrupt_checkpoint_names_its_location() {
        let corrupt = anyhow::Error::new(TransferError::Corrupt(CorruptCheckpoint {
            location: "file:///ckpt/stage1/step-00000004-g2".into(),
            reason: "model.safetensors is missing".into(),
        }))
        .context("resuming");
        assert_eq!(
            cause(&corrupt),
            FailureCause::CorruptCheckpoint {
                location: "file:///ckpt/stage1/step-00000004-g2".into()
            }
        );
        let report = report(&corrupt);
        assert!(
            report.reason.contains("model.safetensors is missing"),
            "{}",
            report.reason
        );
    }
}
