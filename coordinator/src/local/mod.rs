//! The local harness: a generated RE10K-layout dataset, a cluster YAML for it, and a
//! coordinator plus worker processes on loopback. The README's main command and the
//! integration tests run jobs this way.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use data::Split;
use data::scenes::SceneConfig;
use data::store::DataRoot;
use data::synthetic::SyntheticDataset;
use settings::DeviceChoice;
use settings::objective::ObjectiveVariant;
use settings::work::WireFormat;

use generated::{Found, GENERATED_WITH, GeneratedWith};

pub mod figures;
mod generated;
pub mod watch;
mod yaml;

/// Size of a local job.
#[derive(Debug, Clone)]
pub struct LocalJob {
    /// Folder holding data, YAML, checkpoints, report and logs.
    pub dir: PathBuf,
    /// Worker processes.
    pub workers: usize,
    /// Fewest workers the job may continue with.
    pub minimum: usize,
    /// Generated scenes (each rendered along every trajectory).
    pub scenes: u64,
    /// Generated camera paths.
    pub trajectories: u64,
    /// Frames per sequence (at least 10, the indexers' minimum).
    pub frames: usize,
    /// Training resolution.
    pub image_size: usize,
    /// Model preset (`tiny`, `benchmark`, `paper`, ...; see the cluster YAML's `model.preset`).
    pub preset: String,
    /// Stage-1 steps.
    pub stage1_steps: u64,
    /// Steps stage 1's cosine and window curriculum span (`None`: `stage1_steps`); a larger
    /// span trains the first `stage1_steps` of a longer schedule, step for step as its full run
    /// does (CI's transfer guard trains the recipe's first 4000 of 12000 steps).
    pub stage1_schedule_steps: Option<u64>,
    /// Stage-2 steps.
    pub stage2_steps: u64,
    /// Train stage 1 alone (`stop_after: stage1`): stage 2's settings are written, not trained.
    pub stage1_only: bool,
    /// Samples per step.
    pub global_batch: u64,
    /// Samples per forward pass per worker.
    pub micro_batch: u64,
    /// Commit every this many steps.
    pub checkpoint_every: u64,
    /// Coordinator port.
    pub port: u16,
    /// The host the coordinator listens on (workers of this harness dial loopback).
    pub listen_host: String,
    /// Seed of data and training.
    pub seed: u64,
    /// A worker stuck in its step this long while a peer waits for it is removed.
    pub stall_timeout_s: f64,
    /// Use in-memory generated scenes instead of a stored dataset.
    pub in_memory: bool,
    /// Evaluate the trained stages' final weights after training (a small TPS, probe and
    /// reconstruction run on generated scenes).
    pub evaluate: bool,
    /// The objective variant of stage 1, and of stage 2 unless it is a stage-1-only one;
    /// `None`: the default.
    pub objective_variant: Option<ObjectiveVariant>,
    /// The pose-latent size instead of the preset's.
    pub pose_dim: Option<usize>,
    /// Port of the coordinator's `/metrics` endpoint; `None`: no endpoint.
    pub coordinator_metrics_port: Option<u16>,
    /// A read-only token for the status page (`viewing:` in the YAML); `None`: only the job
    /// token opens it.
    pub viewing_token: Option<String>,
    /// Ports of the workers' `/metrics` endpoints, by worker index; missing: no endpoint.
    pub worker_metrics_ports: Vec<u16>,
    /// More `xfactor-worker` arguments, by worker index (fault drills, say).
    pub worker_args: Vec<Vec<String>>,
    /// Where the generated dataset goes; `None`: `dir/data`. A URI such as `s3://bucket/data`
    /// puts it in an object store.
    pub data_uri: Option<String>,
    /// Where checkpoints and `job.json` go; `None`: [`LocalJob::checkpoint_dir`].
    pub checkpoint_uri: Option<String>,
    /// Peak learning rate of stage 1's warm-up + cosine schedule (stage 2's is 1e-3).
    pub stage1_peak_lr: f64,
    /// Stage 2 keeps stage 1's Render and trains with this many views (`None`: the release's
    /// recipe, a fresh Render and its views).
    pub stage2_views_keeping_render: Option<usize>,
    /// Size of the evaluation stage.
    pub evaluation: LocalEvaluation,
    /// The device every worker trains on (`cpu` by default: two workers share one host).
    pub device: DeviceChoice,
    /// How the ring carries gradients (`f32` by default; written to the YAML only when not).
    pub allreduce_wire: WireFormat,
    /// Steps between parameter checksums (`None`: `auto`, every step for the small models).
    pub checksum_every: Option<u64>,
    /// Store settings as environment variables (`AWS_ENDPOINT`, `AWS_ALLOW_HTTP`, ...): given
    /// to the coordinator and worker processes, and used by the harness's own store access.
    pub store_env: Vec<(String, String)>,
    /// A folder with `server.pem`, `server.key` and `ca.pem` (valid for 127.0.0.1): the job
    /// runs TLS (`tls:` in the YAML), and every worker brings that certificate for its ring.
    pub tls: Option<PathBuf>,
}

