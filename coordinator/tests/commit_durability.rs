//! A commit is recorded in `job.json` before the job's memory takes it: when that write fails,
//! the commit is refused and the job still stands where it stood, so memory and store agree.
//! Through a real gRPC connection to an in-process coordinator.

use std::time::Duration;

use coordinator::config::ClusterConfig;
use coordinator::local::free_port;
use coordinator::plan::Plan;
use coordinator::service::CoordinatorService;
use proto::v1::coordinator_client::CoordinatorClient;
use proto::v1::{
    Assignment, AwaitAssignmentRequest, CheckpointCommit, RegisterReply, RegisterRequest,
    StatusRequest, StepReport, assignment,
};
use settings::Phase;
use settings::commit::{CommitFile, CommitManifest, MANIFEST_NAME};
use tokio::sync::oneshot;

fn yaml(port: u16, checkpoints: &str) -> String {
    format!(
        "job: durability-test
listen: 127.0.0.1:{port}
auth:
  token: token
model:
  preset: tiny
data:
  generated: {{scenes: 1, trajectories: 1, frames: 6}}
workers: {{expected: 1, minimum: 1}}
stage1: {{steps: 1, global_batch: 2, micro_batch: 1, lpips_weight: 0}}
stage2: {{steps: 1, global_batch: 2, micro_batch: 1, lpips_weight: 0}}
checkpoint: {{uri: {checkpoints}, every: 1}}
"
    )
}

/// Writes a checkpoint with one file and its `COMMIT.json`, as a worker's upload leaves it.
fn write_checkpoint(dir: &std::path::Path) {
    std::fs::create_dir_all(dir).unwrap();
    let weights = b"weights".to_vec();
    std::fs::write(dir.join("model.safetensors"), &weights).unwrap();
    let manifest = CommitManifest {
        phase: Phase::Stage1,
        step: 1,
        files: vec![CommitFile {
            name: "model.safetensors".into(),
            bytes: weights.len() as u64,
            crc32: Some(crc32fast::hash(&weights)),
        }],
    };
    std::fs::write(
        dir.join(MANIFEST_NAME),
        serde_json::to_vec(&manifest).unwrap(),
    )
    .unwrap();
}

type Client = CoordinatorClient<
    tonic::service::interceptor::InterceptedService<tonic::transport::Channel, proto::AttachToken>,
>;

/// Starts a coordinator for `checkpoints` in this process; returns a client, the sender that
/// stops it and its task.
async fn start(
    checkpoints: &std::path::Path,
) -> (
    Client,
    oneshot::Sender<()>,
    tokio::task::JoinHandle<Result<coordinator::job::Report, coordinator::service::ServeError>>,
) {
    let port = free_port().unwrap();
    let config =
        ClusterConfig::from_yaml(&yaml(port, &checkpoints.display().to_string()), "test.yaml")
            .unwrap();
    let service = CoordinatorService::new(Plan::build(config).await.unwrap())
        .await
        .unwrap();
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(service.run("token", async {
        let _ = stopped.await;
    }));
    let channel = loop {
        let endpoint =
            tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{port}")).unwrap();
        match endpoint.connect().await {
            Ok(channel) => break channel,
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    };
    let client =
        CoordinatorClient::with_interceptor(channel, proto::AttachToken::new("token").unwrap());
    (client, stop, server)
}

/// Registers one worker and takes its first assignment.
async fn register_and_assign(client: &mut Client) -> (RegisterReply, Assignment) {
    let registered = client
        .register(RegisterRequest {
            protocol_version: proto::PROTOCOL_VERSION,
            model_config_version: settings::XFactorConfig::SCHEMA_VERSION,
            worker_name: "only".into(),
            collective_address: "127.0.0.1:1".into(),
            device: Some(proto::v1::Device::Cpu as i32),
            expected_model: None,
            ring_tls: false,
        })
        .await
        .unwrap()
        .into_inner();
    let assignment = client
        .await_assignment(AwaitAssignmentRequest {
            worker_id: registered.worker_id,
            after_generation: 0,
            session: registered.session.clone(),
            failure: None,
        })
        .await
        .unwrap()
        .into_inner();
    (registered, assignment)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_commit_whose_job_json_write_fails_is_refused_and_leaves_the_job_where_it_was() {
    let dir = tempfile::tempdir().unwrap();
    let (mut client, stop, server) = start(dir.path()).await;
    let (registered, assignment) = register_and_assign(&mut client).await;
    let Some(assignment::Work::Train(train)) = &assignment.work else {
        panic!("expected training work, got {assignment:?}");
    };
    let location = format!(
        "{}/step-00000001-g{}",
        train.checkpoint_prefix, assignment.generation
    );
    write_checkpoint(std::path::Path::new(&location));
    // The only rank vouches for the parameters of the step it commits.
    let report = StepReport {
        worker_id: registered.worker_id,
        generation: assignment.generation,
        phase: proto::v1::Phase::Stage1 as i32,
        step: 0,
        parameter_checksum: 7,
        checksum_computed: true,
        session: registered.session.clone(),
        ..StepReport::default()
    };
    assert!(
        client
            .report_step(report)
            .await
            .unwrap()
            .into_inner()
            .generation_current
    );
    // A directory where job.json goes: the store refuses the write.
    let state = dir.path().join("job.json");
    let _ = std::fs::remove_file(&state);
    std::fs::create_dir_all(state.join("blocked")).unwrap();

    let refused = client
        .commit_checkpoint(CheckpointCommit {
            worker_id: registered.worker_id,
            generation: assignment.generation,
            phase: proto::v1::Phase::Stage1 as i32,
            step: 1,
            location: location.clone(),
            session: registered.session.clone(),
        })
        .await
        .unwrap_err();
    assert!(
        refused.message().contains("recording the commit failed"),
        "{refused:?}"
    );
    let status = client.status(StatusRequest {}).await.unwrap().into_inner();
    assert_eq!(
        status.phase,
        proto::v1::Phase::Stage1 as i32,
        "the job did not move on to stage 2 in memory"
    );
    assert_eq!(
        status.last_commit, "",
        "memory holds no commit the store lacks"
    );

    stop.send(()).unwrap();
    server.await.unwrap().unwrap();
}
