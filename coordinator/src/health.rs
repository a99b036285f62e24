//! `grpc.health.v1` for the coordinator: Kubernetes gRPC probes and load balancers ask it
//! whether the job is running. The health service is served beside the Coordinator service but
//! outside the job-token check (a probe has no token), and it answers only that status.

use tonic_health::ServingStatus;
use tonic_health::pb::health_server::{Health, HealthServer};
use tonic_health::server::HealthReporter;

/// The service name probes may ask about besides the server as a whole (`""`). It is the
/// protocol's name for the Coordinator service, whichever type implements it, so health
/// reporting needs nothing of the service module.
pub const COORDINATOR_SERVICE: &str = proto::v1::coordinator_server::SERVICE_NAME;

/// What the health service says about the job.
#[derive(Clone)]
pub struct JobHealth {
    reporter: HealthReporter,
}

impl JobHealth {
    /// A reporter and the service it feeds, both saying SERVING until told otherwise.
    pub async fn new() -> (Self, HealthServer<impl Health>) {
        let (reporter, server) = tonic_health::server::health_reporter();
        let health = Self { reporter };
        health.set(ServingStatus::Serving).await;
        (health, server)
    }

    /// The job is finished or stopping: probes see NOT_SERVING from now on.
    pub async fn job_ending(&self) {
        self.set(ServingStatus::NotServing).await;
    }

    /// Ends open `Watch` streams (the server's graceful shutdown waits for open streams).
    pub async fn close(mut self) {
        for name in ["", COORDINATOR_SERVICE] {
            self.reporter.clear_service_status(name).await;
        }
    }

    /// Says `status` for the server as a whole and for the Coordinator service alike.
    async fn set(&self, status: ServingStatus) {
        for name in ["", COORDINATOR_SERVICE] {
            self.reporter.set_service_status(name, status).await;
        }
    }
}
