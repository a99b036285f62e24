//! The coordinator's refusals, through a real gRPC connection: wrong or missing token, another
//! protocol version, another model config, and requests forged in another worker's name.

use std::time::Duration;

use coordinator::config::ClusterConfig;
use coordinator::local::free_port;
use coordinator::plan::Plan;
use coordinator::service::CoordinatorService;
use proto::v1::coordinator_client::CoordinatorClient;
use proto::v1::{
    CheckpointCommit, HeartbeatRequest, LeaveRequest, RegisterReply, RegisterRequest, StatusRequest,
};
use tokio::sync::oneshot;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

/// A two-worker job on `port` whose checkpoints go to `checkpoints`.
fn yaml(port: u16, checkpoints: &str) -> String {
    format!(
        "job: rpc-test
listen: 127.0.0.1:{port}
auth:
  token: right-token
model:
  preset: tiny
data:
  generated: {{scenes: 1, trajectories: 1, frames: 6}}
stage1: {{steps: 1, global_batch: 2, micro_batch: 1, lpips_weight: 0}}
stage2: {{steps: 1, global_batch: 2, micro_batch: 1, lpips_weight: 0}}
checkpoint: {{uri: {checkpoints}, every: 1}}
"
    )
}

/// A registration; `model` (the model config as JSON) is the one the worker insists on.
fn request(protocol: u32, model: Option<&serde_json::Value>) -> RegisterRequest {
    let model = model.map(|json| {
        let config: settings::XFactorConfig = serde_json::from_value(json.clone()).unwrap();
        proto::v1::ModelConfig::from(&config)
    });
    RegisterRequest {
        protocol_version: protocol,
        model_config_version: settings::XFactorConfig::SCHEMA_VERSION,
        worker_name: "test".into(),
        collective_address: "127.0.0.1:1".into(),
        device: Some(proto::v1::Device::Cpu as i32),
        expected_model: model,
        ring_tls: false,
    }
}

/// A client that attaches a job token to every request.
type Client = CoordinatorClient<InterceptedService<Channel, proto::AttachToken>>;

/// A client presenting `token` on `channel`.
fn client_with(channel: Channel, token: &str) -> Client {
    CoordinatorClient::with_interceptor(channel, proto::AttachToken::new(token).unwrap())
}

