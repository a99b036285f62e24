//! `deploy/` checked against the code: every example cluster YAML goes through the real
//! parser, the Kubernetes ConfigMap source is the example, every flag the manifests and units
//! pass exists, and the Dockerfile builds the binaries the README builds.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use coordinator::config::{ClusterConfig, LastStage};

// Only the help-text reader: the help assertions are tests/cli.rs's.
#[allow(dead_code)]
#[path = "../../test-support/help.rs"]
mod help;

fn repository() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn read(relative: &str) -> String {
    std::fs::read_to_string(repository().join(relative))
        .unwrap_or_else(|e| panic!("{relative}: {e}"))
}

#[test]
fn every_example_cluster_yaml_parses_and_validates() {
    let examples = repository().join("deploy/examples");
    let mut parsed = 0;
    for entry in std::fs::read_dir(&examples).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "yaml") {
            let config = ClusterConfig::from_file(&path)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            config
                .model_config()
                .unwrap_or_else(|e| panic!("{}: model: {e}", path.display()));
            parsed += 1;
        }
    }
    assert!(
        parsed >= 3,
        "expected local, two-hosts and kubernetes examples"
    );
}

#[test]
fn the_paper_example_trains_with_the_release_numbers() {
    let config =
        ClusterConfig::from_file(&repository().join("deploy/examples/paper.yaml")).unwrap();
    assert_eq!(config.model_config().unwrap().image_size, 256);
    let coordinator::config::DataConfig::Datasets(datasets) = &config.data else {
        panic!("the paper trains on stored datasets");
    };
    assert_eq!(datasets.len(), 4);
    for (steps, batch, schedule, lpips) in [
        (
            config.stage1.steps,
            config.stage1.global_batch,
            &config.stage1.schedule,
            config.stage1.objective.lpips_weight,
        ),
        (
            config.stage2.steps,
            config.stage2.global_batch,
            &config.stage2.schedule,
            config.stage2.objective.lpips_weight,
        ),
    ] {
        assert_eq!(batch, 256);
        assert_eq!(lpips, 0.5);
        assert_eq!(schedule.warmup_steps, 4000);
        assert_eq!(schedule.total_steps, steps);
        assert_eq!(
            (schedule.initial_lr, schedule.peak_lr, schedule.final_lr),
            (1e-12, 4e-4, 1e-4)
        );
    }
    assert_eq!(
        (config.stage1.steps, config.stage2.steps),
        (100_000, 200_000)
    );
    assert!(!config.stage2.objective.render_from_stage1);
}

#[test]
fn the_kubernetes_config_map_is_the_kubernetes_example() {
    assert_eq!(
        read("deploy/k8s/cluster.yaml"),
        read("deploy/examples/kubernetes.yaml"),
        "deploy/k8s/cluster.yaml must be a copy of deploy/examples/kubernetes.yaml"
    );
}

/// The `--flags` a binary's `--help` defines.
fn usage_flags(binary: &str, arguments: &[&str]) -> BTreeSet<String> {
    help::flags(&help::help(binary, arguments))
        .into_keys()
        .collect()
}

