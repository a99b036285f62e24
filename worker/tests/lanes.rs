//! The ring on TCP lanes between in-process ranks on loopback: the same sums, to the bit, as
//! on the gRPC stream, whatever the lanes, chunks and wire; a lane that cannot prove the left
//! neighbour's secret is refused before any chunk, a dialler shows whoever answers neither
//! the job's token nor its secret, and a flood of strangers on a rank's port neither stops the
//! ring nor makes the rank hold more than the desk's limits.

mod common;

use std::time::Duration;

use common::{gradient, serve_with};
use tokio_util::sync::CancellationToken;
use worker::collective::{Link, Mailbox, Ring, RingKeys, WireFormat};

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
    serve_with(&link(1)).await
}

fn keys(rank: usize, world: usize) -> RingKeys {
    RingKeys {
        own: format!("secret-{rank}"),
        left: format!("secret-{}", (rank + world - 1) % world),
    }
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
    reduce_on(servers, lanes, chunk, len, wire).await
}

/// As [`reduce`], on the ranks served at `servers`.
async fn reduce_on(
    servers: Vec<(String, std::sync::Arc<Mailbox>)>,
    lanes: usize,
    chunk: usize,
    len: usize,
    wire: WireFormat,
) -> Vec<Vec<f32>> {
    let world = servers.len();
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

/// Writes `message` with its length as a little-endian u32 before it.
async fn send(stream: &mut tokio::net::TcpStream, message: &impl prost::Message) {
    use tokio::io::AsyncWriteExt;
    let body = message.encode_to_vec();
    let mut framed = (body.len() as u32).to_le_bytes().to_vec();
    framed.extend_from_slice(&body);
    stream.write_all(&framed).await.unwrap();
}

/// Reads one length-prefixed message.
async fn receive<M: prost::Message + Default>(stream: &mut tokio::net::TcpStream) -> M {
    use tokio::io::AsyncReadExt;
    let mut length = [0u8; 4];
    stream.read_exact(&mut length).await.unwrap();
    let mut body = vec![0u8; u32::from_le_bytes(length) as usize];
    stream.read_exact(&mut body).await.unwrap();
    M::decode(body.as_slice()).unwrap()
}

/// HMAC-SHA256 keyed with `secret` over `label`, `nonce` and lane 0 of 1 of generation 5, as
/// the protocol (`proto/proto/xfactor.proto`, `LaneHello`) defines a proof.
fn proof(secret: &str, label: &str, nonce: &[u8]) -> Vec<u8> {
    let mut message = label.as_bytes().to_vec();
    message.extend_from_slice(nonce);
    message.extend_from_slice(&5u64.to_le_bytes());
    message.extend_from_slice(&0u32.to_le_bytes());
    message.extend_from_slice(&1u32.to_le_bytes());
    let key = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, secret.as_bytes());
    ring::hmac::sign(&key, &message).as_ref().to_vec()
}

