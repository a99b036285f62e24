//! The two stores a job runs on, through the real processes: the local file system (the
//! default) and S3, here moto's S3 server started on loopback. On each: indexing a dataset
//! with its manifest cache, training both stages with data and checkpoints there, a restarted
//! coordinator resuming from the commit there, and the conditional write of `job.json` that
//! refuses a second writer. The S3 tests fail, never skip, when moto cannot be started
//! (`scripts/setup.sh` installs it).

mod common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::{Moto, Running, commits, small_job, wait_exit};
use coordinator::job::Durable;
use coordinator::service::store::{DurableWriteError, read_durable, write_durable};
use data::DatasetKind;
use data::cache::{CacheUse, load_or_index};
use data::scenes::SceneConfig;
use data::store::DataRoot;
use data::synthetic::SyntheticDataset;
use serde_json::Value;
use settings::Phase;
use tokio::sync::Mutex;

/// Where one test keeps its data and checkpoints.
struct Store {
    base: String,
    env: Vec<(String, String)>,
    _server: Option<Moto>,
}

impl Store {
    fn local(dir: &Path) -> Self {
        Self {
            base: dir.join("store").display().to_string(),
            env: Vec::new(),
            _server: None,
        }
    }

    fn s3(dir: &Path) -> Self {
        let moto = Moto::start(dir);
        moto.create_bucket("xfactor");
        Self {
            base: "s3://xfactor/run".to_string(),
            env: moto.env(),
            _server: Some(moto),
        }
    }

    fn uri(&self, relative: &str) -> String {
        format!("{}/{relative}", self.base)
    }

