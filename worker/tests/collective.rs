//! The ring all-reduce between in-process ranks on loopback: sums, chunk pipelining, a peer
//! that sends a chunk of the wrong size, and streams that do not carry the left neighbour's
//! ring secret.

mod common;

use std::time::Duration;

use bytes::Bytes;
use common::{gradient, serve_with, test_tls};
use proto::v1::Chunk;
use proto::v1::collective_client::CollectiveClient;
use tokio_util::sync::CancellationToken;
use worker::collective::{
    CollectiveError, Link, Mailbox, RING_SECRET_KEY, ReduceStats, Ring, RingKeys,
};

const TOKEN: &str = "ring-test";

fn plain() -> Link {
    Link {
        token: TOKEN.into(),
        timeout: Duration::from_secs(10),
        tls: None,
        lanes: 0,
    }
}

fn with_test_certificate() -> Link {
    Link {
        tls: Some(test_tls()),
        ..plain()
    }
}

async fn serve() -> (String, std::sync::Arc<Mailbox>) {
    serve_with(&plain()).await
}

/// The secret of `rank` in these tests (the coordinator draws them at random).
fn secret(rank: usize) -> String {
    format!("ring-secret-of-rank-{rank}")
}

fn keys(rank: usize, world: usize) -> RingKeys {
    RingKeys {
        own: secret(rank),
        left: secret((rank + world - 1) % world),
    }
}

async fn join(
    mailbox: &Mailbox,
    rank: usize,
    peers: &[String],
    generation: u64,
    cancelled: CancellationToken,
) -> Ring {
    let keys = keys(rank, peers.len());
    Ring::connect(mailbox, rank, peers, generation, &keys, &plain(), cancelled)
        .await
        .unwrap()
}

/// A stream of `chunks` to `address` presenting `secret`.
fn pushed(
    chunks: Vec<Chunk>,
    secret: &str,
) -> tonic::Request<tokio_stream::Iter<std::vec::IntoIter<Chunk>>> {
    let mut request = tonic::Request::new(tokio_stream::iter(chunks));
    request
        .metadata_mut()
        .insert(RING_SECRET_KEY, secret.parse().unwrap());
    request
}

