//! The ring on TLS lanes (a job with `tls:`), between in-process ranks on loopback: the same
//! bits as on plain lanes, nothing but the lane's magic in the clear, and a plain lane
//! refused by a TLS ring with the reason.

mod common;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::{gradient, serve_with as serve, test_tls};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;
use worker::collective::{Link, Mailbox, Ring, RingKeys, WireFormat};

const TOKEN: &str = "tls-lane-test";

fn link(lanes: usize, tls: bool) -> Link {
    Link {
        token: TOKEN.into(),
        timeout: Duration::from_secs(10),
        tls: tls.then(test_tls),
        lanes,
    }
}

fn keys(rank: usize, world: usize) -> RingKeys {
    RingKeys {
        own: format!("secret-{rank}"),
        left: format!("secret-{}", (rank + world - 1) % world),
    }
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

/// Every rank's buffer after two all-reduces of `len` values with `wire` on a ring whose
/// ranks are served at `servers` and dial each other at `peers`.
async fn reduce_at(
    servers: Vec<Arc<Mailbox>>,
    peers: Vec<String>,
    link: &Link,
    len: usize,
    wire: WireFormat,
) -> Vec<Vec<f32>> {
    let world = servers.len();
    let mut tasks = Vec::new();
    for (rank, mailbox) in servers.into_iter().enumerate() {
        let (peers, link) = (peers.clone(), link.clone());
        tasks.push(tokio::spawn(async move {
            let cancel = CancellationToken::new();
            let keys = keys(rank, world);
            let ring = Ring::connect(&mailbox, rank, &peers, 5, &keys, &link, cancel);
            let mut ring = ring.await.unwrap().with_wire(wire);
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

async fn reduce(world: usize, link: &Link, len: usize, wire: WireFormat) -> Vec<Vec<f32>> {
    let mut servers = Vec::new();
    let mut peers = Vec::new();
    for _ in 0..world {
        let (address, mailbox) = serve(link).await;
        peers.push(address);
        servers.push(mailbox);
    }
    reduce_at(servers, peers, link, len, wire).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_lanes_sum_to_the_same_bits_as_plain_lanes() {
    // 16 MB a rank: many times the session's backlog and the socket's buffers.
    for (world, lanes, len, wire) in [
        (2, 1, 1 << 22, WireFormat::F32),
        (2, 2, 1 << 22, WireFormat::Bf16),
        (3, 2, 100_003, WireFormat::F32),
    ] {
        let plain = reduce(world, &link(lanes, false), len, wire).await;
        let tls = reduce(world, &link(lanes, true), len, wire).await;
        for (rank, values) in tls.iter().enumerate() {
            assert_eq!(
                bits(values),
                bits(&plain[rank]),
                "{world} ranks, {lanes} lanes, {}: rank {rank}",
                wire.name()
            );
        }
    }
}

/// Forwards connections from `listener` to `target`, keeping what the dialler sent.
async fn eavesdrop(listener: tokio::net::TcpListener, target: String, heard: Arc<Mutex<Vec<u8>>>) {
    loop {
        let Ok((mut dialler, _)) = listener.accept().await else {
            return;
        };
        let mut listener_side = tokio::net::TcpStream::connect(&target).await.unwrap();
        let heard = heard.clone();
        tokio::spawn(async move {
            let (mut from_dialler, mut to_dialler) = dialler.split();
            let (mut from_listener, mut to_listener) = listener_side.split();
            let forward = async {
                let mut buffer = vec![0u8; 1 << 16];
                loop {
                    let read = from_dialler.read(&mut buffer).await.unwrap_or(0);
                    if read == 0 {
                        let _ = to_listener.shutdown().await;
                        return;
                    }
                    heard.lock().unwrap().extend_from_slice(&buffer[..read]);
                    if to_listener.write_all(&buffer[..read]).await.is_err() {
                        return;
                    }
                }
            };
            let back = tokio::io::copy(&mut from_listener, &mut to_dialler);
            let _ = tokio::join!(forward, back);
        });
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nothing_of_a_tls_lane_is_in_the_clear_but_its_magic() {
    let link = link(1, true);
    let (address_0, mailbox_0) = serve(&link).await;
    let (address_1, mailbox_1) = serve(&link).await;
    // Rank 0 reaches rank 1 through a listener that keeps every byte rank 0 sends.
    let proxy = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let proxy_address = proxy.local_addr().unwrap().to_string();
    let heard = Arc::new(Mutex::new(Vec::new()));
    tokio::spawn(eavesdrop(proxy, address_1, heard.clone()));
    let len = 1 << 16;
    let results = reduce_at(
        vec![mailbox_0, mailbox_1],
        vec![address_0, proxy_address],
        &link,
        len,
        WireFormat::F32,
    )
    .await;
    assert_eq!(bits(&results[0]), bits(&results[1]));
    let heard = heard.lock().unwrap().clone();
    assert!(
        heard.len() > 4 * len,
        "the chunks went through: {}",
        heard.len()
    );
    assert_eq!(&heard[..8], b"XFLANE1S");
    assert_eq!(heard[8], 0x16, "a TLS handshake follows the magic");
    let values: Vec<u8> = gradient(0, len)[1000..1016]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    for (what, secret) in [
        ("the token", TOKEN.as_bytes()),
        ("rank 0's secret", keys(0, 2).own.as_bytes()),
        ("rank 0's values", &values[..]),
    ] {
        let shown = heard.windows(secret.len()).any(|window| window == secret);
        assert!(!shown, "{what} crossed the connection in the clear");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tls_ring_refuses_a_plain_lane_and_says_why() {
    let (address, _mailbox) = serve(&link(1, true)).await;
    let mut stream = tokio::net::TcpStream::connect(&address).await.unwrap();
    stream.write_all(b"XFLANE01").await.unwrap();
    let mut length = [0u8; 4];
    stream.read_exact(&mut length).await.unwrap();
    let mut body = vec![0u8; u32::from_le_bytes(length) as usize];
    stream.read_exact(&mut body).await.unwrap();
    let challenge: proto::v1::LaneChallenge = prost::Message::decode(body.as_slice()).unwrap();
    assert!(challenge.refusal.contains("TLS"), "{}", challenge.refusal);
    assert!(challenge.proof.is_empty());
}
