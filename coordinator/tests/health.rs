//! `grpc.health.v1` on the coordinator, as a Kubernetes gRPC probe sees it: no job token
//! needed, SERVING while the job trains, NOT_SERVING once it is done; the Coordinator service
//! beside it still refuses calls without the token.

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
    let mut job = small_job(dir.path());
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
    let report = running.finish(Duration::from_secs(60));
    assert_eq!(report["outcome"], "finished", "{report:#}");
}