impl LocalJob {
    /// A laptop-sized default: 2 workers, 4 scenes x 4 paths of 12 frames at 32x32, 20 + 10
    /// steps of 8 samples.
    pub fn new(dir: &Path, port: u16) -> Self {
        Self {
            dir: dir.to_path_buf(),
            workers: 2,
            minimum: 1,
            scenes: 4,
            trajectories: 4,
            frames: 12,
            image_size: 32,
            preset: "tiny".into(),
            stage1_steps: 20,
            stage1_schedule_steps: None,
            stage2_steps: 10,
            stage1_only: false,
            global_batch: 8,
            micro_batch: 4,
            checkpoint_every: 5,
            port,
            listen_host: "127.0.0.1".into(),
            seed: 7,
            stall_timeout_s: 60.0,
            in_memory: false,
            evaluate: false,
            objective_variant: None,
            pose_dim: None,
            coordinator_metrics_port: None,
            viewing_token: None,
            worker_metrics_ports: Vec::new(),
            worker_args: Vec::new(),
            data_uri: None,
            checkpoint_uri: None,
            store_env: Vec::new(),
            stage1_peak_lr: 1e-3,
            stage2_views_keeping_render: None,
            evaluation: LocalEvaluation::default(),
            device: DeviceChoice::Cpu,
            allreduce_wire: WireFormat::F32,
            checksum_every: None,
            tls: None,
        }
    }

    /// The README's first run: long enough, on data small enough, that its report shows the
    /// trained model ahead of an untrained one on every metric in about four minutes on 2
    /// cores: 16 scenes x 16 paths of 12 frames at 32x32, 4000 stage-1 steps at a peak
    /// learning rate of 2e-3, then 150 stage-2 steps that keep stage 1's Render and train
    /// with three views (a short stage 2 with a fresh Render, as the release trains it,
    /// would score no better than copying the context frame), then an evaluation on 8 scenes.
    pub fn demo(dir: &Path, port: u16) -> Self {
        Self {
            scenes: 16,
            trajectories: 16,
            stage1_steps: 4000,
            stage2_steps: 150,
            checkpoint_every: 500,
            stage1_peak_lr: 2e-3,
            stage2_views_keeping_render: Some(3),
            evaluate: true,
            evaluation: LocalEvaluation::demo(),
            ..Self::new(dir, port)
        }
    }

