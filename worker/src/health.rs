//! `grpc.health.v1` on the worker's collective port, for Kubernetes gRPC probes: SERVING for
//! the server as a whole (`""`) and for `xfactor.v1.Collective` while the server runs. Served
//! outside the job-token check, since probes carry no token; it reveals nothing but that.

use proto::v1::collective_server::CollectiveServer;
use tonic_health::pb::health_server::{Health, HealthServer};

use crate::collective::CollectiveService;

/// The health service of a collective server that is up.
pub async fn collective_health() -> HealthServer<impl Health> {
    let (reporter, server) = tonic_health::server::health_reporter();
    reporter
        .set_serving::<CollectiveServer<CollectiveService>>()
        .await;
    server
}
