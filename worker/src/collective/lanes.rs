//! A ring on lanes: how it opens them and how an all-reduce shares the buffer among them.

use std::time::Instant;

use tokio::sync::mpsc;

use super::carrier::Carrier;
use super::core::with_retries;
use super::lane::{Lane, LaneJob};
use super::opening::{LaneTlsClient, answer, dial};
use super::{AdmittedLane, CollectiveError, Encoding, ReduceStats, Ring, Schedule};

impl Ring {
    /// Dials `hello.lanes` lanes to the right neighbour at `address` (proving `secret`, this
    /// rank's ring secret; over TLS with `tls`) while taking as many from the left one, within
    /// the link's timeout.
    /// Both at once: a dialled lane is answered only once its ring has taken it, so a rank
    /// that dialled before taking would wait on its right neighbour doing the same, around the
    /// ring.
    pub(super) async fn open_lanes(
        &self,
        address: &str,
        hello: proto::v1::LaneHello,
        secret: &str,
        tls: Option<&LaneTlsClient>,
        admitted: mpsc::Receiver<AdmittedLane>,
    ) -> Result<Vec<Lane>, CollectiveError> {
        let deadline = tokio::time::Instant::now() + self.timeout;
        let count = hello.lanes as usize;
        let dialling = async {
            let mut right = Vec::with_capacity(count);
            for lane in 0..hello.lanes {
                let hello = proto::v1::LaneHello {
                    lane,
                    ..hello.clone()
                };
                right.push(
                    self.dial_lane(address, &hello, secret, tls, deadline)
                        .await?,
                );
            }
            Ok(right)
        };
        let taking = self.take_left_lanes(count, admitted, deadline);
        let (right, left) = tokio::try_join!(dialling, taking)?;
        right
            .into_iter()
            .zip(left)
            .map(|(right, left)| Lane::new(right, left))
            .collect::<std::io::Result<Vec<Lane>>>()
            .map_err(|e| CollectiveError::Aborted(format!("a lane's runtime: {e}")))
    }

    /// Takes the left neighbour's `count` lanes as the listener admits them (each proved the
    /// neighbour's secret), answering each once taken: a lane index already open is refused,
    /// not put in the earlier connection's place.
    async fn take_left_lanes(
        &self,
        count: usize,
        mut admitted: mpsc::Receiver<AdmittedLane>,
        deadline: tokio::time::Instant,
    ) -> Result<Vec<Carrier>, CollectiveError> {
        let left_rank = self.left_rank();
        let mut left: Vec<Option<Carrier>> = (0..count).map(|_| None).collect();
        while left.iter().any(Option::is_none) {
            let mut arrived = tokio::select! {
                arrived = admitted.recv() => arrived.ok_or(CollectiveError::Cancelled)?,
                () = self.cancel.cancelled() => return Err(CollectiveError::Cancelled),
                () = tokio::time::sleep_until(deadline) => return Err(CollectiveError::Timeout {
                    rank: left_rank,
                    seconds: self.timeout.as_secs_f64(),
                }),
            };
            if arrived.lanes as usize != count {
                let detail = format!(
                    "it opened lane {} of {}, where this ring has {count}",
                    arrived.lane, arrived.lanes
                );
                let _ = answer(&mut arrived.stream, &detail).await;
                return Err(CollectiveError::BadChunk {
                    rank: left_rank,
                    detail,
                });
            }
            let slot = &mut left[arrived.lane as usize];
            if slot.is_some() {
                let refusal = format!("lane {} is open already", arrived.lane);
                tracing::warn!(
                    lane = arrived.lane,
                    "a second connection for an open lane was refused"
                );
                let _ = answer(&mut arrived.stream, &refusal).await;
                continue;
            }
            if answer(&mut arrived.stream, "").await.is_ok() {
                *slot = Some(arrived.stream);
            }
        }
        Ok(left.into_iter().flatten().collect())
    }

    /// One lane to `address`, tried again while nothing answers, until `deadline`. The
    /// neighbour answers once it has joined the generation too, so the wait for the answer is
    /// bounded by the deadline and the generation's end.
    async fn dial_lane(
        &self,
        address: &str,
        hello: &proto::v1::LaneHello,
        secret: &str,
        tls: Option<&LaneTlsClient>,
        deadline: tokio::time::Instant,
    ) -> Result<Carrier, CollectiveError> {
        with_retries(deadline, &self.cancel, || dial(address, hello, secret, tls))
            .await
            .map_err(|gave_up| self.connect_failed(address, gave_up))
    }

    /// Sums `values` across the ring on its lanes, each lane taking one range of the buffer
    /// on a thread of its own; a lane that fails stops the others. Blocks the calling thread.
    pub(super) fn reduce_on_lanes(
        &mut self,
        values: &mut [f32],
        exact_tail: usize,
    ) -> Result<ReduceStats, CollectiveError> {
        let start = Instant::now();
        let len = values.len();
        let exact_from = len.saturating_sub(exact_tail);
        let count = self.lanes.len();
        let mut parts = Vec::with_capacity(count);
        let (mut rest, mut offset) = (values, 0);
        for lane in 0..count {
            let end = (lane + 1) * len / count;
            let (part, tail) = rest.split_at_mut(end - offset);
            parts.push((offset, part));
            (rest, offset) = (tail, end);
        }
        let stop = self.cancel.child_token();
        let jobs: Vec<LaneJob<'_>> = parts
            .iter()
            .map(|(offset, part)| LaneJob {
                schedule: Schedule {
                    world: self.world,
                    rank: self.rank,
                    chunk_values: self.chunk_values,
                    len: part.len(),
                },
                encoding: Encoding {
                    wire: self.wire,
                    exact_from: exact_from.saturating_sub(*offset),
                },
                operation: self.operation,
                timeout: self.timeout,
                cancel: &stop,
            })
            .collect();
        let results: Vec<Result<u64, CollectiveError>> = std::thread::scope(|scope| {
            let running: Vec<_> = self
                .lanes
                .iter_mut()
                .zip(parts)
                .zip(&jobs)
                .map(|((lane, (_, part)), job)| {
                    let stop = &stop;
                    scope.spawn(move || {
                        let result = lane.all_reduce(job, part);
                        if result.is_err() {
                            stop.cancel();
                        }
                        result
                    })
                })
                .collect();
            running
                .into_iter()
                .map(|thread| {
                    thread
                        .join()
                        .unwrap_or_else(|_| Err(CollectiveError::Aborted("a lane panicked".into())))
                })
                .collect()
        });
        self.operation += 1;
        first_failure(results, self.cancel.is_cancelled()).map(|bytes_sent| ReduceStats {
            seconds: start.elapsed().as_secs_f64(),
            bytes_sent,
        })
    }
}

/// The lanes' bytes sent, or the failure that stopped them: the first that is not the stop
/// it caused in the other lanes (unless the generation itself was abandoned).
fn first_failure(
    results: Vec<Result<u64, CollectiveError>>,
    abandoned: bool,
) -> Result<u64, CollectiveError> {
    let mut cancelled = false;
    let mut bytes = 0;
    let mut failure = None;
    for result in results {
        match result {
            Ok(sent) => bytes += sent,
            Err(CollectiveError::Cancelled) => cancelled = true,
            Err(error) => failure = failure.or(Some(error)),
        }
    }
    match failure {
        Some(error) if !abandoned => Err(error),
        _ if cancelled || abandoned => Err(CollectiveError::Cancelled),
        _ => Ok(bytes),
    }
}
