//! What probes and scrapers see of a running job: `grpc.health.v1` on the coordinator as a
//! Kubernetes gRPC probe sees it (no job token needed, SERVING while the job trains,
//! NOT_SERVING once it is done; the Coordinator service beside it still refuses calls without
//! the token), and the workers' duration histograms on `/metrics`, checked by
//! `promtool check metrics` where promtool is installed.

mod common;

use std::time::{Duration, Instant};

use common::{Running, small_job};
use proto::v1::StatusRequest;
use proto::v1::coordinator_client::CoordinatorClient;
use tonic::transport::{Channel, Endpoint};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

async fn connect(port: u16, running: &Running) -> Channel {
    let endpoint = Endpoint::from_shared(format!("http://127.0.0.1:{port}")).unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        match endpoint.connect().await {
            Ok(channel) => return channel,
            Err(error) => assert!(
                Instant::now() < deadline,
                "coordinator not listening: {error}\n{}",
                running.logs()
            ),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn check(service: &str) -> HealthCheckRequest {
    HealthCheckRequest {
        service: service.to_string(),
    }
}

#[test]
fn the_health_service_says_serving_during_training_and_not_serving_after_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 8;
    let port = job.port;
    let committed = job.checkpoint_dir().join("job.json");
    let running = Running::start(job);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        let channel = connect(port, &running).await;
        let mut health = HealthClient::new(channel.clone());
        let deadline = Instant::now() + Duration::from_secs(120);
        while !committed.exists() {
            assert!(Instant::now() < deadline, "no commit\n{}", running.logs());
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        for service in ["", "xfactor.v1.Coordinator"] {
            let answer = health.check(check(service)).await.unwrap().into_inner();
            assert_eq!(
                answer.status(),
                ServingStatus::Serving,
                "service `{service}` while training"
            );
        }
        let unknown = health.check(check("no.such.Service")).await.unwrap_err();
        assert_eq!(unknown.code(), tonic::Code::NotFound);
        let refused = CoordinatorClient::new(channel)
            .status(StatusRequest {})
            .await
            .unwrap_err();
        assert_eq!(refused.code(), tonic::Code::Unauthenticated);
        let mut watch = health.watch(check("")).await.unwrap().into_inner();
        let mut seen = Vec::new();
        let ending = Instant::now() + Duration::from_secs(180);
        while let Ok(Ok(Some(update))) =
            tokio::time::timeout_at(ending.into(), watch.message()).await
        {
            seen.push(update.status());
            if update.status() == ServingStatus::NotServing {
                break;
            }
        }
        assert_eq!(
            seen.first(),
            Some(&ServingStatus::Serving),
            "{seen:?}\n{}",
            running.logs()
        );
        assert_eq!(
            seen.last(),
            Some(&ServingStatus::NotServing),
            "{seen:?}\n{}",
            running.logs()
        );
    });
    // Closes this test's connections: an idle client that is not polled would never answer
    // the server's graceful-shutdown ping, and the coordinator would wait for it.
    drop(runtime);
    let report = running.finish(Duration::from_secs(60));
    assert_eq!(report["outcome"], "finished", "{report:#}");
}

/// The `/metrics` page on a loopback port, if it answers.
async fn page(port: u16) -> Option<String> {
    let address = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    match telemetry::http::get(address, "/metrics").await {
        Ok((200, body)) => Some(body),
        _ => None,
    }
}

/// `(series, value)` of every sample line of family `name`'s histogram (`_bucket`, `_sum`,
/// `_count`).
fn histogram_lines(text: &str, name: &str) -> Vec<(String, f64)> {
    text.lines()
        .filter(|line| line.starts_with(&format!("{name}_")))
        .filter_map(|line| line.rsplit_once(' '))
        .map(|(series, value)| (series.to_string(), value.parse().unwrap()))
        .collect()
}

/// The histogram's observation count, after checking its buckets are cumulative and its
/// `+Inf` bucket equals the count.
fn checked_count(text: &str, name: &str) -> f64 {
    let lines = histogram_lines(text, name);
    assert!(
        text.contains(&format!("# TYPE {name} histogram\n")),
        "{name} is no histogram:\n{text}"
    );
    let buckets: Vec<f64> = lines
        .iter()
        .filter(|(series, _)| series.starts_with(&format!("{name}_bucket{{")))
        .map(|(_, value)| *value)
        .collect();
    assert!(buckets.len() > 2, "{name}: {lines:?}");
    assert!(
        buckets.windows(2).all(|w| w[0] <= w[1]),
        "{name}: {lines:?}"
    );
    let count = lines
        .iter()
        .find(|(series, _)| *series == format!("{name}_count"))
        .map(|(_, value)| *value)
        .unwrap_or_else(|| panic!("{name}_count missing: {lines:?}"));
    assert_eq!(buckets.last(), Some(&count), "{name}: {lines:?}");
    count
}

/// `promtool check metrics` on `text` when promtool is installed; `None` when it is not.
fn promtool(text: &str) -> Option<(bool, String)> {
    let mut child = std::process::Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .ok()?;
    use std::io::Write;
    child.stdin.take()?.write_all(text.as_bytes()).ok()?;
    let output = child.wait_with_output().ok()?;
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    Some((output.status.success(), said))
}

#[test]
fn worker_pages_carry_duration_histograms_that_promtool_accepts() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 8;
    job.coordinator_metrics_port = Some(coordinator::local::free_port().unwrap());
    job.worker_metrics_ports = (0..2)
        .map(|_| coordinator::local::free_port().unwrap())
        .collect();
    let ports = job.worker_metrics_ports.clone();
    let coordinator_port = job.coordinator_metrics_port.unwrap();
    let committed = job.checkpoint_dir().join("job.json");
    let running = Running::start(job);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    while !committed.exists() {
        assert!(Instant::now() < deadline, "no commit\n{}", running.logs());
        std::thread::sleep(Duration::from_millis(50));
    }
    let mut pages: Vec<String> = ports
        .iter()
        .map(|&port| runtime.block_on(page(port)).expect("a worker's /metrics"))
        .collect();
    let mut uploads = 0.0;
    for text in &pages {
        for name in [
            "xfactor_step_duration_seconds",
            "xfactor_allreduce_duration_seconds",
            "xfactor_data_wait_seconds",
        ] {
            let count = checked_count(text, name);
            assert!(
                count >= 2.0,
                "{name}: {count} observations by the first commit"
            );
            eprintln!("{name}: {count} observations");
        }
        if text.contains("xfactor_checkpoint_upload_seconds_count") {
            uploads += checked_count(text, "xfactor_checkpoint_upload_seconds");
        }
    }
    assert!(
        uploads >= 1.0,
        "rank 0 observed its upload:\n{}",
        pages.join("\n")
    );
    pages.push(
        runtime
            .block_on(page(coordinator_port))
            .expect("the coordinator's /metrics"),
    );
    for text in &pages {
        match promtool(text) {
            Some((accepted, said)) => assert!(accepted, "promtool check metrics: {said}\n{text}"),
            None => eprintln!("promtool is not on PATH: `promtool check metrics` not run"),
        }
    }
    let report = running.finish(Duration::from_secs(120));
    assert_eq!(report["outcome"], "finished", "{report:#}");
}
