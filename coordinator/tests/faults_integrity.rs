//! Faults against what a job has committed and who may change it, injected into real
//! coordinator and worker processes on loopback: a newest commit whose files changed, a `COMMIT.json` naming `../x` or
//! `/etc/x`, Leave and commit requests forged in a worker's name, a replica that keeps
//! diverging (also at a commit step off the checksum interval), and rank 0 killed while its
//! checkpoint uploads. Each prints `fault=... key=value`
//! figures.

mod common;

use std::time::{Duration, Instant};

use common::proxy::ThrottledProxy;
use common::{
    Moto, Running, commits, commits_in_job_json, last_committed, signal, small_job, walk,
};
use data::store::{DataRoot, StoreError};
use proto::v1::coordinator_client::CoordinatorClient;
use proto::v1::{CheckpointCommit, LeaveRequest, StatusRequest};

/// Runs a job to its second commit, freezes it, lets `tamper` change the newest commit's
/// folder, and makes the group resume from it: the job must fall back to the commit before.
/// Returns the job's folder for what else the caller checks.
fn newest_commit_tampered_falls_back(
    fault: &str,
    tamper: impl FnOnce(&std::path::Path),
) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 40;
    let mut running = Running::start(job);
    let checkpoints = running.job.checkpoint_dir();
    let deadline = Instant::now() + Duration::from_secs(240);
    while commits_in_job_json(&checkpoints) < 2 {
        assert!(
            Instant::now() < deadline,
            "no second commit\n{}",
            running.logs()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // Freeze the group, change the newest commit, and make the group re-form so that it must
    // resume from that commit.
    for worker in &running.workers {
        signal(worker, "STOP");
    }
    let newest = last_committed(&checkpoints);
    tamper(std::path::Path::new(&newest));
    running.workers[1].kill().unwrap();
    signal(&running.workers[0], "CONT");
    let tampered = Instant::now();
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault={fault} finished_after_s={:.1} restarts={} fallbacks={}",
        tampered.elapsed().as_secs_f64(),
        report["restarts"],
        report["fallbacks"]
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(report["fallbacks"][0], newest.as_str(), "{report:#}");
    assert!(
        report["exclusions"].as_array().unwrap().len() <= 1,
        "{report:#}"
    );
    dir
}

#[test]
fn a_corrupt_newest_commit_falls_back_to_the_one_before() {
    let _ = newest_commit_tampered_falls_back("corrupt_newest_commit", |newest| {
        let weights = newest.join("model.safetensors");
        let mut bytes = std::fs::read(&weights).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0x5a;
        std::fs::write(&weights, bytes).unwrap();
    });
}

/// Renames the first file `COMMIT.json` lists to `name`, leaving everything else as it was.
fn rename_in_manifest(newest: &std::path::Path, name: &str) {
    let path = newest.join("COMMIT.json");
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    manifest["files"][0]["name"] = serde_json::json!(name);
    std::fs::write(&path, serde_json::to_vec_pretty(&manifest).unwrap()).unwrap();
}

#[test]
fn a_commit_json_naming_a_parent_folder_is_refused_and_nothing_is_written_outside() {
    let dir = newest_commit_tampered_falls_back("commit_json_parent_path", |newest| {
        // `../x` from a worker's download folder; the CRC stays that of the real file.
        rename_in_manifest(newest, "../x");
    });
    let written: Vec<_> = walk(dir.path())
        .into_iter()
        .filter(|p| p.file_name().is_some_and(|n| n == "x"))
        .collect();
    assert!(written.is_empty(), "{written:?}");
}

#[test]
fn a_commit_json_naming_an_absolute_path_is_refused() {
    let _ = newest_commit_tampered_falls_back("commit_json_absolute_path", |newest| {
        rename_in_manifest(newest, "/etc/x");
    });
    assert!(!std::path::Path::new("/etc/x").exists());
}

#[test]
fn leave_and_commit_forged_in_a_workers_name_are_refused_and_the_job_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 12;
    let port = job.port;
    let token = job.token();
    let running = Running::start(job);
    common::wait_for_first_commit(&running);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (workers_before, refused) = runtime.block_on(async {
        let channel = tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{port}"))
            .unwrap()
            .connect()
            .await
            .unwrap();
        let mut client =
            CoordinatorClient::with_interceptor(channel, proto::AttachToken::new(token).unwrap());
        let status = client.status(StatusRequest {}).await.unwrap().into_inner();
        let mut refused = Vec::new();
        // Worker ids are small numbers; try every one the job could have handed out.
        for worker_id in 1..=4 {
            for session in [String::new(), "0".repeat(32)] {
                let leave = client
                    .leave(LeaveRequest {
                        worker_id,
                        reason: "forged".into(),
                        session: session.clone(),
                    })
                    .await
                    .unwrap_err();
                let commit = client
                    .commit_checkpoint(CheckpointCommit {
                        worker_id,
                        generation: 1,
                        phase: proto::v1::Phase::Stage1 as i32,
                        step: 12,
                        location: "/etc".into(),
                        session,
                    })
                    .await
                    .unwrap_err();
                refused.push((leave.code(), commit.code()));
            }
        }
        (status.workers, refused)
    });
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=forged_leave_and_commit forged_requests={} workers_before={workers_before} restarts={}",
        2 * refused.len(),
        report["restarts"]
    );
    for (leave, commit) in refused {
        assert!(
            matches!(leave, tonic::Code::PermissionDenied | tonic::Code::NotFound),
            "{leave:?}"
        );
        assert!(
            matches!(
                commit,
                tonic::Code::PermissionDenied | tonic::Code::NotFound
            ),
            "{commit:?}"
        );
    }
    assert_eq!(workers_before, 2);
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert_eq!(
        report["restarts"], 0,
        "no forged request ended a generation: {report:#}"
    );
    assert!(
        commits(&report, 1).iter().all(|(_, l)| l != "/etc"),
        "{report:#}"
    );
}

