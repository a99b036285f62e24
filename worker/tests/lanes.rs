//! The ring on TCP lanes between in-process ranks on loopback: the same sums, to the bit, as
//! on the gRPC stream, whatever the lanes, chunks and wire; and a lane that does not carry the
//! job's token or the left neighbour's secret is refused before any chunk.

use std::time::Duration;

use tokio_util::sync::CancellationToken;
use worker::collective::{
    CollectiveService, Link, Mailbox, Ring, RingKeys, WireFormat, spawn_server,
};

const TOKEN: &str = "lane-test";

fn link(lanes: usize) -> Link {
    Link {
        token: TOKEN.into(),
        timeout: Duration::from_secs(10),
        tls: None,
        lanes,
    }
}

async fn serve() -> (String, std::sync::Arc<Mailbox>) {
    let service = CollectiveService::default();
    let mailbox = service.mailbox();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    spawn_server(listener, service, &link(1)).unwrap();
    (address, mailbox)
}

fn keys(rank: usize, world: usize) -> RingKeys {
    RingKeys {
        own: format!("secret-{rank}"),
        left: format!("secret-{}", (rank + world - 1) % world),
    }
}

/// Gradient-like values of `rank`: small, of both signs, different on every rank.
fn gradient(rank: usize, len: usize) -> Vec<f32> {
    (0..len)
        .map(|i| ((i * 7919 + rank * 104_729) % 2003) as f32 * 1e-6 - 1e-3)
        .collect()
}

