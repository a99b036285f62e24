//! A TCP proxy on loopback whose upload direction (client to server) can be throttled, so a
//! test can hold a checkpoint upload in flight long enough to kill its uploader mid-way.

use std::io::{Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// Forwards every connection to `upstream`; bytes towards it pass at most `rate` bytes per
/// second per connection (0: unthrottled), bytes back pass at once.
pub struct ThrottledProxy {
    /// `http://127.0.0.1:PORT`, the endpoint clients dial.
    pub endpoint: String,
    rate: Arc<AtomicU64>,
}

impl ThrottledProxy {
    /// Listens on a free loopback port and forwards to `127.0.0.1:upstream_port`.
    pub fn start(upstream_port: u16, bytes_per_s: u64) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let endpoint = format!("http://{}", listener.local_addr().unwrap());
        let rate = Arc::new(AtomicU64::new(bytes_per_s));
        let shared = Arc::clone(&rate);
        std::thread::spawn(move || {
            for client in listener.incoming().flatten() {
                let Ok(server) = TcpStream::connect(("127.0.0.1", upstream_port)) else {
                    continue;
                };
                let (Ok(client_read), Ok(server_read)) = (client.try_clone(), server.try_clone())
                else {
                    continue;
                };
                let rate = Arc::clone(&shared);
                std::thread::spawn(move || pump(client_read, server, Some(rate)));
                std::thread::spawn(move || pump(server_read, client, None));
            }
        });
        Self { endpoint, rate }
    }

    /// Changes the upload rate of every connection from now on (0: unthrottled).
    pub fn set_rate(&self, bytes_per_s: u64) {
        self.rate.store(bytes_per_s, Ordering::SeqCst);
    }
}

/// Copies `from` into `to` until either side closes, pacing the copy to `rate` when given.
fn pump(mut from: TcpStream, mut to: TcpStream, rate: Option<Arc<AtomicU64>>) {
    let mut buffer = [0u8; 4096];
    loop {
        let read = match from.read(&mut buffer) {
            Ok(0) | Err(_) => break,
            Ok(read) => read,
        };
        if to.write_all(&buffer[..read]).is_err() {
            break;
        }
        // Each chunk waits its share of a second, so a pooled connection that sat idle
        // earns no credit for a burst later.
        let limit = rate.as_ref().map_or(0, |r| r.load(Ordering::SeqCst));
        if limit > 0 {
            std::thread::sleep(Duration::from_secs_f64(read as f64 / limit as f64));
        }
    }
    let _ = to.shutdown(Shutdown::Write);
    let _ = from.shutdown(Shutdown::Read);
}
