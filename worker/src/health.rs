//! `grpc.health.v1` on the worker's collective port, for Kubernetes gRPC probes: SERVING for
//! the server as a whole (`""`) and for `xfactor.v1.Collective` while the server runs, and
//! NOT_SERVING for `""` while the coordinator has removed this worker (silent, or stuck in its
//! step while its peers waited), so a liveness probe restarts a stuck worker. Served outside
//! the job-token check, since probes carry no token; it reveals nothing but that.

use std::sync::Arc;
use std::time::Duration;

use tonic_health::ServingStatus;
use tonic_health::server::HealthReporter;

use crate::progress::Progress;

/// Keeps the server's overall status in step with [`Progress::health`], checked every
/// `interval` (the heartbeat's, which is what can change it).
pub async fn mirror_membership(
    reporter: HealthReporter,
    progress: Arc<Progress>,
    interval: Duration,
) {
    let check = Progress::health(&progress);
    let mut serving = true;
    loop {
        tokio::time::sleep(interval).await;
        let healthy = check().is_ok();
        if healthy != serving {
            let status = if healthy {
                ServingStatus::Serving
            } else {
                ServingStatus::NotServing
            };
            reporter.set_service_status("", status).await;
            serving = healthy;
        }
    }
}
