//! The status page on a real job (coordinator and two workers as processes on loopback): it
//! shows nothing without the job token, shows the job and its workers with it, and shows the
//! fault after a worker is killed.

mod common;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use common::{Running, small_job};
use coordinator::job::snapshot::StatusSnapshot;
use coordinator::local::free_port;
use telemetry::http::{Answer, request};

fn ask(port: u16, method: &str, path: &str, headers: &[(&str, &str)], body: &str) -> Answer {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let address = SocketAddr::from(([127, 0, 0, 1], port));
    runtime
        .block_on(request(address, method, path, headers, body))
        .unwrap_or_else(|e| panic!("{method} {path}: {e}"))
}

/// The snapshot `/api/status` serves to the token's bearer, once it satisfies `wanted`.
fn wait_for(
    running: &Running,
    port: u16,
    what: &str,
    wanted: impl Fn(&StatusSnapshot) -> bool,
) -> StatusSnapshot {
    let bearer = format!("Bearer {}", running.job.token());
    let deadline = Instant::now() + Duration::from_secs(180);
    loop {
        assert!(
            Instant::now() < deadline,
            "never {what}\n{}",
            running.logs()
        );
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let address = SocketAddr::from(([127, 0, 0, 1], port));
        let answer = runtime.block_on(request(
            address,
            "GET",
            "/api/status",
            &[("Authorization", &bearer)],
            "",
        ));
        if let Ok(answer) = answer
            && answer.status == 200
            && let Ok(snapshot) = serde_json::from_str::<StatusSnapshot>(&answer.body)
            && wanted(&snapshot)
        {
            return snapshot;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// `xfactor-coordinator status --page` prints the snapshot the page draws, and is refused
/// without the token.
fn status_command_reads_the_page(port: u16, token: &str) {
    let binary = env!("CARGO_BIN_EXE_xfactor-coordinator");
    let page_address = format!("127.0.0.1:{port}");
    let printed = std::process::Command::new(binary)
        .args(["status", "--page", &page_address, "--token", token])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&printed.stdout);
    assert!(printed.status.success(), "{text}");
    assert!(
        text.starts_with("job=") && text.contains("phase=stage1"),
        "{text}"
    );
    assert_eq!(text.lines().filter(|l| l.starts_with("worker=")).count(), 2);
    let refused = std::process::Command::new(binary)
        .args(["status", "--page", &page_address, "--token", "guess"])
        .output()
        .unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("401"));
}

/// The YAML's read-only viewing token opens the page too, as a bearer and at the sign-in form.
fn the_viewing_token_opens_the_page(port: u16) {
    let viewer = [("Authorization", "Bearer viewer-of-this-job")];
    assert_eq!(ask(port, "GET", "/api/status", &viewer, "").status, 200);
    let viewer_login = ask(
        port,
        "POST",
        "/login",
        &[("Content-Type", "application/x-www-form-urlencoded")],
        "token=viewer-of-this-job",
    );
    assert_eq!(viewer_login.status, 303, "{viewer_login:?}");
}

#[test]
fn the_status_page_shows_the_job_to_its_token_and_a_killed_worker_as_a_fault() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.minimum = 1;
    job.stage1_steps = 300;
    job.checkpoint_every = 20;
    let port = free_port().unwrap();
    job.coordinator_metrics_port = Some(port);
    job.viewing_token = Some("viewer-of-this-job".into());
    let mut running = Running::start(job);

    let training = wait_for(&running, port, "training on two workers", |s| {
        s.step >= 3 && s.workers.len() == 2 && s.state == "running"
    });
    assert_eq!(training.phase, "stage1");
    assert!(training.eta_s.is_some_and(|eta| eta > 0.0), "{training:?}");

    // Nothing of the job without the token.
    let refused = ask(port, "GET", "/", &[], "");
    assert_eq!(refused.status, 401);
    assert!(refused.body.contains("Job token"), "{}", refused.body);
    assert!(!refused.body.contains(&training.workers[0].name));
    assert_eq!(ask(port, "GET", "/api/status", &[], "").status, 401);
    let wrong = ask(
        port,
        "POST",
        "/login",
        &[("Content-Type", "application/x-www-form-urlencoded")],
        "token=guess",
    );
    assert_eq!(wrong.status, 401);
    assert!(wrong.header("Set-Cookie").is_none());

    // The token buys a session cookie that shows the page.
    let signed_in = ask(
        port,
        "POST",
        "/login",
        &[("Content-Type", "application/x-www-form-urlencoded")],
        &format!("token={}", running.job.token()),
    );
    assert_eq!(signed_in.status, 303, "{signed_in:?}");
    let cookie = signed_in.header("Set-Cookie").expect("a session cookie");
    assert!(
        !cookie.contains(running.job.token()),
        "the cookie is not the token"
    );
    let cookie = cookie.split(';').next().unwrap().to_string();
    let page = ask(port, "GET", "/", &[("Cookie", &cookie)], "");
    assert_eq!(page.status, 200);
    the_viewing_token_opens_the_page(port);
    for worker in &training.workers {
        assert!(page.body.contains(&worker.name), "{}", page.body);
    }
    assert!(page.body.contains("<svg"), "the loss curve");

    status_command_reads_the_page(port, running.job.token());

    running.workers[1].kill().unwrap();
    let faulted = wait_for(&running, port, "the killed worker shown as lost", |s| {
        s.workers.iter().any(|w| w.state == "lost")
            && s.timeline.iter().any(|e| e.event.starts_with("ended"))
    });
    let page = ask(port, "GET", "/", &[("Cookie", &cookie)], "");
    assert!(page.body.contains("lost"), "{}", page.body);
    assert!(page.body.contains("ended at step"), "{}", page.body);
    assert!(
        faulted.generation >= 2 || faulted.state != "running",
        "{faulted:?}"
    );
    let report = running.finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
}
