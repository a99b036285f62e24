//! Watching a local job's processes. On a cluster a worker that dies is restarted by its host's
//! supervisor and the coordinator waits for it; here `xfactor-local` is that supervisor, so a
//! worker that fails while the coordinator runs ends the job with the worker's reason instead
//! of leaving the coordinator waiting for a worker that will never come back.

use std::process::{Child, ExitStatus};
use std::time::Duration;

/// How a local job's processes ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ended {
    /// The coordinator exited (the job finished or failed on its own terms).
    Coordinator(ExitStatus),
    /// Worker `index` failed while the coordinator still ran.
    WorkerFailed {
        /// The worker's index (`worker-<index>.log`).
        index: usize,
        /// How it exited.
        status: ExitStatus,
    },
}

/// Waits until the coordinator exits or a worker fails, checking every `poll`. A worker that
/// exits successfully is left alone: the coordinator tells it when the job is over.
pub fn watch(
    coordinator: &mut Child,
    workers: &mut [Child],
    poll: Duration,
) -> std::io::Result<Ended> {
    let mut finished = vec![false; workers.len()];
    loop {
        if let Some(status) = coordinator.try_wait()? {
            return Ok(Ended::Coordinator(status));
        }
        for (index, worker) in workers.iter_mut().enumerate() {
            if finished[index] {
                continue;
            }
            if let Some(status) = worker.try_wait()? {
                if !status.success() {
                    return Ok(Ended::WorkerFailed { index, status });
                }
                finished[index] = true;
            }
        }
        std::thread::sleep(poll);
    }
}

/// Why a process stopped, read from its log: its panic's place and message, else its last
/// `Error:` (without the prefix) or `ERROR` line, else its last line.
pub fn failure_reason(log: &str) -> Option<String> {
    let lines: Vec<&str> = log.lines().map(str::trim).collect();
    if let Some(at) = lines.iter().position(|line| line.contains(" panicked at ")) {
        let place = lines[at].split(" panicked at ").nth(1).unwrap_or_default();
        let message: Vec<&str> = lines[at + 1..]
            .iter()
            .take_while(|line| !line.is_empty() && !line.starts_with("stack backtrace"))
            .take(4)
            .copied()
            .collect();
        return Some(format!("panicked at {place} {}", message.join(" ")));
    }
    let error = lines
        .iter()
        .rev()
        .find(|line| line.starts_with("Error:") || line.contains(" ERROR "));
    error
        .or_else(|| lines.iter().rev().find(|line| !line.is_empty()))
        .map(|line| line.strip_prefix("Error: ").unwrap_or(line).to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_is_named_by_its_place_and_message() {
        let log = "2026-11-27T14:55:39Z  INFO worker: joined\n\
            thread '<unnamed>' (2326) panicked at src/tensor/api/base.rs:2701:9:\n\
            === Tensor Operation Error ===\n  Operation: 'Narrow'\n\n\
            stack backtrace:\n   0: rust_begin_unwind\n";
        assert_eq!(
            failure_reason(log).unwrap(),
            "panicked at src/tensor/api/base.rs:2701:9: === Tensor Operation Error === \
             Operation: 'Narrow'"
        );
    }

    #[test]
    fn without_a_panic_the_last_error_then_the_last_line() {
        let log = "x  ERROR worker: first\nError: the device cuda is not built in\n\nlater\n";
        assert_eq!(
            failure_reason(log).unwrap(),
            "the device cuda is not built in"
        );
        assert_eq!(failure_reason("one\ntwo\n\n").unwrap(), "two");
        assert_eq!(failure_reason(""), None);
    }

    #[test]
    fn a_failed_worker_ends_the_watch_and_a_finished_one_does_not() {
        let spawn = |script: &str| {
            std::process::Command::new("sh")
                .args(["-c", script])
                .spawn()
                .unwrap()
        };
        let mut coordinator = spawn("sleep 30");
        let mut workers = vec![spawn("exit 0"), spawn("sleep 0.3; exit 3")];
        let ended = watch(&mut coordinator, &mut workers, Duration::from_millis(20)).unwrap();
        coordinator.kill().unwrap();
        coordinator.wait().unwrap();
        match ended {
            Ended::WorkerFailed { index, status } => {
                assert_eq!((index, status.code()), (1, Some(3)));
            }
            other => panic!("expected worker 1's failure, got {other:?}"),
        }
        let mut coordinator = spawn("exit 0");
        let ended = watch(&mut coordinator, &mut [], Duration::from_millis(20)).unwrap();
        assert!(matches!(ended, Ended::Coordinator(status) if status.success()));
    }
}