/// Dials `address` as lane 0 of 1 of generation 5 holding `secret`, written by hand from the
/// protocol: returns whether the listener proved that it holds `secret`, and the refusal of
/// the listener's last word (empty: admitted).
async fn handshake(address: &str, secret: &str) -> (bool, String) {
    use tokio::io::AsyncWriteExt;
    let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
    let nonce = vec![42u8; 32];
    stream.write_all(b"XFLANE01").await.unwrap();
    let hello = proto::v1::LaneHello {
        generation: 5,
        lane: 0,
        lanes: 1,
        nonce: nonce.clone(),
    };
    send(&mut stream, &hello).await;
    let challenge: proto::v1::LaneChallenge = receive(&mut stream).await;
    assert!(challenge.refusal.is_empty(), "{}", challenge.refusal);
    let listener_proven = challenge.proof == proof(secret, "xfactor-lane-listener", &nonce);
    let answer = proto::v1::LaneProof {
        proof: proof(secret, "xfactor-lane-dialler", &challenge.nonce),
    };
    send(&mut stream, &answer).await;
    let last: proto::v1::LaneAnswer = receive(&mut stream).await;
    (listener_proven, last.refusal)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lane_must_prove_the_left_neighbours_secret_and_the_listener_proves_it_back() {
    let (address, mailbox) = serve().await;
    let peers = vec![address.clone(), "127.0.0.1:1".to_string()];
    // Rank 0 joins generation 5 (its left neighbour is rank 1) and waits for its lanes.
    let joining = tokio::spawn(async move {
        let keys = keys(0, 2);
        let link = Link {
            timeout: Duration::from_secs(3),
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
    let (listener_proven, refusal) = handshake(&address, &keys(0, 2).own).await;
    assert!(
        !listener_proven,
        "the listener's proof is under rank 1's secret"
    );
    assert!(refusal.contains("wrong proof"), "{refusal}");
    let (listener_proven, refusal) = handshake(&address, &keys(1, 2).own).await;
    assert!(listener_proven);
    assert_eq!(refusal, "", "the left neighbour's lane is taken");
    // Rank 0 cannot reach its right neighbour: it says which rank and where.
    let failed = joining.await.unwrap().err().unwrap().to_string();
    assert!(failed.contains("rank 1 at 127.0.0.1:1"), "{failed}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dialler_shows_an_impostor_neither_the_token_nor_the_secret() {
    use tokio::io::AsyncReadExt;
    let (address, mailbox) = serve().await;
    // Whoever answers at rank 1's address: it cannot prove rank 0's secret, and keeps all it
    // hears.
    let impostor = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let impostor_address = impostor.local_addr().unwrap().to_string();
    let heard = tokio::spawn(async move {
        let (mut stream, _) = impostor.accept().await.unwrap();
        let mut magic = [0u8; 8];
        stream.read_exact(&mut magic).await.unwrap();
        let hello: proto::v1::LaneHello = receive(&mut stream).await;
        let challenge = proto::v1::LaneChallenge {
            refusal: String::new(),
            nonce: vec![7; 32],
            proof: vec![0; 32],
        };
        send(&mut stream, &challenge).await;
        let mut rest = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(2), stream.read_to_end(&mut rest)).await;
        let mut heard = magic.to_vec();
        heard.extend_from_slice(&prost::Message::encode_to_vec(&hello));
        heard.extend_from_slice(&rest);
        (heard, rest.len())
    });
    let peers = vec![address, impostor_address];
    let link = Link {
        timeout: Duration::from_secs(3),
        ..link(1)
    };
    let joined = Ring::connect(
        &mailbox,
        0,
        &peers,
        5,
        &keys(0, 2),
        &link,
        CancellationToken::new(),
    )
    .await;
    let failed = joined.err().unwrap().to_string();
    assert!(failed.contains("could not prove"), "{failed}");
    let (heard, after_challenge) = heard.await.unwrap();
    assert_eq!(
        after_challenge, 0,
        "the dialler sent nothing after a bad proof"
    );
    for secret in [TOKEN, &keys(0, 2).own] {
        let shown = heard
            .windows(secret.len())
            .any(|window| window == secret.as_bytes());
        assert!(!shown, "{secret} crossed the connection");
    }
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

/// Descriptors this process holds open.
fn open_descriptors() -> usize {
    std::fs::read_dir("/proc/self/fd").map_or(0, Iterator::count)
}

/// Resident memory of this process in KiB.
fn resident_kib() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))
        .and_then(|rest| rest.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ring_forms_and_sums_while_strangers_flood_a_ranks_port() {
    let servers = vec![serve().await, serve().await];
    let target = servers[1].0.clone();
    let (descriptors_before, memory_before) = (open_descriptors(), resident_kib());
    // 600 connections at a time from each of two addresses, for 8 s, of every kind.
    let flooder = std::process::Command::new("python3")
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/flood.py"))
        .args([target.as_str(), "8", "600", "127.0.0.2", "127.0.0.3"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("python3 runs the flooder");
    let sampling = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let sampler = {
        let sampling = sampling.clone();
        std::thread::spawn(move || {
            let mut most = (0, 0);
            while sampling.load(std::sync::atomic::Ordering::Relaxed) {
                most = (most.0.max(open_descriptors()), most.1.max(resident_kib()));
                std::thread::sleep(Duration::from_millis(20));
            }
            most
        })
    };
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let (len, lanes) = (100_003, 2);
    let results = reduce_on(servers, lanes, 1000, len, WireFormat::F32).await;
    let flooded = tokio::task::spawn_blocking(move || flooder.wait_with_output())
        .await
        .unwrap()
        .unwrap();
    sampling.store(false, std::sync::atomic::Ordering::Relaxed);
    let (most_descriptors, most_memory) = sampler.join().unwrap();
    let figures = String::from_utf8_lossy(&flooded.stdout).trim().to_string();
    println!(
        "flood {figures} descriptors_before={descriptors_before} most_descriptors={most_descriptors} memory_before_kib={memory_before} most_memory_kib={most_memory}"
    );
    assert!(flooded.status.success(), "the flooder failed: {flooded:?}");
    let opened: u64 = figures
        .split_whitespace()
        .find_map(|pair| pair.strip_prefix("opened="))
        .and_then(|n| n.parse().ok())
        .unwrap_or(0);
    assert!(
        opened >= 2000,
        "the flood opened {opened} connections: {figures}"
    );
    assert_eq!(bits(&results[0]), bits(&results[1]));
    // Each source address holds at most its share of handshakes in progress; the flooder
    // kept 1200 connections open the whole time.
    let bound = descriptors_before + 2 * worker::collective::MAX_HANDSHAKES_PER_ADDRESS + 100;
    assert!(
        most_descriptors <= bound,
        "{most_descriptors} descriptors open, above {bound}"
    );
    assert!(
        most_memory <= memory_before + 256 * 1024,
        "resident memory grew from {memory_before} KiB to {most_memory} KiB"
    );
}
