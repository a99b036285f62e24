//! The local run's progress line: a bar over both stages with the phase, the last loss and an
//! ETA from the pace so far. Drawn on stderr only when it is a terminal, so logs and CI output
//! stay free of carriage returns.

use std::time::Duration;

use proto::v1::JobStatus;

/// Width of the bar in characters.
const BAR_WIDTH: usize = 30;

/// One redrawable line for `status`, `elapsed` after the job started.
pub fn line(status: &JobStatus, elapsed: Duration) -> String {
    let total = status.job_steps_total.max(1);
    let done = status.job_steps_done.min(total);
    let filled = (done as usize * BAR_WIDTH) / total as usize;
    let bar: String = (0..BAR_WIDTH)
        .map(|i| if i < filled { '#' } else { '-' })
        .collect();
    let eta = if done == 0 {
        "--:--".to_string()
    } else {
        let remaining = elapsed.as_secs_f64() * (total - done) as f64 / done as f64;
        clock(remaining)
    };
    format!(
        "[{bar}] {done}/{total} {} loss={:.4} workers={} elapsed={} eta={eta}",
        proto::convert::status_label(status),
        status.last_loss,
        status.workers,
        clock(elapsed.as_secs_f64())
    )
}

fn clock(seconds: f64) -> String {
    let seconds = seconds.max(0.0).round() as u64;
    if seconds >= 3600 {
        format!(
            "{}:{:02}:{:02}",
            seconds / 3600,
            seconds / 60 % 60,
            seconds % 60
        )
    } else {
        format!("{:02}:{:02}", seconds / 60, seconds % 60)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(done: u64, total: u64) -> JobStatus {
        JobStatus {
            phase: proto::v1::Phase::Stage1 as i32,
            group_running: true,
            last_loss: 0.5,
            workers: 2,
            job_steps_done: done,
            job_steps_total: total,
            ..JobStatus::default()
        }
    }

    #[test]
    fn the_bar_fills_with_progress_and_the_eta_follows_the_pace() {
        let half = line(&status(15, 30), Duration::from_secs(40));
        assert!(
            half.starts_with(&format!(
                "[{}{}] 15/30 stage1",
                "#".repeat(15),
                "-".repeat(15)
            )),
            "{half}"
        );
        assert!(half.ends_with("elapsed=00:40 eta=00:40"), "{half}");
        let start = line(&status(0, 30), Duration::from_secs(3));
        assert!(start.ends_with("eta=--:--"), "{start}");
        let long = line(&status(1, 100), Duration::from_secs(100));
        assert!(long.ends_with("eta=2:45:00"), "{long}");
    }
}
