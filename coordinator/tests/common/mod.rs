//! The harness the process tests share: a local job's coordinator and workers as real
//! processes on loopback, with helpers to wait for commits, signal processes and read reports.
#![allow(dead_code)] // each test binary compiles this module; not all of them use every helper

use std::path::{Path, PathBuf};
use std::process::Child;
use std::time::{Duration, Instant};

use coordinator::local::{LocalJob, free_port};
use serde_json::Value;
use trainer_core::flax::FlaxTensors;

pub fn binaries() -> PathBuf {
    let coordinator = PathBuf::from(env!("CARGO_BIN_EXE_xfactor-coordinator"));
    let folder = coordinator.parent().expect("binary folder").to_path_buf();
    assert!(
        folder.join("xfactor-worker").exists(),
        "xfactor-worker must be built next to xfactor-coordinator (cargo test --workspace builds both)"
    );
    folder
}

pub struct Running {
    pub job: LocalJob,
    pub coordinator: Child,
    pub workers: Vec<Child>,
}

impl Running {
    pub fn start(job: LocalJob) -> Self {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        runtime.block_on(job.prepare()).unwrap();
        let binaries = binaries();
        let coordinator = job.spawn_coordinator(&binaries).unwrap();
        let workers = (0..job.workers)
            .map(|i| job.spawn_worker(&binaries, i).unwrap())
            .collect();
        Self {
            job,
            coordinator,
            workers,
        }
    }

    pub fn logs(&self) -> String {
        let mut text = String::new();
        for entry in std::fs::read_dir(&self.job.dir).unwrap().flatten() {
            let path = entry.path();
            if path.extension().is_some_and(|e| e == "log") {
                let log = std::fs::read_to_string(&path).unwrap_or_default();
                let tail: Vec<&str> = log.lines().rev().take(25).collect();
                text.push_str(&format!("== {}\n", path.display()));
                for line in tail.into_iter().rev() {
                    text.push_str(line);
                    text.push('\n');
                }
            }
        }
        text
    }

    /// Waits for the coordinator to end and returns the report.
    pub fn finish(mut self, limit: Duration) -> Value {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.coordinator.try_wait().unwrap() {
                assert!(
                    status.success(),
                    "coordinator failed: {status}\n{}",
                    self.logs()
                );
                break;
            }
            if Instant::now() > deadline {
                let _ = self.coordinator.kill();
                panic!("the job did not finish in {limit:?}\n{}", self.logs());
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        for worker in &mut self.workers {
            let deadline = Instant::now() + Duration::from_secs(20);
            while worker.try_wait().unwrap().is_none() && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(100));
            }
            let _ = worker.kill();
        }
        serde_json::from_slice(&std::fs::read(self.job.report_path()).unwrap()).unwrap()
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.coordinator.kill();
        for worker in &mut self.workers {
            let _ = worker.kill();
        }
    }
}

pub fn small_job(dir: &Path, workers: usize) -> LocalJob {
    let mut job = LocalJob::new(dir, free_port().unwrap());
    job.workers = workers;
    job.scenes = 3;
    job.trajectories = 3;
    job.frames = 10;
    job.stage1_steps = 4;
    job.stage2_steps = 3;
    job.checkpoint_every = 2;
    job
}

pub fn commits(report: &Value, stage: u64) -> Vec<(u64, String)> {
    report["commits"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["stage"] == stage)
        .map(|c| {
            (
                c["step"].as_u64().unwrap(),
                c["location"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

pub fn load_weights(location: &str) -> FlaxTensors {
    let weights = Path::new(location).join("model.safetensors");
    trainer_core::checkpoint::load(&weights, &burn::tensor::Device::flex())
        .unwrap_or_else(|e| panic!("checkpoint {location} does not load: {e}"));
    FlaxTensors::read(&weights).unwrap()
}

pub fn signal(child: &Child, name: &str) {
    let status = std::process::Command::new("kill")
        .args([&format!("-{name}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success(), "kill -{name} failed");
}

pub fn wait_exit(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "process did not exit in {limit:?}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

pub fn wait_for_first_commit(running: &Running) {
    let marker = running.job.checkpoint_dir().join("job.json");
    let deadline = Instant::now() + Duration::from_secs(240);
    while !marker.exists() {
        assert!(Instant::now() < deadline, "no commit\n{}", running.logs());
        std::thread::sleep(Duration::from_millis(50));
    }
}

pub fn last_committed(checkpoints: &Path) -> String {
    let durable: Value =
        serde_json::from_slice(&std::fs::read(checkpoints.join("job.json")).unwrap()).unwrap();
    durable["last_commit"]["location"]
        .as_str()
        .unwrap_or_else(|| panic!("no last commit in {durable}"))
        .to_string()
}