/// Three workers, 24 steps of stage 1 committed every 4; worker `drifting`'s accelerator
/// goes bad at step `from` (counted from 0): from then on its replica drifts each step.
fn one_of_three_drifting(
    dir: &std::path::Path,
    drifting: usize,
    from: u64,
) -> coordinator::local::LocalJob {
    let mut job = small_job(dir, 3);
    job.global_batch = 6;
    job.micro_batch = 2;
    job.stage1_steps = 24;
    job.checkpoint_every = 4;
    job.worker_args = vec![Vec::new(); 3];
    job.worker_args[drifting] = vec!["--drill-diverge-from-step".into(), from.to_string()];
    job
}

#[test]
fn a_replica_that_keeps_diverging_is_rolled_back_then_excluded_and_the_job_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let job = one_of_three_drifting(dir.path(), 2, 9);
    let started = Instant::now();
    let running = Running::start(job);
    let report = running.finish(Duration::from_secs(400));
    let mismatches = report["checksum_mismatches"].as_array().unwrap();
    println!(
        "fault=replica_diverges mismatches={} restarts={} exclusions={} seconds={:.1}",
        mismatches.len(),
        report["restarts"],
        report["exclusions"].as_array().map_or(0, Vec::len),
        started.elapsed().as_secs_f64()
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(mismatches.len() >= 2, "{report:#}");
    assert!(report["restarts"].as_u64().unwrap() >= 2, "{report:#}");
    let excluded = report["exclusions"].to_string();
    assert!(excluded.contains("local-2"), "{report:#}");
    assert!(
        !excluded.contains("local-0") && !excluded.contains("local-1"),
        "{report:#}"
    );
    // Every commit holds weights every replica of its group agreed on.
    let unverified = unverified_commits(&report);
    assert!(
        unverified.is_empty(),
        "unverified: {unverified:?}\n{report:#}"
    );
    assert_eq!(commits(&report, 1).last().unwrap().0, 24, "{report:#}");
}