    /// What this job's training departs from the release's, in words: the evaluation report
    /// lists them, and `xfactor-local` prints them, so its figures are not read as the paper's.
    pub fn departures(&self) -> Vec<String> {
        let mut notes = vec![
            format!(
                "data: generated scenes ({} scenes x {} paths of {} frames), not the release's four datasets",
                self.scenes, self.trajectories, self.frames
            ),
            format!(
                "model: preset {} at {}x{} (the paper: 305M parameters at 256x256)",
                self.preset, self.image_size, self.image_size
            ),
            format!(
                "training: {} steps of {} samples{}, no LPIPS term (lpips_weight 0)",
                if self.stage1_only {
                    format!("{} stage-1", self.stage1_steps)
                } else {
                    format!("{} + {}", self.stage1_steps, self.stage2_steps)
                },
                self.global_batch,
                match self.stage1_schedule() {
                    span if span == self.stage1_steps => String::new(),
                    span => format!(" (stage 1: the first of a {span}-step schedule)"),
                }
            ),
        ];
        if let (Some(views), false) = (self.stage2_views_keeping_render, self.stage1_only) {
            notes.push(format!(
                "stage 2 keeps stage 1's Render and trains with {views} views (the release: a fresh Render, 6 views)"
            ));
        }
        if let Some(variant) = self.objective_variant {
            notes.push(format!("objective variant {variant:?}"));
        }
        notes
    }

