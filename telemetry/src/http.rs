//! The `/metrics` endpoint: a minimal HTTP/1.1 responder on its own port, enough for
//! Prometheus scrapes and Kubernetes probes (`/healthz`). Every connection gets one answer and
//! is closed, so there is no keep-alive state to get wrong.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::metrics::Registry;

/// The longest request head accepted; scrapers send a few hundred bytes.
const MAX_REQUEST_BYTES: usize = 8 * 1024;

/// Connections served at once; more wait to be accepted, so a flood cannot exhaust sockets.
const MAX_CONNECTIONS: usize = 64;

/// The whole exchange (reading the request, writing the page) must finish within this.
const REQUEST_DEADLINE: Duration = Duration::from_secs(5);

/// Why the endpoint could not start.
#[derive(Debug, thiserror::Error)]
pub enum HttpError {
    /// The address could not be bound.
    #[error("cannot listen for /metrics on {address}: {source}")]
    Bind {
        /// What was asked for.
        address: String,
        /// Why.
        source: std::io::Error,
    },
}

/// Why a process that is up is no use: `/healthz` answers 503 with this text.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Unhealthy(pub String);

/// What `/healthz` asks: `Ok` answers 200 `ok`, `Err(Unhealthy(reason))` answers 503 with the
/// reason, so a liveness probe restarts a process that is up but no use (a worker stuck in its
/// step).
pub type HealthCheck = Arc<dyn Fn() -> Result<(), Unhealthy> + Send + Sync>;

/// A check that always answers `ok`: the process is healthy while it answers at all.
pub fn always_healthy() -> HealthCheck {
    Arc::new(|| Ok(()))
}

/// Binds `address` and serves `registry` on `/metrics` and `health` on `/healthz` there until
/// the process ends. Returns the bound address (useful with port 0).
pub async fn serve(
    address: &str,
    registry: Arc<Registry>,
    health: HealthCheck,
) -> Result<SocketAddr, HttpError> {
    let (bound, serving) = bind(address, registry, health).await?;
    tokio::spawn(serving);
    Ok(bound)
}

/// Binds `address` for [`serve`] and returns the bound address and the server, which serves
/// until it is dropped: for a caller that owns its tasks and ends them itself.
pub async fn bind(
    address: &str,
    registry: Arc<Registry>,
    health: HealthCheck,
) -> Result<(SocketAddr, impl Future<Output = ()> + Send + 'static), HttpError> {
    let bind_error = |source| HttpError::Bind {
        address: address.to_string(),
        source,
    };
    let listener = TcpListener::bind(address).await.map_err(bind_error)?;
    let bound = listener.local_addr().map_err(bind_error)?;
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    let serving = async move {
        loop {
            let Ok(slot) = Arc::clone(&slots).acquire_owned().await else {
                return;
            };
            match listener.accept().await {
                Ok((stream, peer)) => {
                    let registry = Arc::clone(&registry);
                    let health = Arc::clone(&health);
                    tokio::spawn(async move {
                        let answered = tokio::time::timeout(
                            REQUEST_DEADLINE,
                            answer(stream, &registry, health.as_ref()),
                        )
                        .await;
                        match answered {
                            Ok(Ok(())) => {}
                            Ok(Err(error)) => {
                                tracing::debug!(%peer, %error, "metrics request failed");
                            }
                            Err(_) => tracing::debug!(%peer, "metrics request timed out"),
                        }
                        drop(slot);
                    });
                }
                Err(error) => {
                    tracing::warn!(%error, "metrics listener failed to accept");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }
    };
    tracing::info!(address = %bound, "serving /metrics");
    Ok((bound, serving))
}

async fn answer(
    mut stream: TcpStream,
    registry: &Registry,
    health: &(dyn Fn() -> Result<(), Unhealthy> + Send + Sync),
) -> std::io::Result<()> {
    let mut head = Vec::with_capacity(512);
    let mut buffer = [0u8; 1024];
    let read = async {
        while !head.windows(4).any(|w| w == b"\r\n\r\n") && head.len() < MAX_REQUEST_BYTES {
            let n = stream.read(&mut buffer).await?;
            if n == 0 {
                break;
            }
            head.extend_from_slice(&buffer[..n]);
        }
        std::io::Result::Ok(())
    };
    read.await?;
    let request_line = head.split(|&b| b == b'\n').next().unwrap_or_default();
    let request_line = String::from_utf8_lossy(request_line);
    let mut parts = request_line.split_whitespace();
    let (method, path) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    let path = path.split('?').next().unwrap_or("");
    let (status, content_type, body) = match (method, path) {
        ("GET", "/metrics") => (
            "200 OK",
            "text/plain; version=0.0.4; charset=utf-8",
            registry.render(),
        ),
        ("GET", "/healthz") => match health() {
            Ok(()) => ("200 OK", "text/plain; charset=utf-8", "ok\n".to_string()),
            Err(reason) => (
                "503 Service Unavailable",
                "text/plain; charset=utf-8",
                format!("{reason}\n"),
            ),
        },
        ("GET", _) => (
            "404 Not Found",
            "text/plain; charset=utf-8",
            "try /metrics\n".to_string(),
        ),
        _ => (
            "405 Method Not Allowed",
            "text/plain; charset=utf-8",
            "GET only\n".to_string(),
        ),
    };
    let response = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(response.as_bytes()).await?;
    stream.shutdown().await
}

/// Fetches `http://{address}{path}` and returns the status code and body: what tests and the
/// local runner use to scrape, without an HTTP client dependency.
pub async fn get(address: SocketAddr, path: &str) -> std::io::Result<(u16, String)> {
    let mut stream = TcpStream::connect(address).await?;
    let request = format!("GET {path} HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response).await?;
    let text = String::from_utf8_lossy(&response).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|code| code.parse().ok())
        .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::InvalidData, "no status line"))?;
    Ok((status, body.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::Metric;

    #[tokio::test]
    async fn serves_metrics_and_health_and_refuses_the_rest() {
        let registry = Arc::new(Registry::new());
        registry.set(&Metric::gauge("xfactor_step", "Steps."), &[], 12.0);
        let healthy = Arc::new(std::sync::atomic::AtomicBool::new(true));
        let flag = Arc::clone(&healthy);
        let health: HealthCheck = Arc::new(move || {
            if flag.load(std::sync::atomic::Ordering::SeqCst) {
                Ok(())
            } else {
                Err(Unhealthy("removed by the coordinator".to_string()))
            }
        });
        let address = serve("127.0.0.1:0", Arc::clone(&registry), health)
            .await
            .expect("bind");
        let (status, body) = get(address, "/metrics").await.expect("scrape");
        assert_eq!(status, 200);
        assert!(body.contains("xfactor_step 12\n"), "{body}");
        assert_eq!(get(address, "/healthz").await.expect("probe").0, 200);
        healthy.store(false, std::sync::atomic::Ordering::SeqCst);
        assert_eq!(
            get(address, "/healthz").await.expect("probe"),
            (503, "removed by the coordinator\n".to_string())
        );
        assert_eq!(get(address, "/nope").await.expect("404").0, 404);
    }

    #[tokio::test]
    async fn a_taken_port_is_named() {
        let registry = Arc::new(Registry::new());
        let address = serve("127.0.0.1:0", Arc::clone(&registry), always_healthy())
            .await
            .expect("bind");
        let error = serve(&address.to_string(), registry, always_healthy())
            .await
            .expect_err("port taken");
        assert!(error.to_string().contains(&address.to_string()), "{error}");
    }
}
