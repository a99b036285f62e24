//! Shutdown: one cancellation token, set by SIGTERM or Ctrl-C, that every part of the worker
//! watches. The training loop finishes its step and leaves; waiting for an assignment stops at
//! once; a second signal exits without waiting.

use tokio_util::sync::CancellationToken;

/// Starts watching for SIGTERM and Ctrl-C; the returned token is cancelled on the first.
pub fn on_signals(runtime: &tokio::runtime::Runtime) -> CancellationToken {
    let token = CancellationToken::new();
    runtime.spawn(watch(token.clone()));
    token
}

async fn watch(token: CancellationToken) {
    let mut terminate =
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(signal) => signal,
            Err(error) => {
                tracing::warn!(%error, "SIGTERM cannot be caught; shutdown will be abrupt");
                return;
            }
        };
    let interrupted = || async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        _ = terminate.recv() => {}
        () = interrupted() => {}
    }
    tracing::warn!(
        "shutdown requested: finishing the current step, then leaving the job (signal again to stop at once)"
    );
    token.cancel();
    tokio::select! {
        _ = terminate.recv() => {}
        () = interrupted() => {}
    }
    tracing::warn!(
        "second signal: stopping now; the last committed checkpoint stays the resume point"
    );
    std::process::exit(130);
}