/// A channel to `endpoint`, retried until the coordinator listens.
async fn connect(endpoint: Endpoint) -> Channel {
    loop {
        match endpoint.connect().await {
            Ok(channel) => break channel,
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_name_their_reason() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port().unwrap();
    let config =
        ClusterConfig::from_yaml(&yaml(port, &dir.path().display().to_string()), "test.yaml")
            .unwrap();
    let model = serde_json::to_value(config.model_config().unwrap()).unwrap();
    let plan = Plan::build(config).await.unwrap();
    let service = CoordinatorService::new(plan).await.unwrap();
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(service.run("right-token", async {
        let _ = stopped.await;
    }));
    let endpoint = Endpoint::from_shared(format!("http://127.0.0.1:{port}")).unwrap();
    let channel = connect(endpoint).await;

    token_refusals(&channel).await;
    let mut client = client_with(channel, "right-token");
    registration_refusals(&mut client, &model).await;

    let accepted = client
        .register(request(proto::PROTOCOL_VERSION, Some(&model)))
        .await
        .unwrap()
        .into_inner();
    assert!(accepted.worker_id > 0);
    assert_eq!(accepted.session.len(), 32, "128 random bits as hex");
    let status = client.status(StatusRequest {}).await.unwrap().into_inner();
    assert_eq!(status.job_name, "rpc-test");
    assert_eq!(status.workers, 1);

    forged_requests_refused(&mut client, &accepted).await;
    devices_reported_and_listed(&mut client, &accepted).await;

    stop.send(()).unwrap();
    server.await.unwrap().unwrap();
}

/// A request without the job token, or with a guessed one, is refused as unauthenticated
/// before any handler sees it.
async fn token_refusals(channel: &Channel) {
    let mut anonymous = CoordinatorClient::new(channel.clone());
    let missing = anonymous.status(StatusRequest {}).await.unwrap_err();
    assert_eq!(missing.code(), tonic::Code::Unauthenticated);
    assert!(
        missing.message().contains("missing job token"),
        "{missing:?}"
    );

    let mut wrong = client_with(channel.clone(), "guessed");
    let refused = wrong
        .register(request(proto::PROTOCOL_VERSION, None))
        .await
        .unwrap_err();
    assert_eq!(refused.code(), tonic::Code::Unauthenticated);
    assert!(refused.message().contains("wrong job token"));
}

/// A worker speaking another protocol version, or insisting on another model than the job's
/// (`model`, as JSON), is refused naming the difference.
async fn registration_refusals(client: &mut Client, model: &serde_json::Value) {
    let protocol = client
        .register(request(proto::PROTOCOL_VERSION + 1, None))
        .await
        .unwrap_err();
    assert_eq!(protocol.code(), tonic::Code::FailedPrecondition);
    assert!(
        protocol
            .message()
            .contains(&format!("protocol version {}", proto::PROTOCOL_VERSION + 1)),
        "{protocol:?}"
    );

    let mut other = model.clone();
    other["width"] = serde_json::json!(64);
    let differs = client
        .register(request(proto::PROTOCOL_VERSION, Some(&other)))
        .await
        .unwrap_err();
    assert_eq!(differs.code(), tonic::Code::FailedPrecondition);
    assert!(
        differs.message().contains("width: job 32 vs worker 64"),
        "{differs:?}"
    );

    let ring_tls = RegisterRequest {
        ring_tls: true,
        ..request(proto::PROTOCOL_VERSION, None)
    };
    let mixed = client.register(ring_tls).await.unwrap_err();
    assert_eq!(mixed.code(), tonic::Code::FailedPrecondition);
    assert!(mixed.message().contains("without TLS"), "{mixed:?}");
}

/// A second registration holds the job token but not the `accepted` worker's session: it can
/// neither make the first leave nor commit in its name. It then leaves in its own name.
async fn forged_requests_refused(client: &mut Client, accepted: &RegisterReply) {
    let intruder = client
        .register(request(proto::PROTOCOL_VERSION, None))
        .await
        .unwrap()
        .into_inner();
    let forged_leave = client
        .leave(LeaveRequest {
            worker_id: accepted.worker_id,
            reason: "forged".into(),
            session: intruder.session.clone(),
        })
        .await
        .unwrap_err();
    assert_eq!(forged_leave.code(), tonic::Code::PermissionDenied);
    assert!(
        forged_leave.message().contains("session secret"),
        "{forged_leave:?}"
    );
    let forged_commit = client
        .commit_checkpoint(CheckpointCommit {
            worker_id: accepted.worker_id,
            generation: 1,
            phase: proto::v1::Phase::Stage1 as i32,
            step: 1,
            location: "/etc".into(),
            session: String::new(),
        })
        .await
        .unwrap_err();
    assert_eq!(forged_commit.code(), tonic::Code::PermissionDenied);
    let status = client.status(StatusRequest {}).await.unwrap().into_inner();
    assert_eq!(status.workers, 2, "no forged request removed a worker");
    client
        .leave(LeaveRequest {
            worker_id: intruder.worker_id,
            reason: "done".into(),
            session: intruder.session,
        })
        .await
        .unwrap();
}

/// A worker's heartbeat names the device it trains on and `status` lists it beside the
/// worker; a device reported as `auto` (never resolved) is refused naming the field.
async fn devices_reported_and_listed(client: &mut Client, accepted: &RegisterReply) {
    let heartbeat = |device: proto::v1::DeviceInUse| HeartbeatRequest {
        worker_id: accepted.worker_id,
        generation: 0,
        step: 0,
        activity: proto::v1::Activity::Idle as i32,
        session: accepted.session.clone(),
        device: Some(device),
    };
    let h100 = proto::v1::DeviceInUse {
        backend: proto::v1::Device::Vulkan as i32,
        name: "NVIDIA H100 80GB HBM3 (Vulkan)".into(),
        replicas: 4,
    };
    client.heartbeat(heartbeat(h100.clone())).await.unwrap();
    let status = client.status(StatusRequest {}).await.unwrap().into_inner();
    let listed = status
        .worker_list
        .iter()
        .find(|worker| worker.worker_id == accepted.worker_id)
        .expect("the worker is listed");
    assert_eq!(listed.device.as_ref(), Some(&h100));
    assert_eq!(
        proto::convert::worker_line(listed),
        format!(
            "worker={} name=\"test\" backend=vulkan device=\"NVIDIA H100 80GB HBM3 (Vulkan)\" \
             replicas=4 pairs_per_s=0.00",
            accepted.worker_id
        )
    );
    let unresolved = proto::v1::DeviceInUse {
        backend: proto::v1::Device::Auto as i32,
        ..h100
    };
    let refused = client.heartbeat(heartbeat(unresolved)).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::InvalidArgument);
    assert!(
        refused.message().contains("heartbeat.device"),
        "{refused:?}"
    );
}

/// The folder of the test CA, server certificate and keys.
fn test_certificates() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../proto/testdata/tls")
}

