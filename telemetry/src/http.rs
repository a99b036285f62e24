//! The metrics port: `/metrics` for Prometheus scrapes, `/healthz` for Kubernetes probes, and
//! whatever pages a process adds (the coordinator's status page), routed by axum and served by
//! hyper's HTTP/1.1 server. Every connection gets one answer and is closed, within a deadline,
//! and only so many are served at once, so a flood of idle connections cannot exhaust sockets.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use hyper_util::rt::TokioIo;
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::metrics::Registry;

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
    serve_with(address, registry, health, Router::new()).await
}

/// [`serve`] with `pages` beside `/metrics` and `/healthz`.
pub async fn serve_with(
    address: &str,
    registry: Arc<Registry>,
    health: HealthCheck,
    pages: Router,
) -> Result<SocketAddr, HttpError> {
    let (bound, serving) = bind_with(address, registry, health, pages).await?;
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
    bind_with(address, registry, health, Router::new()).await
}

/// [`bind`] with `pages` beside `/metrics` and `/healthz`.
pub async fn bind_with(
    address: &str,
    registry: Arc<Registry>,
    health: HealthCheck,
    pages: Router,
) -> Result<(SocketAddr, impl Future<Output = ()> + Send + 'static), HttpError> {
    let bind_error = |source| HttpError::Bind {
        address: address.to_string(),
        source,
    };
    let listener = TcpListener::bind(address).await.map_err(bind_error)?;
    let bound = listener.local_addr().map_err(bind_error)?;
    let routes = Router::new()
        .route("/metrics", axum::routing::get(metrics).with_state(registry))
        .route("/healthz", axum::routing::get(healthz).with_state(health))
        .merge(pages)
        .fallback(|| async { (StatusCode::NOT_FOUND, "try /metrics\n") });
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    let serving = async move {
        loop {
            let Ok(slot) = Arc::clone(&slots).acquire_owned().await else {
                return;
            };
            match listener.accept().await {
                Ok((stream, peer)) => {
                    let service = TowerToHyperService::new(routes.clone());
                    tokio::spawn(async move {
                        let connection = hyper::server::conn::http1::Builder::new()
                            .keep_alive(false)
                            .serve_connection(TokioIo::new(stream), service);
                        match tokio::time::timeout(REQUEST_DEADLINE, connection).await {
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

async fn metrics(State(registry): State<Arc<Registry>>) -> impl IntoResponse {
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        registry.render(),
    )
}

async fn healthz(State(health): State<HealthCheck>) -> impl IntoResponse {
    match health() {
        Ok(()) => (StatusCode::OK, "ok\n".to_string()),
        Err(reason) => (StatusCode::SERVICE_UNAVAILABLE, format!("{reason}\n")),
    }
}

/// Fetches `http://{address}{path}` and returns the status code and body: what tests and the
/// local runner use to scrape, without an HTTP client dependency.
pub async fn get(address: SocketAddr, path: &str) -> std::io::Result<(u16, String)> {
    let answer = request(address, "GET", path, &[], "").await?;
    Ok((answer.status, answer.body))
}

/// An HTTP answer as [`request`] reads it.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    /// Its status code.
    pub status: u16,
    /// Its header lines, `name: value` as sent.
    pub headers: Vec<String>,
    /// Its body.
    pub body: String,
}

impl Answer {
    /// The value of header `name` (case-insensitive), if it was sent.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find_map(|line| {
            let (key, value) = line.split_once(':')?;
            key.trim().eq_ignore_ascii_case(name).then(|| value.trim())
        })
    }
}

/// Sends one HTTP/1.1 request with `headers` and `body` to `address` and reads the answer to
/// the end (the server closes every connection after its answer).
pub async fn request(
    address: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> std::io::Result<Answer> {
    let mut stream = TcpStream::connect(address).await?;
    let mut head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    for (name, value) in headers {
        head.push_str(&format!("{name}: {value}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes()).await?;
    stream.write_all(body.as_bytes()).await?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response).await?;
    let text = String::from_utf8_lossy(&response).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let mut lines = head.lines();
    let status = lines
        .next()
        .and_then(|line| line.split_whitespace().nth(1))
        .and_then(|code| code.parse().ok())
        .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::InvalidData, "no status line"))?;
    Ok(Answer {
        status,
        headers: lines.map(str::to_string).collect(),
        body: body.to_string(),
    })
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
        let posted = request(address, "POST", "/metrics", &[], "").await;
        assert_eq!(posted.expect("405").status, 405);
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