    /// The stages this job trains (1, or 1 and 2).
    pub fn trained_stages(&self) -> &'static [u64] {
        if self.stage1_only { &[1] } else { &[1, 2] }
    }

    /// Steps of every stage this job trains.
    pub fn trained_steps(&self) -> u64 {
        self.stage1_steps
            + if self.stage1_only {
                0
            } else {
                self.stage2_steps
            }
    }

    /// The steps stage 1's schedule spans.
    fn stage1_schedule(&self) -> u64 {
        self.stage1_schedule_steps.unwrap_or(self.stage1_steps)
    }

    /// The job token (fixed per folder; local jobs are loopback-only).
    pub fn token(&self) -> &'static str {
        "local-harness-token"
    }

    /// Path of the cluster YAML.
    pub fn config_path(&self) -> PathBuf {
        self.dir.join("cluster.yaml")
    }

    /// Path of the job report.
    pub fn report_path(&self) -> PathBuf {
        self.dir.join("report.json")
    }

    /// Where checkpoints go.
    pub fn checkpoint_dir(&self) -> PathBuf {
        self.dir.join("checkpoints")
    }

    /// Where the dataset is: [`LocalJob::data_uri`] or `dir/data`.
    pub fn data_location(&self) -> String {
        self.data_uri
            .clone()
            .unwrap_or_else(|| self.dir.join("data").display().to_string())
    }

    /// Where checkpoints go: [`LocalJob::checkpoint_uri`] or [`LocalJob::checkpoint_dir`].
    pub fn checkpoint_location(&self) -> String {
        self.checkpoint_uri
            .clone()
            .unwrap_or_else(|| self.checkpoint_dir().display().to_string())
    }

    /// Writes the generated dataset (unless in memory, or already there as this job would make
    /// it) and the cluster YAML. A dataset made with other settings (`generated-with.json`) is
    /// regenerated when it is this job's own `dir/data`, and refused naming the difference
    /// when it lives elsewhere ([`LocalJob::data_uri`]): a rerun never trains on stale frames.
    pub async fn prepare(&self) -> anyhow::Result<()> {
        std::fs::create_dir_all(&self.dir)?;
        let data = self.data_location();
        if !self.in_memory {
            let mut root = DataRoot::create_with(&data, &self.store_env)?;
            let wanted = GeneratedWith::of(self);
            match wanted.found(&root).await? {
                Found::Nothing => self.generate(&root, &wanted).await?,
                Found::Same => tracing::info!(%data, "reusing the generated dataset"),
                Found::Other(found) if self.data_uri.is_none() => {
                    tracing::warn!(%data, differences = %wanted.differences(found.as_ref()), "the dataset was generated with other settings; generating it again");
                    std::fs::remove_dir_all(self.dir.join("data"))?;
                    root = DataRoot::create_with(&data, &self.store_env)?;
                    self.generate(&root, &wanted).await?;
                }
                Found::Other(found) => anyhow::bail!(
                    "{data} holds a dataset generated with other settings ({}): remove it or point the job at another location",
                    wanted.differences(found.as_ref())
                ),
            }
        }
        std::fs::write(self.config_path(), self.yaml(&data))?;
        Ok(())
    }

    /// Generates the training scenes into `root`, then writes what they were made with.
    async fn generate(&self, root: &DataRoot, wanted: &GeneratedWith) -> anyhow::Result<()> {
        let scene = SceneConfig {
            image_size: self.image_size,
            ..SceneConfig::default()
        };
        let dataset = SyntheticDataset::generate(
            self.seed,
            self.scenes,
            self.trajectories,
            self.frames,
            &scene,
        );
        let frames = dataset
            .write_re10k(root, Split::Train, scene.fov_degrees)
            .await?;
        root.write(GENERATED_WITH, serde_json::to_vec_pretty(wanted)?)
            .await?;
        tracing::info!(frames, data = %root.uri(), "generated RE10K-layout dataset");
        Ok(())
    }

    /// Starts the coordinator process (its log is appended to `coordinator.log`, so a
    /// restarted coordinator's log follows the first one's).
    pub fn spawn_coordinator(&self, binaries: &Path) -> anyhow::Result<Child> {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.dir.join("coordinator.log"))?;
        let mut command = Command::new(binaries.join("xfactor-coordinator"));
        command
            .arg("run")
            .arg("--config")
            .arg(self.config_path())
            .arg("--report")
            .arg(self.report_path());
        if let Some(port) = self.coordinator_metrics_port {
            command
                .arg("--metrics-address")
                .arg(format!("127.0.0.1:{port}"));
        }
        Ok(command
            .envs(self.store_env.iter().map(|(key, value)| (key, value)))
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()?)
    }

    /// Starts worker process number `index` (its log goes to `worker-<index>.log`).
    pub fn spawn_worker(&self, binaries: &Path, index: usize) -> anyhow::Result<Child> {
        let log = std::fs::File::create(self.dir.join(format!("worker-{index}.log")))?;
        let mut command = Command::new(binaries.join("xfactor-worker"));
        if let Some(port) = self.worker_metrics_ports.get(index) {
            command
                .arg("--metrics-address")
                .arg(format!("127.0.0.1:{port}"));
        }
        if let Some(tls) = &self.tls {
            command
                .arg("--tls-ca")
                .arg(tls.join("ca.pem"))
                .arg("--tls-cert")
                .arg(tls.join("server.pem"))
                .arg("--tls-key")
                .arg(tls.join("server.key"));
        }
        let scheme = if self.tls.is_some() { "https" } else { "http" };
        Ok(command
            .arg("--coordinator")
            .arg(format!("{scheme}://127.0.0.1:{}", self.port))
            .arg("--token")
            .arg(self.token())
            .arg("--name")
            .arg(format!("local-{index}"))
            .arg("--scratch")
            .arg(self.dir.join("scratch"))
            .args(self.worker_args.get(index).into_iter().flatten())
            .envs(self.store_env.iter().map(|(key, value)| (key, value)))
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()?)
    }
}

/// The evaluation stage of a local job: held-out generated scenes (the test split's draws, which
/// no training scene shares), TPS pairs, reconstructed sequences and the pose probe.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalEvaluation {
    /// Scenes generated for the evaluation.
    pub scenes: u64,
    /// Camera paths per scene.
    pub trajectories: u64,
    /// Frames per path.
    pub frames: usize,
    /// Transfer pairs.
    pub tps_pairs: usize,
    /// Sequences reconstructed.
    pub reconstruction_sequences: usize,
    /// Probe steps.
    pub probe_steps: usize,
    /// Probe batch.
    pub probe_batch: usize,
    /// Probe MLP width (`features`; the paper's: 256).
    pub probe_width: usize,
    /// Scenes the probe is tested on (held out of its training).
    pub probe_test_scenes: u64,
    /// The probe's rotation starts at the identity (`evaluate.probe.rotation_from_identity`).
    pub probe_rotation_from_identity: bool,
}

