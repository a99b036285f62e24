use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use proto::v1::coordinator_server::{Coordinator, CoordinatorServer};
use proto::v1::{
    Assignment, AwaitAssignmentRequest, CheckpointCommit, CommitAck, Finish, HeartbeatReply,
    HeartbeatRequest, JobStatus, LeaveReply, LeaveRequest, RegisterReply, RegisterRequest,
    StatusRequest, StepAck, StepReport,
};
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};
use tonic::{Request, Response, Status};

use super::{PollFailure, await_assignment, connect, poll_failure};
use crate::progress::Progress;

#[test]
fn a_cut_long_poll_is_waited_out_and_only_the_workers_own_refusals_end_it() {
    use tonic::Code;
    for code in [
        Code::Unavailable,
        Code::Unknown,
        Code::Internal,
        Code::Cancelled,
    ] {
        assert_eq!(poll_failure(code), PollFailure::CoordinatorSide, "{code:?}");
    }
    assert_eq!(poll_failure(Code::NotFound), PollFailure::NotKnown);
    for code in [
        Code::Unauthenticated,
        Code::InvalidArgument,
        Code::FailedPrecondition,
    ] {
        assert_eq!(poll_failure(code), PollFailure::Refused, "{code:?}");
    }
}

/// A coordinator whose first long poll never answers and whose later ones say the job is
/// finished.
#[derive(Default)]
struct SlowFirstPoll {
    polls: AtomicUsize,
}

#[tonic::async_trait]
impl Coordinator for SlowFirstPoll {
    async fn register(
        &self,
        _: Request<RegisterRequest>,
    ) -> Result<Response<RegisterReply>, Status> {
        Err(Status::unimplemented("not in this test"))
    }

    async fn await_assignment(
        &self,
        _: Request<AwaitAssignmentRequest>,
    ) -> Result<Response<Assignment>, Status> {
        if self.polls.fetch_add(1, Ordering::SeqCst) == 0 {
            tokio::time::sleep(Duration::from_secs(60)).await;
        }
        Ok(Response::new(Assignment {
            generation: 3,
            work: Some(proto::v1::assignment::Work::Finish(Finish {})),
        }))
    }

    async fn heartbeat(
        &self,
        _: Request<HeartbeatRequest>,
    ) -> Result<Response<HeartbeatReply>, Status> {
        Err(Status::unimplemented("not in this test"))
    }

    async fn report_step(&self, _: Request<StepReport>) -> Result<Response<StepAck>, Status> {
        Err(Status::unimplemented("not in this test"))
    }

    async fn commit_checkpoint(
        &self,
        _: Request<CheckpointCommit>,
    ) -> Result<Response<CommitAck>, Status> {
        Err(Status::unimplemented("not in this test"))
    }

    async fn status(&self, _: Request<StatusRequest>) -> Result<Response<JobStatus>, Status> {
        Err(Status::unimplemented("not in this test"))
    }

    async fn leave(&self, _: Request<LeaveRequest>) -> Result<Response<LeaveReply>, Status> {
        Err(Status::unimplemented("not in this test"))
    }
}

/// Forwards connections to `target`; the first is reset (RST) after `reset_after`.
async fn resetting_proxy(target: String, reset_after: Duration) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    tokio::spawn(async move {
        let mut first = true;
        while let Ok((mut client, _)) = listener.accept().await {
            let Ok(mut server) = TcpStream::connect(&target).await else {
                continue;
            };
            let reset = std::mem::take(&mut first);
            tokio::spawn(async move {
                if reset {
                    let forward = tokio::io::copy_bidirectional(&mut client, &mut server);
                    let _ = tokio::time::timeout(reset_after, forward).await;
                    let _ = client.set_zero_linger();
                    drop(client);
                    let _ = server.shutdown().await;
                } else {
                    let _ = tokio::io::copy_bidirectional(&mut client, &mut server).await;
                }
            });
        }
    });
    address
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_reset_during_the_long_poll_is_waited_out_and_the_worker_asks_again() {
    let service = Arc::new(SlowFirstPoll::default());
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let server_address = listener.local_addr().unwrap().to_string();
    let serving = CoordinatorServer::from_arc(service.clone());
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(serving)
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    let proxy = resetting_proxy(server_address, Duration::from_millis(500)).await;
    let mut client = connect(&format!("http://{proxy}"), "token", None)
        .await
        .unwrap();
    let progress = Progress::new();
    let assignment = tokio::time::timeout(
        Duration::from_secs(20),
        await_assignment(&mut client, &progress, 0, None),
    )
    .await
    .expect("the worker asked again after the reset")
    .expect("the reset is not the worker's fault");
    assert_eq!(assignment.generation, 3);
    assert_eq!(
        service.polls.load(Ordering::SeqCst),
        2,
        "one cut poll, one answered"
    );
}
