//! What the ring's test files share: a rank's Collective service on loopback, gradient-like
//! values, and the test certificates.
#![allow(dead_code)] // each test binary compiles this module; not all of them use every helper

use std::sync::Arc;

use worker::collective::{CollectiveService, Link, Mailbox, PeerTls, spawn_server};

/// A rank's Collective service on a free loopback port under `link`: its address and mailbox.
pub async fn serve_with(link: &Link) -> (String, Arc<Mailbox>) {
    let service = CollectiveService::default();
    let mailbox = service.mailbox();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    spawn_server(listener, service, link).unwrap();
    (address, mailbox)
}

/// Gradient-like values of `rank`: small, of both signs, different on every rank.
pub fn gradient(rank: usize, len: usize) -> Vec<f32> {
    (0..len)
        .map(|i| ((i * 7919 + rank * 104_729) % 2003) as f32 * 1e-6 - 1e-3)
        .collect()
}

/// A rank's TLS with the test certificates of `proto/testdata/tls` (valid for localhost and
/// 127.0.0.1), each peer checked against its own host.
pub fn test_tls() -> PeerTls {
    let certificates =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../proto/testdata/tls");
    PeerTls::from_files(
        &certificates.join("server.pem"),
        &certificates.join("server.key"),
        &certificates.join("ca.pem"),
        None,
    )
    .unwrap()
}