impl Default for LocalEvaluation {
    /// A quick check that the stage runs: 3 scenes, 8 pairs, 150 probe steps.
    fn default() -> Self {
        Self {
            scenes: 3,
            trajectories: 4,
            frames: 6,
            tps_pairs: 8,
            reconstruction_sequences: 4,
            probe_steps: 150,
            probe_batch: 16,
            probe_width: 64,
            probe_test_scenes: 1,
            probe_rotation_from_identity: false,
        }
    }
}

impl LocalEvaluation {
    /// Appends the `evaluate:` section for a job seeded with `seed`.
    fn write_yaml(&self, seed: u64, notes: &[String], yaml: &mut String) {
        let notes: Vec<String> = notes
            .iter()
            .map(|note| serde_json::Value::from(note.as_str()).to_string())
            .collect();
        let _ = writeln!(
            yaml,
            "evaluate:\n  notes: [{}]\n  seed: {}\n  scenes: {}\n  trajectories: {}\n  frames: {}\n  tps_pairs: {}\n  reconstruction_sequences: {}\n  probe: {{steps: {}, batch: {}, width: {}, test_scenes: {}, rotation_from_identity: {}}}",
            notes.join(", "),
            seed,
            self.scenes,
            self.trajectories,
            self.frames,
            self.tps_pairs,
            self.reconstruction_sequences,
            self.probe_steps,
            self.probe_batch,
            self.probe_width,
            self.probe_test_scenes,
            self.probe_rotation_from_identity
        );
    }

    /// The first run's: 16 held-out scenes x 8 paths, every sequence reconstructed, 128
    /// transfers, a probe of 1000 steps of 64 tested on 4 scenes (about half a minute): enough
    /// pairs that each headline figure's spread is a fraction of the model's lead.
    pub fn demo() -> Self {
        Self {
            scenes: 16,
            trajectories: 8,
            frames: 8,
            tps_pairs: 128,
            reconstruction_sequences: 128,
            probe_steps: 1000,
            probe_batch: 64,
            probe_width: 64,
            probe_test_scenes: 4,
            probe_rotation_from_identity: true,
        }
    }
}

/// Where [`free_port`] looks: below Linux's ephemeral range (32768-60999), which sockets
/// bound to port 0 draw from.
const HANDED_OUT_PORTS: std::ops::Range<u16> = 20000..32000;

/// A free TCP port on loopback for a process about to be started (bound then released). It
/// comes from below the ephemeral range, so no socket bound to port 0 meanwhile (a worker's
/// collective service, another test's process) can take it before its user binds it: a port
/// handed out from that range once went to another process first. A random start spreads
/// concurrent callers; where the whole range is taken, any free port.
pub fn free_port() -> std::io::Result<u16> {
    use std::hash::{BuildHasher, Hasher};
    let count = HANDED_OUT_PORTS.end - HANDED_OUT_PORTS.start;
    let start = std::collections::hash_map::RandomState::new()
        .build_hasher()
        .finish()
        % u64::from(count);
    let candidates = (0..count).map(|offset| {
        let index = (start + u64::from(offset)) % u64::from(count);
        HANDED_OUT_PORTS.start + index as u16
    });
    for port in candidates {
        if std::net::TcpListener::bind(("127.0.0.1", port)).is_ok() {
            return Ok(port);
        }
    }
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

#[cfg(test)]
mod port_tests {
    use super::*;

    #[test]
    fn handed_out_ports_are_free_and_below_the_ephemeral_range() {
        let ports: Vec<u16> = (0..8).map(|_| free_port().expect("a free port")).collect();
        for port in &ports {
            assert!(HANDED_OUT_PORTS.contains(port), "{port}");
            std::net::TcpListener::bind(("127.0.0.1", *port)).expect("still free");
        }
        let distinct: std::collections::BTreeSet<u16> = ports.iter().copied().collect();
        assert!(distinct.len() > 1, "{ports:?}");
    }
}
