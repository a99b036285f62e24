//! `grpc.health.v1` on a worker's collective port: answered without the job token (Kubernetes
//! probes have none), while the Collective service beside it still demands the token.

use std::time::Duration;

use proto::v1::collective_client::CollectiveClient;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use worker::collective::{CollectiveService, Link, spawn_server};

#[tokio::test]
async fn the_collective_port_answers_health_checks_without_the_token() {
    let link = Link {
        token: "health-test".into(),
        timeout: Duration::from_secs(10),
        tls: None,
        lanes: 0,
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = format!("http://{}", listener.local_addr().unwrap());
    spawn_server(listener, CollectiveService::default(), &link).unwrap();
    let channel = tonic::transport::Endpoint::from_shared(address)
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = HealthClient::new(channel.clone());
    for service in ["", "xfactor.v1.Collective"] {
        let answer = health
            .check(HealthCheckRequest {
                service: service.to_string(),
            })
            .await
            .unwrap_or_else(|e| panic!("health of `{service}`: {e}"))
            .into_inner();
        assert_eq!(answer.status(), ServingStatus::Serving, "`{service}`");
    }
    let refused = CollectiveClient::new(channel)
        .push(tokio_stream::iter(Vec::<proto::v1::Chunk>::new()))
        .await
        .unwrap_err();
    assert_eq!(refused.code(), tonic::Code::Unauthenticated);
}
