//! Shutdown as one tree: a root token, cancelled by the first SIGTERM or Ctrl-C; a child of it
//! per generation (cancelled too when the coordinator abandons that generation), which stops
//! the step in flight and its all-reduce; and every background task (heartbeats, the health
//! mirror, the servers) owned here and joined before the worker's `run` returns.
//!
//! One signal is enough: the worker stops its step, leaves the job and exits 0. A worker
//! wedged inside a step (a computation that cannot be interrupted, a stopped peer) is left
//! for it after the grace period by the signal watcher, which tells the coordinator and exits
//! 0; a second signal only cuts that wait short.

use std::future::Future;
use std::pin::Pin;
use std::sync::Mutex;
use std::time::Duration;

use tokio::runtime::Runtime;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

/// How long `join` waits for the background tasks to notice the cancellation.
const JOIN_LIMIT: Duration = Duration::from_secs(5);

/// What the signal watcher does before it exits on its own: tells the coordinator the worker
/// leaves.
pub type Farewell = Box<dyn FnOnce() -> Pin<Box<dyn Future<Output = ()> + Send>> + Send>;

/// The worker's shutdown tree and the tasks it owns.
#[derive(Default)]
pub struct Shutdown {
    root: CancellationToken,
    tasks: Mutex<Vec<JoinHandle<()>>>,
    watcher: Mutex<Option<JoinHandle<()>>>,
}

impl Shutdown {
    /// Whether shutdown was requested.
    pub fn is_cancelled(&self) -> bool {
        self.root.is_cancelled()
    }

    /// Completes once shutdown is requested.
    pub async fn cancelled(&self) {
        self.root.cancelled().await;
    }

    /// A token for one generation: cancelled with the root, or on its own when the
    /// coordinator abandons the generation.
    pub fn generation(&self) -> CancellationToken {
        self.root.child_token()
    }

    /// Runs `task` on `runtime` until it ends or shutdown is requested; [`Shutdown::join`]
    /// waits for it.
    pub fn spawn(&self, runtime: &Runtime, task: impl Future<Output = ()> + Send + 'static) {
        let root = self.root.clone();
        let handle = runtime.spawn(async move {
            tokio::select! {
                () = task => {}
                () = root.cancelled() => {}
            }
        });
        if let Ok(mut tasks) = self.tasks.lock() {
            tasks.push(handle);
        }
    }

    /// Watches for SIGTERM and Ctrl-C: the first cancels the root; if the worker has not
    /// left `grace` later (or at a second signal), the watcher runs `farewell` and exits 0.
    pub fn watch_signals(&self, runtime: &Runtime, grace: Duration, farewell: Farewell) {
        let handle = runtime.spawn(watch(self.root.clone(), grace, farewell));
        if let Ok(mut watcher) = self.watcher.lock() {
            *watcher = Some(handle);
        }
    }

    /// Ends every task this tree owns: cancels the root, waits up to [`JOIN_LIMIT`] for the
    /// tasks to return and aborts any still running, and stops the signal watcher. Nothing
    /// spawned through it outlives this call.
    pub fn join(&self, runtime: &Runtime) {
        self.root.cancel();
        if let Some(watcher) = self.watcher.lock().ok().and_then(|mut w| w.take()) {
            watcher.abort();
        }
        let tasks = self
            .tasks
            .lock()
            .map(|mut tasks| std::mem::take(&mut *tasks))
            .unwrap_or_default();
        runtime.block_on(async {
            let aborts: Vec<_> = tasks.iter().map(JoinHandle::abort_handle).collect();
            let all = async {
                for task in tasks {
                    let _ = task.await;
                }
            };
            if tokio::time::timeout(JOIN_LIMIT, all).await.is_err() {
                tracing::warn!("background tasks still running after {JOIN_LIMIT:?}; aborted");
                aborts.iter().for_each(tokio::task::AbortHandle::abort);
            }
        });
    }
}

/// The first signal, then the grace period or a second signal.
async fn watch(root: CancellationToken, grace: Duration, farewell: Farewell) {
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
        grace_s = grace.as_secs_f64(),
        "shutdown requested: stopping the step in flight and leaving the job (a signal again leaves at once)"
    );
    root.cancel();
    tokio::select! {
        () = tokio::time::sleep(grace) => tracing::warn!("still busy after the grace period; leaving now"),
        _ = terminate.recv() => tracing::warn!("second signal: leaving now"),
        () = interrupted() => tracing::warn!("second signal: leaving now"),
    }
    farewell().await;
    std::process::exit(0);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn join_ends_every_task_and_generations_end_with_the_root() {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let shutdown = Shutdown::default();
        let generation = shutdown.generation();
        let (sender, mut receiver) = tokio::sync::mpsc::unbounded_channel::<()>();
        shutdown.spawn(&runtime, async move {
            std::future::pending::<()>().await;
            drop(sender);
        });
        let deaf = runtime.spawn(std::future::pending::<()>());
        assert!(!generation.is_cancelled());
        shutdown.join(&runtime);
        assert!(generation.is_cancelled() && shutdown.is_cancelled());
        let closed = runtime.block_on(async { receiver.recv().await });
        assert_eq!(closed, None, "the owned task ended and dropped its sender");
        assert!(
            !deaf.is_finished(),
            "tasks it does not own are not its business"
        );
        deaf.abort();
    }
}