/// Every rank's buffer after two all-reduces of `len` values on a ring of `world` ranks with
/// `lanes` lanes (0: the gRPC stream), chunks of `chunk` values, and `wire`.
async fn reduce(
    world: usize,
    lanes: usize,
    chunk: usize,
    len: usize,
    wire: WireFormat,
) -> Vec<Vec<f32>> {
    let mut servers = Vec::new();
    for _ in 0..world {
        servers.push(serve().await);
    }
    let peers: Vec<String> = servers.iter().map(|(a, _)| a.clone()).collect();
    let mut tasks = Vec::new();
    for (rank, (_, mailbox)) in servers.into_iter().enumerate() {
        let peers = peers.clone();
        tasks.push(tokio::spawn(async move {
            let keys = keys(rank, world);
            let cancel = CancellationToken::new();
            let link = link(lanes);
            let ring = Ring::connect(&mailbox, rank, &peers, 5, &keys, &link, cancel);
            let mut ring = ring.await.unwrap().with_wire(wire);
            ring.set_chunk_values(chunk);
            let mut values = gradient(rank, len);
            for _ in 0..2 {
                ring.all_reduce(&mut values, 3).await.unwrap();
            }
            values
        }));
    }
    let mut results = Vec::new();
    for task in tasks {
        results.push(task.await.unwrap());
    }
    results
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lanes_sum_to_the_same_bits_as_the_grpc_stream() {
    // One lane cuts the buffer as the stream does, so the additions happen in the same order.
    for (world, chunk, len, wire) in [
        (2, 1 << 18, 1 << 22, WireFormat::F32),
        (3, 37, 1003, WireFormat::Bf16),
        (4, 5, 3, WireFormat::F32),
    ] {
        let on_lane = reduce(world, 1, chunk, len, wire).await;
        let on_stream = reduce(world, 0, chunk, len, wire).await;
        for (rank, values) in on_lane.iter().enumerate() {
            assert_eq!(
                bits(values),
                bits(&on_stream[0]),
                "{world} ranks, chunks of {chunk}, {len} values, {}: rank {rank}",
                wire.name()
            );
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn several_lanes_leave_every_rank_the_same_sum() {
    for (world, lanes, chunk, len) in [(2, 3, 37, 1003), (3, 2, 1000, 100_003), (3, 4, 7, 10)] {
        let results = reduce(world, lanes, chunk, len, WireFormat::F32).await;
        for (rank, values) in results.iter().enumerate() {
            // Each lane cuts its own range into segments, so a value's owner (and with three
            // ranks or more its order of additions) differs from one lane's; every rank still
            // ends with the owner's bits.
            assert_eq!(
                bits(values),
                bits(&results[0]),
                "{world} ranks, {lanes} lanes: rank {rank}"
            );
        }
        for (i, value) in results[0].iter().enumerate() {
            // Two all-reduces: the sum of the sums.
            let exact: f64 = (0..world)
                .map(|rank| f64::from(gradient(rank, len)[i]))
                .sum::<f64>()
                * world as f64;
            assert!(
                (f64::from(*value) - exact).abs() <= 1e-6 * exact.abs().max(1e-3),
                "{world} ranks, {lanes} lanes, value {i}: {value} against {exact}"
            );
        }
    }
}

/// Dials `address` as a lane presenting `token` and `secret` for generation 5; the answer's
/// refusal (empty: admitted).
async fn hello(address: &str, token: &str, secret: &str) -> String {
    use prost::Message;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
    let hello = proto::v1::LaneHello {
        token: token.into(),
        ring_secret: secret.into(),
        generation: 5,
        lane: 0,
        lanes: 1,
    };
    let body = hello.encode_to_vec();
    let mut opening = b"XFLANE01".to_vec();
    opening.extend_from_slice(&(body.len() as u32).to_le_bytes());
    opening.extend_from_slice(&body);
    stream.write_all(&opening).await.unwrap();
    let mut length = [0u8; 4];
    stream.read_exact(&mut length).await.unwrap();
    let mut answer = vec![0u8; u32::from_le_bytes(length) as usize];
    stream.read_exact(&mut answer).await.unwrap();
    proto::v1::LaneAnswer::decode(answer.as_slice())
        .unwrap()
        .refusal
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lane_needs_the_job_token_and_the_left_neighbours_secret() {
    let (address, mailbox) = serve().await;
    let peers = vec![address.clone(), "127.0.0.1:1".to_string()];
    // Rank 0 joins generation 5 (its left neighbour is rank 1) and waits for its lanes.
    let joining = tokio::spawn(async move {
        let keys = keys(0, 2);
        let link = Link {
            timeout: Duration::from_secs(2),
            ..link(1)
        };
        Ring::connect(
            &mailbox,
            0,
            &peers,
            5,
            &keys,
            &link,
            CancellationToken::new(),
        )
        .await
    });
    tokio::time::sleep(Duration::from_millis(200)).await;
    let wrong_token = hello(&address, "not-the-token", &keys(1, 2).own).await;
    assert!(wrong_token.contains("token"), "{wrong_token}");
    let wrong_secret = hello(&address, TOKEN, &keys(0, 2).own).await;
    assert!(wrong_secret.contains("left neighbour"), "{wrong_secret}");
    assert_eq!(hello(&address, TOKEN, &keys(1, 2).own).await, "");
    // Rank 0 cannot reach its right neighbour: it says which rank and where.
    let failed = joining.await.unwrap().err().unwrap().to_string();
    assert!(failed.contains("rank 1 at 127.0.0.1:1"), "{failed}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_chunk_header_that_disagrees_blames_the_left_neighbour() {
    let servers = [serve().await, serve().await];
    let peers: Vec<String> = servers.iter().map(|(a, _)| a.clone()).collect();
    let mut tasks = Vec::new();
    // Rank 1 sends bf16 where rank 0 expects float32: its headers announce half the bytes.
    for (rank, (_, mailbox)) in servers.into_iter().enumerate() {
        let peers = peers.clone();
        tasks.push(tokio::spawn(async move {
            let keys = keys(rank, 2);
            let link = link(1);
            let ring = Ring::connect(
                &mailbox,
                rank,
                &peers,
                5,
                &keys,
                &link,
                CancellationToken::new(),
            );
            let wire = if rank == 0 {
                WireFormat::F32
            } else {
                WireFormat::Bf16
            };
            let mut ring = ring.await.unwrap().with_wire(wire);
            let mut values = gradient(rank, 1000);
            ring.all_reduce(&mut values, 0).await
        }));
    }
    let rank_0 = tasks.remove(0).await.unwrap();
    match rank_0 {
        Err(worker::collective::CollectiveError::BadChunk { rank, detail }) => {
            assert_eq!(rank, 1, "{detail}");
            assert!(detail.contains("bytes"), "{detail}");
        }
        other => panic!("rank 0 ended with {other:?}"),
    }
    let _ = tasks.remove(0).await;
}