async fn channel_to(address: &str) -> tonic::transport::Channel {
    tonic::transport::Endpoint::from_shared(format!("http://{address}"))
        .unwrap()
        .connect()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bf16_wire_sums_in_float32_and_leaves_every_rank_the_same_bits() {
    let world = 3;
    let mut servers = Vec::new();
    for _ in 0..world {
        servers.push(serve().await);
    }
    let peers: Vec<String> = servers.iter().map(|(a, _)| a.clone()).collect();
    let cancelled = CancellationToken::new();
    let (len, exact_tail) = (1003, 3);
    let mut tasks = Vec::new();
    for (rank, (_, mailbox)) in servers.into_iter().enumerate() {
        let peers = peers.clone();
        let cancelled = cancelled.clone();
        tasks.push(tokio::spawn(async move {
            let ring = join(&mailbox, rank, &peers, 7, cancelled).await;
            let mut ring = ring.with_wire(worker::collective::WireFormat::Bf16);
            ring.set_chunk_values(37);
            let mut values = gradient(rank, len);
            let stats = ring.all_reduce(&mut values, exact_tail).await.unwrap();
            (values, stats.bytes_sent)
        }));
    }
    let exact: Vec<f64> = (0..len)
        .map(|i| {
            (0..world)
                .map(|rank| f64::from(gradient(rank, len)[i]))
                .sum()
        })
        .collect();
    let mut results = Vec::new();
    for task in tasks {
        results.push(task.await.unwrap());
    }
    let (first, sent) = &results[0];
    for (values, _) in &results[1..] {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(values), bits(first), "every rank holds the same sum");
    }
    for (i, (value, truth)) in first.iter().zip(&exact).enumerate() {
        let error = (f64::from(*value) - truth).abs();
        if i >= len - exact_tail {
            assert!(error <= 1e-9, "exact value {i}: {value} against {truth}");
        } else {
            // Each of the 3 summands and the sum rounded once to bf16 (2^-9 relative each).
            let bound = 4.0 * 2f64.powi(-9) * 3e-3;
            assert!(
                error <= bound,
                "{i}: {value} against {truth} (error {error:e})"
            );
        }
    }
    // 2 (n - 1) / n of the buffer, at 2 bytes a value instead of 4 (the exact tail at 4).
    let float32_bytes = 2 * (world - 1) * len * 4 / world;
    let sent = *sent as usize;
    assert!(
        sent <= float32_bytes / 2 + 2 * exact_tail * 4,
        "sent {sent} bytes, float32 would be {float32_bytes}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_ranks_sum_in_small_pipelined_chunks() {
    let mut servers = Vec::new();
    for _ in 0..3 {
        servers.push(serve().await);
    }
    let peers: Vec<String> = servers.iter().map(|(a, _)| a.clone()).collect();
    let cancelled = CancellationToken::new();
    let len = 1001;
    let mut tasks = Vec::new();
    for (rank, (_, mailbox)) in servers.into_iter().enumerate() {
        let peers = peers.clone();
        let cancelled = cancelled.clone();
        tasks.push(tokio::spawn(async move {
            let mut ring = join(&mailbox, rank, &peers, 7, cancelled).await;
            ring.set_chunk_values(37);
            let mut values: Vec<f32> = (0..len).map(|i| (i * (rank + 1)) as f32).collect();
            for divisor in [6.0, 3.0] {
                ring.all_reduce(&mut values, 0).await.unwrap();
                values.iter_mut().for_each(|v| *v /= divisor);
            }
            values
        }));
    }
    for task in tasks {
        let values = task.await.unwrap();
        for (i, v) in values.iter().enumerate() {
            assert!(
                (v - i as f32).abs() <= 1e-3 * (i as f32).max(1.0),
                "{i}: {v}"
            );
        }
    }
}

/// Rank 0 of a two-rank ring all-reduces 100 values while a member holding rank 1's ring
/// secret pushes `chunk` into its inbox; rank 0's result.
async fn all_reduce_beside(chunk: Chunk) -> Result<ReduceStats, CollectiveError> {
    let (address_0, mailbox_0) = serve().await;
    let (address_1, _) = serve().await;
    let peers = vec![address_0.clone(), address_1];
    let cancelled = CancellationToken::new();
    let honest = tokio::spawn(async move {
        let mut ring = join(&mailbox_0, 0, &peers, 3, cancelled).await;
        let mut values = vec![1.0f32; 100];
        ring.all_reduce(&mut values, 0).await
    });
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{address_0}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut member =
        CollectiveClient::with_interceptor(channel, proto::AttachToken::new(TOKEN).unwrap());
    let _ = member.push(pushed(vec![chunk], &secret(1))).await;
    honest.await.unwrap()
}

/// The first chunk rank 1 owes rank 0 (segment 1 of 100 values), with `values` bytes.
fn first_chunk(values: usize, sender: u32) -> Chunk {
    Chunk {
        generation: 3,
        operation: 0,
        ring_step: 0,
        segment: 1,
        offset: 50,
        values: Bytes::from(vec![0u8; values]),
        sender,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_chunk_of_the_wrong_size_is_refused_by_name() {
    // A misbehaving member: it holds rank 1's secret but sends a short chunk.
    match all_reduce_beside(first_chunk(4 * 49, 1)).await {
        Err(CollectiveError::BadChunk { rank, detail }) => {
            assert_eq!(rank, 1);
            assert!(detail.contains("196 bytes"), "{detail}");
            assert!(detail.contains("expected 200"), "{detail}");
        }
        other => panic!("expected a bad-chunk error, got {other:?}"),
    }
}

/// A member holding rank 1's ring secret writes a chunk claiming to come from rank 0, the
/// receiver itself: the blame goes to the rank whose authenticated stream delivered it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_forged_sender_field_blames_the_stream_that_delivered_it() {
    match all_reduce_beside(first_chunk(4 * 50, 0)).await {
        Err(CollectiveError::BadChunk { rank, detail }) => {
            assert_eq!(rank, 1, "the forger, not the rank it named");
            assert!(detail.contains("claiming to be from rank 0"), "{detail}");
        }
        other => panic!("expected a bad-chunk error, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_without_the_token_is_refused() {
    let (address, _) = serve().await;
    let mut client = CollectiveClient::new(channel_to(&address).await);
    let refused = client
        .push(tokio_stream::iter(Vec::<Chunk>::new()))
        .await
        .unwrap_err();
    assert_eq!(refused.code(), tonic::Code::Unauthenticated);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_ranks_sum_over_tls_and_plain_text_is_refused() {
    let link = with_test_certificate();
    let mut servers = Vec::new();
    for _ in 0..2 {
        servers.push(serve_with(&link).await);
    }
    let peers: Vec<String> = servers.iter().map(|(a, _)| a.clone()).collect();
    let cancelled = CancellationToken::new();
    let mut tasks = Vec::new();
    for (rank, (_, mailbox)) in servers.into_iter().enumerate() {
        let (peers, cancelled, link) = (peers.clone(), cancelled.clone(), link.clone());
        tasks.push(tokio::spawn(async move {
            let keys = keys(rank, peers.len());
            let mut ring = Ring::connect(&mailbox, rank, &peers, 3, &keys, &link, cancelled)
                .await
                .unwrap();
            let mut values = vec![rank as f32 + 1.0; 300];
            ring.all_reduce(&mut values, 0).await.unwrap();
            values
        }));
    }
    for task in tasks {
        assert!(task.await.unwrap().iter().all(|&v| v == 3.0));
    }
    let plain_text = tonic::transport::Endpoint::from_shared(format!("http://{}", peers[0]))
        .unwrap()
        .connect()
        .await;
    if let Ok(channel) = plain_text {
        let mut client =
            CollectiveClient::with_interceptor(channel, proto::AttachToken::new(TOKEN).unwrap());
        let chunk = Chunk {
            generation: 9,
            values: Bytes::from(vec![0u8; 8]),
            ..Chunk::default()
        };
        let refused = client.push(tokio_stream::iter(vec![chunk])).await;
        assert!(refused.is_err(), "a plain-text stream reached a TLS server");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_the_left_neighbour_of_the_generation_may_stream() {
    let (address_0, mailbox_0) = serve().await;
    let (address_1, mailbox_1) = serve().await;
    let peers = vec![address_0.clone(), address_1];
    let cancelled = CancellationToken::new();
    // The intruder holds the job token, and even rank 0's own secret, but not rank 1's: its
    // chunk would pass every shape check, and must never reach the sum.
    let mut intruder = CollectiveClient::with_interceptor(
        channel_to(&address_0).await,
        proto::AttachToken::new(TOKEN).unwrap(),
    );
    let forged = Chunk {
        generation: 5,
        operation: 0,
        ring_step: 0,
        segment: 1,
        offset: 50,
        values: Bytes::from(vec![0x7fu8; 4 * 50]),
        sender: 1,
    };
    let early = tokio::spawn(async move {
        let refused = intruder
            .push(pushed(vec![forged.clone()], &secret(0)))
            .await
            .unwrap_err();
        let stale = intruder
            .push(pushed(
                vec![Chunk {
                    generation: 4,
                    ..forged
                }],
                &secret(1),
            ))
            .await
            .unwrap_err();
        (refused, stale)
    });
    let mut tasks = Vec::new();
    for (rank, mailbox) in [(0, mailbox_0), (1, mailbox_1)] {
        let (peers, cancelled) = (peers.clone(), cancelled.clone());
        tasks.push(tokio::spawn(async move {
            let mut ring = join(&mailbox, rank, &peers, 5, cancelled).await;
            let mut values = vec![rank as f32 + 1.0; 100];
            ring.all_reduce(&mut values, 0).await.unwrap();
            values
        }));
    }
    for task in tasks {
        assert!(task.await.unwrap().iter().all(|&v| v == 3.0));
    }
    let (refused, stale) = early.await.unwrap();
    assert_eq!(refused.code(), tonic::Code::PermissionDenied, "{refused:?}");
    assert!(refused.message().contains("left neighbour"), "{refused:?}");
    assert_eq!(stale.code(), tonic::Code::FailedPrecondition, "{stale:?}");
}
