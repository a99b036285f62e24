//! Planning a job over a stored dataset: a split file named in the cluster YAML replaces the
//! layout's train/test rule, and a split file that cannot be read stops the plan naming the
//! YAML key and the file; an evaluation that would read training scenes is refused naming them.

use coordinator::config::ClusterConfig;
use coordinator::plan::{Plan, PlanError};
use data::DatasetKind;
use data::cache::load_or_index;
use data::scenes::SceneConfig;
use data::store::DataRoot;
use data::synthetic::SyntheticDataset;

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

/// A cluster YAML over the RE10K dataset at `uri`, with `extra` added to its dataset entry.
fn cluster_yaml(uri: &str, extra: &str) -> String {
    format!(
        "job: split-demo
auth:
  token: abc
model:
  preset: tiny
  image_size: 32
data:
  datasets:
    - kind: re10k
      uri: {uri}
{extra}stage1:
  steps: 2
  global_batch: 2
  micro_batch: 1
  lpips_weight: 0
stage2:
  steps: 2
  global_batch: 2
  micro_batch: 1
  lpips_weight: 0
checkpoint:
  uri: {uri}-checkpoints
  every: 1
"
    )
}

/// The `data:` line of the plan's description.
fn train_sequences(plan: &Plan) -> String {
    plan.describe()
        .lines()
        .find(|line| line.starts_with("data: re10k"))
        .expect("the plan describes its dataset")
        .to_string()
}

/// Writes 2 scenes x 2 paths of 10 frames at 32x32, drawn for split `drawn` from seed 2, into
/// the RE10K split folders `folders` of a new root `dir/name`; returns the root's URI.
fn write_generated(
    rt: &tokio::runtime::Runtime,
    dir: &std::path::Path,
    name: &str,
    drawn: data::Split,
    folders: &[data::Split],
) -> String {
    let scene = SceneConfig {
        image_size: 32,
        ..SceneConfig::default()
    };
    let uri = dir.join(name).display().to_string();
    let root = DataRoot::create(&uri).unwrap();
    let dataset = SyntheticDataset::generate_split(2, drawn, 2, 2, 10, &scene);
    for &folder in folders {
        rt.block_on(dataset.write_re10k(&root, folder, scene.fov_degrees))
            .unwrap();
    }
    uri
}

#[test]
fn a_split_file_chooses_the_training_sequences() {
    let dir = tempfile::tempdir().unwrap();
    let rt = runtime();
    let train = [data::Split::Train];
    let uri = write_generated(&rt, dir.path(), "re10k", data::Split::Train, &train);
    let root = DataRoot::open(&uri).unwrap();
    let (indexed, _) = rt
        .block_on(load_or_index(&root, DatasetKind::Re10k))
        .unwrap();
    let ids: Vec<String> = indexed
        .manifest
        .sequences
        .iter()
        .map(|s| s.id.clone())
        .collect();
    assert_eq!(ids.len(), 4);

    let plan = |extra: &str| {
        let config = ClusterConfig::from_yaml(&cluster_yaml(&uri, extra), "cluster.yaml").unwrap();
        // Boxed: a plan error carries whole store errors.
        rt.block_on(Plan::build(config)).map_err(Box::new)
    };
    let by_rule = plan("").unwrap();
    assert!(train_sequences(&by_rule).contains(": 4 train sequences"));

    // The paper's files key sequences by id; the values do not matter.
    let keys = format!(r#"{{"{}": 0, "{}": 0}}"#, ids[0], ids[3]);
    std::fs::write(dir.path().join("re10k/train_split.json"), keys).unwrap();
    let relative = plan("      split_file: train_split.json\n").unwrap();
    assert!(
        train_sequences(&relative).contains(": 2 train sequences"),
        "{}",
        relative.describe()
    );
    let absolute = dir.path().join("re10k/train_split.json");
    let absolute = plan(&format!("      split_file: {}\n", absolute.display())).unwrap();
    assert_eq!(train_sequences(&absolute), train_sequences(&relative));

    let missing = plan("      split_file: nowhere.json\n").unwrap_err();
    assert!(matches!(*missing, PlanError::Split { index: 0, .. }));
    let chain = format!("{:#}", anyhow::Error::from(*missing));
    assert!(
        chain.contains("data.datasets[0].split_file") && chain.contains("nowhere.json"),
        "{chain}"
    );
}

/// An `evaluate:` section on generated scenes of `seed`, with `sequences` (YAML list items).
fn evaluate_yaml(seed: u64, sequences: &str) -> String {
    format!(
        "evaluate:\n  seed: {seed}\n  scenes: 2\n  trajectories: 2\n  probe: {{test_scenes: 1}}\n  sequences: [{sequences}]\n"
    )
}

#[test]
fn an_evaluation_that_reads_training_scenes_is_refused_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let rt = runtime();
    let (train, test) = (data::Split::Train, data::Split::Test);
    // The same sequences in the train and the test folder: a test split that trains.
    let uri = write_generated(&rt, dir.path(), "re10k", train, &[train, test]);
    let held_out = write_generated(&rt, dir.path(), "re10k-test", test, &[test]);
    let plan = |evaluate: String| {
        let yaml = cluster_yaml(&uri, "") + &evaluate;
        let config = ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap();
        rt.block_on(Plan::build(config)).map_err(Box::new)
    };
    let protocol = |root: &str| format!("{{kind: re10k, uri: {root}, length: 10, count: 4}}");

    let shared = plan(evaluate_yaml(2, &protocol(&uri))).unwrap_err();
    let message = format!("{:#}", anyhow::Error::from(*shared));
    assert!(
        message.contains("evaluate.sequences[0]")
            && message.contains("4 evaluated scene(s)")
            && message.contains("g2-s0_t0"),
        "{message}"
    );
    plan(evaluate_yaml(2, &protocol(&held_out))).expect("held-out sequences are evaluated");

    // Training on the held-out draws themselves: the generated evaluation scenes are refused.
    let leaked = write_generated(&rt, dir.path(), "leaked", test, &[train]);
    let config = |seed| {
        let yaml = cluster_yaml(&leaked, "") + &evaluate_yaml(seed, "");
        ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap()
    };
    let error = rt.block_on(Plan::build(config(2))).unwrap_err().to_string();
    let first_held_out = data::synthetic::scene_name(2, data::Split::Test, 0);
    assert!(
        error.contains("evaluate (its generated scenes)") && error.contains(&first_held_out),
        "{error}"
    );
    rt.block_on(Plan::build(config(3)))
        .expect("another seed's held-out scenes are unseen");
}
