//! The harness the process tests share: a local job's coordinator and workers as real
//! processes on loopback, helpers to wait for commits, signal processes and read reports, and
//! moto's S3 server on loopback for the S3 tests.
#![allow(dead_code)] // each test binary compiles this module; not all of them use every helper

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub mod proxy;

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

    /// Waits until the coordinator's log shows `text` `count` times.
    pub fn wait_for_log(&self, text: &str, count: usize, limit: Duration) {
        let log = self.job.dir.join("coordinator.log");
        let what = format!("never logged `{text}`");
        self.poll(Instant::now() + limit, &what, |_| {
            let logged = std::fs::read_to_string(&log).unwrap_or_default();
            (logged.matches(text).count() >= count).then_some(())
        });
    }

    /// Calls `found` every 20 ms until it gives a value; fails with `what` and the logs at
    /// `deadline`.
    pub fn poll<T>(&self, deadline: Instant, what: &str, found: impl Fn(&Self) -> Option<T>) -> T {
        loop {
            if let Some(value) = found(self) {
                return value;
            }
            assert!(Instant::now() < deadline, "{what}\n{}", self.logs());
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// What `xfactor-coordinator status` prints for the running job.
    pub fn status_line(&self) -> String {
        let output = std::process::Command::new(binaries().join("xfactor-coordinator"))
            .args(["status", "--address"])
            .arg(format!("http://127.0.0.1:{}", self.job.port))
            .args(["--token", self.job.token()])
            .output()
            .unwrap();
        assert!(
            output.status.success(),
            "status failed: {}",
            String::from_utf8_lossy(&output.stderr)
        );
        String::from_utf8_lossy(&output.stdout).into_owned()
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

/// A two-worker job whose stage 1 has one commit, its final one, under a store location that
/// refuses every write: a file stands where the stage's checkpoint folder goes. Removing the
/// returned file mends the store.
pub fn job_whose_stage1_store_refuses_writes(dir: &Path) -> (LocalJob, PathBuf) {
    let mut job = small_job(dir, 2);
    job.stage1_steps = 2;
    job.checkpoint_every = 2;
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(job.prepare()).unwrap();
    let blocker = job.checkpoint_dir().join("stage1");
    std::fs::create_dir_all(job.checkpoint_dir()).unwrap();
    std::fs::write(&blocker, b"not a directory").unwrap();
    (job, blocker)
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

/// moto's S3 server as a child process on a loopback port, killed on drop.
pub struct Moto {
    child: Child,
    /// `http://127.0.0.1:PORT`.
    pub endpoint: String,
    /// Its loopback port.
    pub port: u16,
    log: PathBuf,
}

/// How long moto may take to answer after starting (it imports Flask and boto; about 2 s on
/// the 2-core CI machine).
const MOTO_START_LIMIT: Duration = Duration::from_secs(60);

impl Moto {
    /// Where `scripts/setup.sh` installs `moto_server`, or `$XFACTOR_MOTO_SERVER`.
    pub fn program() -> PathBuf {
        if let Some(program) = std::env::var_os("XFACTOR_MOTO_SERVER") {
            return PathBuf::from(program);
        }
        settings::cache::project_cache().join("s3-env/bin/moto_server")
    }

    /// Starts the server (its log goes to `dir/moto.log`) and waits until it answers. Panics,
    /// failing the test, when it cannot be started: these tests must not pass by skipping.
    pub fn start(dir: &Path) -> Self {
        let program = Self::program();
        let port = free_port().unwrap();
        let log = dir.join("moto.log");
        let child = Command::new(&program)
            .args(["-H", "127.0.0.1", "-p", &port.to_string()])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot start moto's S3 server `{}`: {e}; run scripts/setup.sh, which installs moto[server] there (or set XFACTOR_MOTO_SERVER)",
                    program.display()
                )
            });
        let mut moto = Self {
            child,
            endpoint: format!("http://127.0.0.1:{port}"),
            port,
            log,
        };
        let started = Instant::now();
        loop {
            if let Some(status) = moto.child.try_wait().unwrap() {
                panic!(
                    "moto's S3 server exited at start ({status}):\n{}",
                    std::fs::read_to_string(&moto.log).unwrap_or_default()
                );
            }
            if moto.request("GET", "/").is_ok_and(|s| s == 200) {
                break;
            }
            assert!(
                started.elapsed() < MOTO_START_LIMIT,
                "moto's S3 server did not answer on {} within {MOTO_START_LIMIT:?}:\n{}",
                moto.endpoint,
                std::fs::read_to_string(&moto.log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        eprintln!(
            "moto S3 server answering on {} after {:.2} s",
            moto.endpoint,
            started.elapsed().as_secs_f64()
        );
        moto
    }

    /// One bodiless HTTP/1.1 request; the response's status code.
    fn request(&self, method: &str, path: &str) -> std::io::Result<u16> {
        let mut stream = TcpStream::connect(("127.0.0.1", self.port))?;
        stream.set_read_timeout(Some(Duration::from_secs(10)))?;
        write!(
            stream,
            "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
            self.port
        )?;
        let mut response = String::new();
        stream.read_to_string(&mut response)?;
        response
            .split_whitespace()
            .nth(1)
            .and_then(|code| code.parse().ok())
            .ok_or_else(|| std::io::Error::other(format!("not an HTTP response: {response:.80}")))
    }

    /// Creates bucket `name` (object_store cannot create buckets).
    /// Sends the server signal `name` (`STOP` freezes it: connections open and requests hang
    /// unanswered, as with a store that is unreachable; `CONT` brings it back, data intact).
    pub fn signal(&self, name: &str) {
        signal(&self.child, name);
    }

    pub fn create_bucket(&self, name: &str) {
        let status = self.request("PUT", &format!("/{name}")).unwrap();
        assert_eq!(status, 200, "creating bucket {name}");
    }

    /// The store settings that point object_store at this server, as environment variables.
    pub fn env(&self) -> Vec<(String, String)> {
        self.env_via(&self.endpoint)
    }

    /// The store settings that reach this server through `endpoint` (a proxy in front of it).
    pub fn env_via(&self, endpoint: &str) -> Vec<(String, String)> {
        [
            ("AWS_ENDPOINT", endpoint),
            ("AWS_ALLOW_HTTP", "true"),
            ("AWS_ACCESS_KEY_ID", "testing"),
            ("AWS_SECRET_ACCESS_KEY", "testing"),
            ("AWS_REGION", "us-east-1"),
        ]
        .into_iter()
        .map(|(key, value)| (key.to_string(), value.to_string()))
        .collect()
    }
}

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// How many commits `job.json` under `checkpoints` knows for the current stage.
pub fn commits_in_job_json(checkpoints: &Path) -> usize {
    let Ok(bytes) = std::fs::read(checkpoints.join("job.json")) else {
        return 0;
    };
    let state: Value = serde_json::from_slice(&bytes).unwrap_or_default();
    let earlier = state["earlier_commits"].as_array().map_or(0, Vec::len);
    earlier + usize::from(!state["last_commit"].is_null())
}

/// Every file under `dir`.
pub fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let path = entry.path();
        if path.is_dir() {
            found.extend(walk(&path));
        } else {
            found.push(path);
        }
    }
    found
}