fn flags_in(text: &str) -> BTreeSet<String> {
    text.split(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
        .filter(|word| {
            word.starts_with("--") && word[2..].starts_with(|c: char| c.is_ascii_lowercase())
        })
        .map(str::to_string)
        .collect()
}

fn flags_of(files: &[&str], marker: &str) -> BTreeSet<String> {
    let mut flags = BTreeSet::new();
    for file in files {
        let text = read(file);
        let relevant: Vec<&str> = text
            .lines()
            .filter(|line| !line.trim_start().starts_with('#'))
            .collect();
        let joined = relevant.join("\n");
        if joined.contains(marker) {
            flags.extend(flags_in(&joined));
        }
    }
    flags
}

#[test]
fn manifests_and_units_pass_only_flags_the_binaries_know() {
    let folder = Path::new(env!("CARGO_BIN_EXE_xfactor-coordinator"))
        .parent()
        .unwrap()
        .to_path_buf();
    let coordinator = usage_flags(env!("CARGO_BIN_EXE_xfactor-coordinator"), &["run"]);
    let worker = usage_flags(&folder.join("xfactor-worker").display().to_string(), &[]);
    assert!(coordinator.contains("--metrics-address") && worker.contains("--coordinator"));
    for (files, known, name) in [
        (
            [
                "deploy/k8s/coordinator.yaml",
                "deploy/systemd/xfactor-coordinator.service",
            ],
            &coordinator,
            "xfactor-coordinator",
        ),
        (
            [
                "deploy/k8s/worker.yaml",
                "deploy/systemd/xfactor-worker.service",
            ],
            &worker,
            "xfactor-worker",
        ),
    ] {
        let used = flags_of(&files, name);
        assert!(!used.is_empty(), "no {name} flags found in {files:?}");
        let unknown: Vec<&String> = used.difference(known).collect();
        assert!(
            unknown.is_empty(),
            "{files:?} pass flags {name} does not know: {unknown:?}"
        );
    }
}

#[test]
fn the_dockerfile_is_well_formed_and_builds_the_readme_binaries() {
    let dockerfile = read("deploy/docker/Dockerfile");
    let instructions = [
        "FROM",
        "RUN",
        "CMD",
        "LABEL",
        "EXPOSE",
        "ENV",
        "ADD",
        "COPY",
        "ENTRYPOINT",
        "VOLUME",
        "USER",
        "WORKDIR",
        "ARG",
        "ONBUILD",
        "STOPSIGNAL",
        "HEALTHCHECK",
        "SHELL",
    ];
    let mut logical = String::new();
    let mut stages = Vec::new();
    for line in dockerfile.lines() {
        let trimmed = line.trim();
        if logical.is_empty() && (trimmed.is_empty() || trimmed.starts_with('#')) {
            continue;
        }
        if logical.is_empty() {
            let keyword = trimmed.split_whitespace().next().unwrap_or_default();
            assert!(
                instructions.contains(&keyword.to_ascii_uppercase().as_str()),
                "not a Dockerfile instruction: {line}"
            );
            if keyword == "FROM" {
                stages.push(trimmed.to_string());
            }
        }
        logical.push_str(trimmed.trim_end_matches('\\'));
        if !trimmed.ends_with('\\') {
            logical.clear();
        }
    }
    assert!(
        logical.is_empty(),
        "the Dockerfile ends inside a continued line"
    );
    assert!(
        stages.len() >= 3,
        "builder, runtime and gpu stages: {stages:?}"
    );
    let run_script = read("scripts/run.sh");
    let readme_build = run_script
        .lines()
        .find(|l| l.starts_with("cargo build"))
        .expect("scripts/run.sh builds with cargo");
    let docker_build = readme_build.replacen("cargo build", "cargo build --release --locked", 1);
    let docker_build =
        docker_build.replacen("--release --locked --release", "--release --locked", 1);
    assert!(
        dockerfile.contains(&docker_build),
        "the Dockerfile must run `{docker_build}` like scripts/run.sh"
    );
    for binary in [
        "xfactor-coordinator",
        "xfactor-worker",
        "xfactor-local",
        "xfactor",
    ] {
        assert!(
            dockerfile.contains(&format!("target/release/{binary} ")),
            "{binary} not copied"
        );
    }
}

/// Every YAML document of a manifest file.
fn documents(relative: &str) -> Vec<serde_norway::Value> {
    use serde::Deserialize;
    serde_norway::Deserializer::from_str(&read(relative))
        .map(|document| {
            serde_norway::Value::deserialize(document).unwrap_or_else(|e| panic!("{relative}: {e}"))
        })
        .collect()
}

#[test]
fn kubernetes_probes_ask_grpc_health_on_the_serving_port() {
    for (file, port_name, port) in [
        ("deploy/k8s/coordinator.yaml", "grpc", 50051),
        ("deploy/k8s/worker.yaml", "collective", 50052),
    ] {
        let workloads: Vec<serde_norway::Value> = documents(file)
            .into_iter()
            .filter(|d| d["kind"] == "Deployment" || d["kind"] == "Job")
            .collect();
        assert_eq!(workloads.len(), 1, "{file}: one workload");
        let containers = workloads[0]["spec"]["template"]["spec"]["containers"]
            .as_sequence()
            .unwrap_or_else(|| panic!("{file}: no containers"));
        for container in containers {
            let declared = container["ports"]
                .as_sequence()
                .and_then(|ports| ports.iter().find(|p| p["name"] == port_name))
                .and_then(|p| p["containerPort"].as_u64());
            assert_eq!(declared, Some(port), "{file}: containerPort {port_name}");
            for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
                let grpc = &container[probe]["grpc"];
                assert_eq!(
                    grpc["port"].as_u64(),
                    Some(port),
                    "{file}: {probe} must be `grpc: {{port: {port}}}` (Kubernetes takes no port name there)"
                );
                for other in ["tcpSocket", "httpGet", "exec"] {
                    assert!(
                        container[probe].get(other).is_none(),
                        "{file}: {probe} has {other} besides grpc"
                    );
                }
            }
        }
    }
    assert!(
        read("deploy/k8s/worker.yaml").contains("0.0.0.0:50052"),
        "the worker listens where its probes ask"
    );
}