    fn root(&self, relative: &str) -> DataRoot {
        DataRoot::create_with(&self.uri(relative), &self.env).unwrap()
    }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

fn timed(name: &str, started: Instant) {
    eprintln!("{name}: {:.1} s", started.elapsed().as_secs_f64());
}

fn indexes_a_dataset(store: &Store, scratch: &Path) {
    let rt = runtime();
    let scene = SceneConfig {
        image_size: 32,
        ..SceneConfig::default()
    };
    let dataset = SyntheticDataset::generate(3, 2, 2, 10, &scene);
    let remote = store.root("data");
    let local = DataRoot::create(&scratch.join("reference").display().to_string()).unwrap();
    for root in [&remote, &local] {
        rt.block_on(dataset.write_re10k(root, data::Split::Train, scene.fov_degrees))
            .unwrap();
    }
    let (built, first) = rt
        .block_on(load_or_index(&remote, DatasetKind::Re10k))
        .unwrap();
    assert_eq!(first, CacheUse::Rebuilt);
    assert_eq!(built.manifest.frame_counts(), vec![10; 4]);
    let (cached, second) = rt
        .block_on(load_or_index(&remote, DatasetKind::Re10k))
        .unwrap();
    assert_eq!(
        second,
        CacheUse::Reused,
        "the cache beside the data is reused"
    );
    let (reference, _) = rt
        .block_on(load_or_index(&local, DatasetKind::Re10k))
        .unwrap();
    assert_eq!(cached.manifest, reference.manifest);
}

#[test]
fn a_dataset_indexes_on_s3() {
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    indexes_a_dataset(&Store::s3(dir.path()), dir.path());
    timed("a_dataset_indexes_on_s3", started);
}

#[test]
fn a_dataset_indexes_on_local_disk() {
    let dir = tempfile::tempdir().unwrap();
    indexes_a_dataset(&Store::local(dir.path()), dir.path());
}

fn job_on(store: &Store, dir: &Path) -> coordinator::local::LocalJob {
    let mut job = small_job(dir, 2);
    job.data_uri = Some(store.uri("data"));
    job.checkpoint_uri = Some(store.uri("checkpoints"));
    job.store_env = store.env.clone();
    job
}

/// Downloads the checkpoint at `location` and loads its weights.
fn load_weights(store: &Store, location: &str, scratch: &Path) {
    let rt = runtime();
    let root = DataRoot::open_with(location, &store.env).unwrap();
    let local = scratch.join(location.rsplit('/').next().unwrap());
    std::fs::create_dir_all(&local).unwrap();
    for listed in rt.block_on(root.list()).unwrap() {
        let bytes = rt.block_on(root.read(&listed.path)).unwrap();
        std::fs::write(local.join(&listed.path), bytes).unwrap();
    }
    trainer_core::checkpoint::load(
        &local.join("model.safetensors"),
        &burn::tensor::Device::flex(),
    )
    .unwrap_or_else(|e| panic!("checkpoint {location} does not load: {e}"));
}

fn job_state(store: &Store) -> Option<Value> {
    match runtime().block_on(store.root("checkpoints").read("job.json")) {
        Ok(bytes) => Some(serde_json::from_slice(&bytes).unwrap()),
        Err(data::store::StoreError::NotFound { .. }) => None,
        Err(error) => panic!("job.json unreadable: {error}"),
    }
}

fn trains_both_stages(store: &Store, dir: &Path) {
    let report = Running::start(job_on(store, dir)).finish(Duration::from_secs(240));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let stage1 = commits(&report, 1);
    let stage2 = commits(&report, 2);
    assert_eq!(stage1.iter().map(|c| c.0).collect::<Vec<_>>(), [2, 4]);
    assert_eq!(stage2.iter().map(|c| c.0).collect::<Vec<_>>(), [2, 3]);
    for (_, location) in stage1.iter().chain(&stage2) {
        assert!(
            location.starts_with(&store.uri("checkpoints/")),
            "{location} is not under the store"
        );
    }
    load_weights(store, &stage1[1].1, dir);
    load_weights(store, &stage2[1].1, dir);
    let state = job_state(store).expect("job.json in the store");
    assert_eq!(state["stage1_final"], stage1[1].1.as_str(), "{state:#}");
    assert_eq!(state["stage2_final"], stage2[1].1.as_str(), "{state:#}");
    let rt = runtime();
    let checkpoints = store.root("checkpoints");
    for (stage, steps) in [(1, 4), (2, 3)] {
        let csv = rt
            .block_on(checkpoints.read(&format!("curves/stage{stage}.csv")))
            .unwrap();
        assert_eq!(String::from_utf8(csv).unwrap().lines().count(), steps + 1);
    }
    // The step history went to the store as the job ran, one JSON line per step.
    let history = rt
        .block_on(checkpoints.read(&coordinator::service::history::segment_path(0)))
        .unwrap();
    let lines: Vec<Value> = String::from_utf8(history)
        .unwrap()
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect();
    let steps = report["steps"].as_array().unwrap();
    assert_eq!(lines.len(), steps.len());
    for (line, step) in lines.iter().zip(steps) {
        assert_eq!(
            (&line["stage"], &line["step"]),
            (&step["stage"], &step["step"])
        );
        assert_eq!(line["loss"], step["loss"]);
    }
    let cache = data::cache::cache_path(DatasetKind::Re10k);
    rt.block_on(store.root("data").read(&cache))
        .expect("the coordinator cached the manifest beside the data");
}

#[test]
fn both_stages_train_with_data_and_checkpoints_on_s3() {
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    trains_both_stages(&Store::s3(dir.path()), dir.path());
    timed("both_stages_train_with_data_and_checkpoints_on_s3", started);
}

#[test]
fn both_stages_train_with_data_and_checkpoints_on_local_disk() {
    let dir = tempfile::tempdir().unwrap();
    trains_both_stages(&Store::local(dir.path()), dir.path());
}

fn resumes_after_a_restart(store: &Store, dir: &Path) {
    let mut job = job_on(store, dir);
    job.stage1_steps = 10;
    let mut running = Running::start(job);
    let deadline = Instant::now() + Duration::from_secs(120);
    while job_state(store).is_none() {
        assert!(Instant::now() < deadline, "no commit\n{}", running.logs());
        std::thread::sleep(Duration::from_millis(100));
    }
    let terminated = std::process::Command::new("kill")
        .args(["-TERM", &running.coordinator.id().to_string()])
        .status()
        .unwrap();
    assert!(terminated.success());
    let status = wait_exit(&mut running.coordinator, Duration::from_secs(30));
    assert!(
        status.success(),
        "coordinator on SIGTERM: {status:?}\n{}",
        running.logs()
    );
    let state = job_state(store).unwrap();
    let resume_point = state["last_commit"]["location"]
        .as_str()
        .unwrap_or_default();
    assert!(
        resume_point.starts_with(&store.uri("checkpoints/")) || state["stage"] != 1,
        "{state:#}"
    );
    running.coordinator = running.job.spawn_coordinator(&common::binaries()).unwrap();
    let report = running.finish(Duration::from_secs(240));
    assert_eq!(report["outcome"], "finished", "{report:#}");
    let first = &report["generations"][0];
    assert!(
        first["stage"] == 2 || first["resume_from"] != "",
        "the restarted coordinator began stage 1 afresh: {report:#}"
    );
    let last = commits(&report, 2).pop().unwrap();
    assert_eq!(last.0, 3, "{report:#}");
    load_weights(store, &last.1, dir);
}

#[test]
fn a_restarted_coordinator_resumes_from_its_commit_on_s3() {
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    resumes_after_a_restart(&Store::s3(dir.path()), dir.path());
    timed(
        "a_restarted_coordinator_resumes_from_its_commit_on_s3",
        started,
    );
}

#[test]
fn a_restarted_coordinator_resumes_from_its_commit_on_local_disk() {
    let dir = tempfile::tempdir().unwrap();
    resumes_after_a_restart(&Store::local(dir.path()), dir.path());
}

/// Two coordinators' writes of one `job.json`: whoever writes from a version that is no
/// longer current is refused, with the URI in the message.
fn job_json_writes_are_conditional(root: &DataRoot) {
    let rt = runtime();
    let first = Durable::new("conditional".into());
    let mut second = first.clone();
    second.phase = Phase::Stage2;
    let writer = Mutex::new(None);
    rt.block_on(write_durable(root, &first, &writer)).unwrap();
    let late_starter = Mutex::new(None);
    let refused = rt
        .block_on(write_durable(root, &first, &late_starter))
        .unwrap_err();
    assert!(
        matches!(refused, DurableWriteError::Stale { .. }),
        "{refused:?}"
    );
    let (read, version) = rt
        .block_on(read_durable(root, "conditional"))
        .unwrap()
        .unwrap();
    assert_eq!(read, first);
    let reader = Mutex::new(Some(version));
    rt.block_on(write_durable(root, &second, &writer)).unwrap();
    let refused = rt
        .block_on(write_durable(root, &first, &reader))
        .unwrap_err();
    let message = refused.to_string();
    assert!(
        matches!(refused, DurableWriteError::Stale { .. }),
        "{refused:?}"
    );
    assert!(
        message.contains(&format!("{}/job.json", root.uri())),
        "{message}"
    );
    let (read, version) = rt
        .block_on(read_durable(root, "conditional"))
        .unwrap()
        .unwrap();
    assert_eq!(read, second, "the refused write left job.json alone");
    rt.block_on(write_durable(root, &first, &Mutex::new(Some(version))))
        .expect("a writer holding the current version may write");
}

#[test]
fn job_json_writes_are_conditional_on_s3() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::s3(dir.path());
    job_json_writes_are_conditional(&store.root("checkpoints"));
}

#[test]
fn job_json_writes_are_conditional_on_local_disk() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::local(dir.path());
    job_json_writes_are_conditional(&store.root("checkpoints"));
}

#[test]
fn job_json_writes_are_conditional_in_memory() {
    job_json_writes_are_conditional(&DataRoot::in_memory("memory://checkpoints"));
}
