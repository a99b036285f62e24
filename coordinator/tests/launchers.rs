//! What users of other launchers complain about most, each as a process test: workers that
//! never register (a Slurm worker derives the coordinator's address from the job's node list
//! and waits for it to come up), signals that are not forwarded (SIGUSR1, Slurm's warning
//! before the time limit, suspends the job after a commit of the step in progress, and every
//! process exits), and requeued jobs that start from zero (the rerun resumes from that commit).
//! `scripts/test-slurm.sh` runs the same through a real Slurm.

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{Running, binaries, signal, small_job, wait_exit};
use serde_json::Value;

/// A worker process launched as Slurm's task `task` of job 77: no `--coordinator`, no
/// `--name`, `scontrol` (a stand-in on PATH) expanding the node list to loopback.
fn slurm_worker(dir: &Path, port: u16, task: usize, token: &str) -> Child {
    let bin = dir.join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    let scontrol = bin.join("scontrol");
    std::fs::write(
        &scontrol,
        "#!/bin/sh\n[ \"$1 $2\" = \"show hostnames\" ] && echo 127.0.0.1\n",
    )
    .unwrap();
    Command::new("chmod")
        .arg("+x")
        .arg(&scontrol)
        .status()
        .unwrap();
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let log = std::fs::File::create(dir.join(format!("worker-{task}.log"))).unwrap();
    Command::new(binaries().join("xfactor-worker"))
        .args(["--token", token, "--scratch"])
        .arg(dir.join(format!("scratch-{task}")))
        .env("PATH", path)
        .env("SLURM_JOB_ID", "77")
        .env("SLURM_PROCID", task.to_string())
        .env("SLURM_NTASKS", "2")
        .env("SLURM_JOB_NODELIST", "node[1-2]")
        .env("SLURMD_NODENAME", "127.0.0.1")
        .env("XFACTOR_COORDINATOR_PORT", port.to_string())
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap()
}

#[test]
fn slurm_workers_started_before_the_coordinator_find_it_and_register() {
    let dir = tempfile::tempdir().unwrap();
    let job = small_job(dir.path(), 2);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(job.prepare()).unwrap();
    let workers: Vec<Child> = (0..2)
        .map(|task| slurm_worker(dir.path(), job.port, task, job.token()))
        .collect();
    // srun starts the workers while the batch step is still starting the coordinator.
    std::thread::sleep(Duration::from_secs(2));
    let coordinator = job.spawn_coordinator(&binaries()).unwrap();
    let running = Running {
        job,
        coordinator,
        workers,
    };
    let logs_dir = running.job.dir.clone();
    let report = running.finish(Duration::from_secs(240));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let log = std::fs::read_to_string(logs_dir.join("coordinator.log")).unwrap();
    for name in ["slurm-77-0", "slurm-77-1"] {
        assert!(log.contains(name), "{name} never registered:\n{log}");
    }
}

/// Lines of the step history written so far.
fn history_lines(checkpoints: &Path) -> usize {
    std::fs::read_to_string(checkpoints.join("history/steps-000000.jsonl"))
        .map_or(0, |text| text.lines().count())
}

#[test]
fn sigusr1_suspends_after_a_commit_and_the_rerun_resumes_from_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut job = small_job(dir.path(), 2);
    job.stage1_steps = 400;
    job.checkpoint_every = 1000;
    let checkpoints = job.checkpoint_dir();
    let mut running = Running::start(job.clone());
    let deadline = Instant::now() + Duration::from_secs(120);
    while history_lines(&checkpoints) < 5 {
        assert!(Instant::now() < deadline, "no steps\n{}", running.logs());
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(
        !checkpoints.join("job.json").exists(),
        "no commit is due before step 400"
    );
    signal(&running.coordinator, "USR1");
    let status = wait_exit(&mut running.coordinator, Duration::from_secs(60));
    assert_eq!(status.code(), Some(75), "suspended\n{}", running.logs());
    for worker in &mut running.workers {
        let status = wait_exit(worker, Duration::from_secs(30));
        assert!(status.success(), "worker exit {status}\n{}", running.logs());
    }
    let durable: Value =
        serde_json::from_slice(&std::fs::read(checkpoints.join("job.json")).unwrap()).unwrap();
    let suspended_at = durable["last_commit"]["step"].as_u64().unwrap();
    assert!(
        (5..400).contains(&suspended_at),
        "committed at {suspended_at}: {durable:#}"
    );
    drop(running);

    let report = Running::start(job).finish(Duration::from_secs(300));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let first = &report["generations"][0];
    assert_eq!(first["stage"], 1, "{report:#}");
    assert!(
        first["resume_from"]
            .as_str()
            .unwrap()
            .contains(&format!("step-{suspended_at:08}")),
        "the rerun did not resume from the suspension's commit: {report:#}"
    );
    // The report holds the whole job (the first run's steps are read back from the store's
    // history); the rerun's own generation starts at the suspension's commit.
    let steps_of = |generation: &Value| -> Vec<u64> {
        report["steps"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|r| r["stage"] == 1 && r["generation"] == *generation)
            .map(|r| r["step"].as_u64().unwrap())
            .collect()
    };
    let rerun = steps_of(&first["generation"]);
    assert_eq!(
        rerun.first().copied(),
        Some(suspended_at),
        "the rerun started at step {:?}",
        rerun.first()
    );
    let all_stage1 = report["steps"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["stage"] == 1)
        .map(|r| r["step"].as_u64().unwrap())
        .min();
    assert_eq!(all_stage1, Some(0), "the first run's history is kept");
}