#[test]
fn the_erayzer_example_mixes_seven_datasets_with_its_weights_and_schedule() {
    let config =
        ClusterConfig::from_file(&repository().join("deploy/examples/erayzer-mixture.yaml"))
            .unwrap();
    for phase in [settings::Phase::Stage1, settings::Phase::Stage2] {
        let sampler = config.sampler(phase);
        let weights: Vec<(&str, f64)> = sampler
            .datasets
            .iter()
            .map(|d| (d.dataset.name(), d.weight))
            .collect();
        assert_eq!(
            weights,
            [
                ("dl3dv", 1.0),
                ("co3dv2", 0.25),
                ("re10k", 0.5),
                ("mvimgnet", 0.25),
                ("arkitscenes", 0.5),
                ("wildrgbd", 0.25),
                ("acid", 0.5),
            ]
        );
    }
    for (schedule, optimizer, steps) in [
        (&config.stage1.schedule, &config.stage1.optimizer, 100_000),
        (&config.stage2.schedule, &config.stage2.optimizer, 200_000),
    ] {
        assert_eq!(
            (schedule.initial_lr, schedule.peak_lr, schedule.final_lr),
            (0.0, 4e-4, 0.0)
        );
        assert_eq!((schedule.warmup_steps, schedule.total_steps), (3000, steps));
        assert_eq!(optimizer.skip_norm_above, Some(5.0));
    }
}

/// The example `deploy/examples/NAME`, read and checked.
fn example(name: &str) -> ClusterConfig {
    ClusterConfig::from_file(&repository().join("deploy/examples").join(name))
        .unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// A Table 3 example: a job that stops after stage 1, the model the table scores.
fn table3_column(name: &str) -> ClusterConfig {
    let column = example(name);
    assert_eq!(
        column.stop_after,
        LastStage::Stage1,
        "{name}: Table 3 is stage 1's"
    );
    column
}

#[test]
fn the_table_3_examples_differ_from_the_paper_only_in_objective_pose_size_and_views() {
    use settings::objective::ObjectiveVariant;
    let paper = example("paper.yaml");
    assert_eq!(paper.stop_after, LastStage::Stage2);
    for (name, variant, pose_dim) in [
        ("table3-xfactor.yaml", ObjectiveVariant::Transfer, 256),
        (
            "table3-unconstrained.yaml",
            ObjectiveVariant::Autoencode,
            256,
        ),
        ("table3-bottleneck.yaml", ObjectiveVariant::Autoencode, 16),
        ("table3-se3-plucker.yaml", ObjectiveVariant::Se3Plucker, 10),
    ] {
        let column = table3_column(name);
        assert_eq!(column.stage1.objective.variant, variant, "{name}");
        assert_eq!(column.stage2.objective.variant, variant, "{name}");
        let model = column.model_config().unwrap();
        assert_eq!(model.pose_dim, pose_dim, "{name}");
        let mut expected = paper.model_config().unwrap();
        expected.pose_dim = pose_dim;
        expected.pose_conditioning = variant.pose_conditioning();
        assert_eq!(
            model.pose_conditioning == settings::model::PoseConditioning::PluckerRays,
            name == "table3-se3-plucker.yaml",
            "{name}"
        );
        assert_eq!(model, expected, "{name}");
        assert_eq!(column.stage1.schedule, paper.stage1.schedule, "{name}");
        assert_eq!(column.stage2.schedule, paper.stage2.schedule, "{name}");
        assert_eq!(
            column.sampler(settings::Phase::Stage1),
            paper.sampler(settings::Phase::Stage1)
        );
        assert_eq!(
            (column.stage1.global_batch, column.stage1.steps),
            (paper.stage1.global_batch, paper.stage1.steps)
        );
    }
    for (name, variant) in [
        (
            "table3-extra-view-decoder.yaml",
            ObjectiveVariant::ExtraViewDecoder,
        ),
        (
            "table3-extra-view-encoder-decoder.yaml",
            ObjectiveVariant::ExtraViewEncoderDecoder,
        ),
    ] {
        let column = table3_column(name);
        assert_eq!(column.stage1.objective.variant, variant, "{name}");
        assert_eq!(
            column.stage2.objective.variant,
            ObjectiveVariant::Transfer,
            "{name}: stage 2 is XFactor's"
        );
        assert_eq!(
            column.model_config().unwrap(),
            paper.model_config().unwrap(),
            "{name}"
        );
        assert_eq!(column.sampler(settings::Phase::Stage1).frames, 3, "{name}");
        assert_eq!(
            column.sampler(settings::Phase::Stage2),
            paper.sampler(settings::Phase::Stage2),
            "{name}"
        );
        assert_eq!(column.stage1.schedule, paper.stage1.schedule, "{name}");
        assert_eq!(column.stage2.schedule, paper.stage2.schedule, "{name}");
    }
}