#[test]
fn a_divergence_at_a_commit_step_off_the_checksum_interval_is_never_committed() {
    let dir = tempfile::tempdir().unwrap();
    // Worker 0's accelerator goes bad at its 8th step (index 7), a commit step. Whichever
    // rank it has, the group's commit of step 8 would hold parameters that not every replica
    // holds.
    let mut job = one_of_three_drifting(dir.path(), 0, 7);
    // Checksums only where the commit schedule commits: without verified commits, the
    // divergence at step 8 would be committed unseen.
    job.checksum_every = Some(1000);
    let running = Running::start(job);
    let report = running.finish(Duration::from_secs(400));
    let mismatches = report["checksum_mismatches"].as_array().unwrap();
    let unverified = unverified_commits(&report);
    println!(
        "fault=diverge_at_commit_step mismatches={} restarts={} exclusions={} commits={} unverified_commits={}",
        mismatches.len(),
        report["restarts"],
        report["exclusions"],
        report["commits"].as_array().map_or(0, Vec::len),
        unverified.len()
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(!mismatches.is_empty(), "the drill fired: {report:#}");
    let excluded = report["exclusions"].to_string();
    assert!(
        !excluded.contains("local-1") && !excluded.contains("local-2"),
        "a refused commit blames no one but the odd replica: {report:#}"
    );
    assert!(
        unverified.is_empty(),
        "unverified: {unverified:?}\n{report:#}"
    );
    assert_eq!(commits(&report, 1).last().unwrap().0, 24, "{report:#}");
}

/// Every training commit whose step no full set of equal checksums covers: its record (the
/// step before, in the generation its location names) must hold one checksum per rank, all
/// equal.
fn unverified_commits(report: &serde_json::Value) -> Vec<String> {
    let steps = report["steps"].as_array().unwrap();
    report["commits"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["stage"] == 1 || c["stage"] == 2)
        .filter(|c| {
            let location = c["location"].as_str().unwrap();
            let generation: u64 = location.rsplit("-g").next().unwrap().parse().unwrap();
            let step = c["step"].as_u64().unwrap() - 1;
            !steps.iter().any(|r| {
                let checksums: Vec<&serde_json::Value> =
                    r["checksums"].as_object().unwrap().values().collect();
                r["stage"] == c["stage"]
                    && r["step"] == step
                    && r["generation"] == generation
                    && checksums.len() as u64 == r["world_size"].as_u64().unwrap()
                    && checksums.windows(2).all(|pair| pair[0] == pair[1])
            })
        })
        .map(|c| c.to_string())
        .collect()
}

/// The text of worker `index`'s log.
fn worker_log(running: &Running, index: usize) -> String {
    std::fs::read_to_string(running.job.dir.join(format!("worker-{index}.log"))).unwrap_or_default()
}

/// The value of `name=` in one log line's fields.
fn field<'a>(fields: &'a str, name: &str) -> Option<&'a str> {
    fields
        .split(&format!("{name}="))
        .nth(1)?
        .split_whitespace()
        .next()
}

/// The first checkpoint upload in `log` past byte `from` of a stage-1 step before
/// `last_step`, when rank 0 has finished a step since it began: its location and the steps
/// done since. The stage's last commit is waited for, so it never counts.
fn upload_in_flight(log: &str, from: usize, last_step: u64) -> Option<(String, usize)> {
    let tail = log.get(from..)?;
    tail.match_indices("uploading checkpoint")
        .find_map(|(offset, line)| {
            let after = &tail[offset + line.len()..];
            let fields = after.lines().next()?;
            let location = field(fields, "location")?;
            let step: u64 = field(fields, "step")?.parse().ok()?;
            let steps = after.matches("step done").count();
            (location.contains("/stage1/") && step < last_step && steps > 0)
                .then(|| (location.to_string(), steps))
        })
}

#[test]
fn rank_0_killed_while_uploading_leaves_no_commit_and_the_survivor_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let moto = Moto::start(dir.path());
    moto.create_bucket("xfactor");
    // The first commit goes through at full speed; then uploads crawl through the proxy (a
    // checkpoint is about 0.9 MB), so rank 0's next checkpoint is still on its way while it
    // trains on, however long the first upload would have taken at the slow rate.
    let proxy = ThrottledProxy::start(moto.port, 0);
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 400;
    job.checkpoint_every = 20;
    job.checkpoint_uri = Some("s3://xfactor/run/checkpoints".into());
    job.store_env = moto.env_via(&proxy.endpoint);
    let mut running = Running::start(job);
    let deadline = Instant::now() + Duration::from_secs(300);
    let (rank0, slowed_at) = running.poll(deadline, "no first commit", |running| {
        (0..2).find_map(|index| {
            let log = worker_log(running, index);
            log.contains(" committed").then_some((index, log.len()))
        })
    });
    proxy.set_rate(100_000);
    let (location, steps_while_uploading) = running.poll(
        deadline,
        "no upload in flight after the first commit",
        |running| upload_in_flight(&worker_log(running, rank0), slowed_at, 400),
    );
    running.workers[rank0].kill().unwrap();
    let killed = Instant::now();
    proxy.set_rate(0);
    let report = running.finish(Duration::from_secs(300));
    println!(
        "fault=rank0_sigkill_during_upload steps_while_uploading={steps_while_uploading} finished_after_s={:.1} restarts={}",
        killed.elapsed().as_secs_f64(),
        report["restarts"]
    );
    assert_eq!(report["outcome"], "finished", "{report:#}");
    assert!(report["restarts"].as_u64().unwrap() >= 1, "{report:#}");
    let stage1 = commits(&report, 1);
    assert_eq!(stage1.last().unwrap().0, 400, "{report:#}");
    assert!(stage1.iter().all(|(_, l)| *l != location), "{report:#}");
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let half_written = DataRoot::open_with(&location, &moto.env()).unwrap();
    let manifest = runtime.block_on(half_written.read("COMMIT.json"));
    assert!(
        matches!(manifest, Err(StoreError::NotFound { .. })),
        "{location} must have no COMMIT.json: {manifest:?}"
    );
}