/// A coordinator whose YAML names the test certificate and `key` (a file of the test folder).
async fn tls_coordinator(
    port: u16,
    checkpoints: &std::path::Path,
    key: &str,
) -> CoordinatorService {
    let certificates = test_certificates();
    let text = format!(
        "{}tls:\n  cert: {}\n  key: {}\n",
        yaml(port, &checkpoints.display().to_string()),
        certificates.join("server.pem").display(),
        certificates.join(key).display()
    );
    let config = ClusterConfig::from_yaml(&text, "tls.yaml").unwrap();
    let plan = Plan::build(config).await.unwrap();
    CoordinatorService::new(plan).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_round_trip_with_a_test_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port().unwrap();
    let certificates = test_certificates();
    let service = tls_coordinator(port, dir.path(), "server.key").await;
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(service.run("right-token", async {
        let _ = stopped.await;
    }));
    let tls = proto::tls::client_config(&certificates.join("ca.pem"), "localhost").unwrap();
    let endpoint = Endpoint::from_shared(format!("https://127.0.0.1:{port}"))
        .unwrap()
        .tls_config(tls)
        .unwrap();
    let channel = connect(endpoint).await;
    let mut client = client_with(channel.clone(), "right-token");
    let status = client.status(StatusRequest {}).await.unwrap().into_inner();
    assert_eq!(status.job_name, "rpc-test");
    let lanes_only = client
        .register(request(proto::PROTOCOL_VERSION, None))
        .await
        .unwrap_err();
    assert_eq!(lanes_only.code(), tonic::Code::FailedPrecondition);
    assert!(
        lanes_only.message().contains("--tls-cert and --tls-key"),
        "{lanes_only:?}"
    );
    let with_certificate = RegisterRequest {
        ring_tls: true,
        ..request(proto::PROTOCOL_VERSION, None)
    };
    client.register(with_certificate).await.unwrap();
    let mut wrong = client_with(channel, "guessed");
    let refused = wrong.status(StatusRequest {}).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::Unauthenticated);

    let plain = Endpoint::from_shared(format!("http://127.0.0.1:{port}"))
        .unwrap()
        .connect()
        .await;
    if let Ok(channel) = plain {
        let mut client = client_with(channel, "right-token");
        assert!(
            client.status(StatusRequest {}).await.is_err(),
            "plain text reached a TLS coordinator"
        );
    }
    let _ = stop.send(());
    server.await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tls_key_that_is_not_a_key_is_named_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let service = tls_coordinator(free_port().unwrap(), dir.path(), "ca.pem").await;
    let error = service
        .run("right-token", std::future::pending())
        .await
        .unwrap_err();
    assert!(error.to_string().contains("ca.pem"), "{error}");
}
