//! The cluster YAML: good files resolve, bad ones are refused naming key, line and rule.

use super::*;

pub(super) const GOOD: &str = "job: demo
auth:
  token: abc
model:
  preset: tiny
  image_size: 32
data:
  datasets:
    - kind: re10k
      uri: /data/re10k
      stage1: {weight: 2, window_begin: 3, window_end: 9}
stage1:
  steps: 10
  global_batch: 8
  micro_batch: 4
  lpips_weight: 0
stage2:
  steps: 5
  global_batch: 8
  micro_batch: 2
  lpips_weight: 0
checkpoint:
  uri: /tmp/ckpt
  every: 5
";

fn error_of(yaml: &str) -> String {
    ClusterConfig::from_yaml(yaml, "cluster.yaml")
        .expect_err("the YAML must be refused")
        .to_string()
}

#[test]
fn a_good_file_resolves_with_paper_defaults_where_silent() {
    let config = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
    assert_eq!(config.stage1.steps, 10);
    assert_eq!(config.stage1.optimizer, AdamWConfig::default());
    assert_eq!(config.stage1.schedule.total_steps, 10);
    assert_eq!(config.stage1.schedule.peak_lr, 4e-4);
    assert_eq!(config.workers.expected.0, 2);
    let sampler = config.sampler(Phase::Stage1);
    assert_eq!(sampler.datasets.len(), 1);
    assert_eq!(sampler.datasets[0].weight, 2.0);
    assert_eq!(sampler.datasets[0].window_end, 9);
    let stage2 = config.sampler(Phase::Stage2);
    assert_eq!(
        stage2.datasets[0].window_end, 200,
        "paper default for RE10K"
    );
    assert_eq!(stage2.frames, 6);
    assert_eq!(config.auth.resolve().unwrap(), "abc");
}

#[test]
fn an_unknown_key_is_named_with_its_line() {
    let yaml = GOOD.replace("  micro_batch: 2\n", "  micro_batch: 2\n  micro_bacth: 3\n");
    let error = error_of(&yaml);
    assert!(error.contains("micro_bacth"), "{error}");
    assert!(error.contains("stage2"), "{error}");
    assert!(error.contains("line 21"), "{error}");
    assert!(error.contains("expected one of"), "{error}");
}

#[test]
fn the_evaluation_section_takes_defaults_and_names_unknown_keys() {
    let config = ClusterConfig::from_yaml(&format!("{GOOD}evaluate: {{tps_pairs: 4}}\n"), "t.yaml")
        .unwrap_or_else(|e| panic!("{e}"));
    let spec = config.evaluate.expect("an evaluation");
    assert_eq!(spec.tps_pairs, 4);
    assert_eq!(spec.probe, EvaluationSpec::default().probe);
    let error = error_of(&format!("{GOOD}evaluate:\n  tps_pairz: 4\n"));
    assert!(error.contains("tps_pairz"), "{error}");
    assert!(error.contains("evaluate"), "{error}");
    assert!(error.contains("line"), "{error}");
    let limits = error_of(&format!(
        "{GOOD}evaluate:\n  scenes: 3\n  probe: {{test_scenes: 3}}\n"
    ));
    assert!(limits.contains("evaluate.probe.test_scenes"), "{limits}");
    assert!(limits.contains("line"), "{limits}");
}

#[test]
fn the_sequence_protocol_takes_one_entry_per_dataset_and_names_a_bad_length() {
    let entry = "  sequences:\n    - {kind: acid, uri: s3://bucket/acid, length: 12, count: 50}\n";
    let config = ClusterConfig::from_yaml(&format!("{GOOD}evaluate:\n{entry}"), "t.yaml")
        .unwrap_or_else(|e| panic!("{e}"));
    let protocol = &config.evaluate.expect("an evaluation").sequences[0];
    assert_eq!(
        (
            protocol.kind,
            protocol.uri.as_str(),
            protocol.length,
            protocol.count
        ),
        (
            settings::data::DatasetKind::Acid,
            "s3://bucket/acid",
            12,
            50
        )
    );
    let short = error_of(&format!(
        "{GOOD}evaluate:\n{}",
        entry.replace("length: 12", "length: 1")
    ));
    assert!(short.contains("evaluate.sequences[0].length"), "{short}");
    let missing = error_of(&format!(
        "{GOOD}evaluate:\n{}",
        entry.replace(", count: 50", "")
    ));
    assert!(missing.contains("count"), "{missing}");
}

#[test]
fn bad_values_name_the_key_the_line_and_the_expectation() {
    let zero = error_of(&GOOD.replace("  steps: 10", "  steps: 0"));
    assert!(zero.contains("stage1.steps"), "{zero}");
    assert!(zero.contains("line 13"), "{zero}");
    assert!(zero.contains("positive whole number"), "{zero}");

    let negative = error_of(&GOOD.replace("weight: 2,", "weight: -1,"));
    assert!(
        negative.contains("data.datasets[0].stage1.weight"),
        "{negative}"
    );
    assert!(negative.contains("line 11"), "{negative}");
    assert!(negative.contains(">= 0"), "{negative}");

    let kind = error_of(&GOOD.replace("kind: re10k", "kind: imagenet"));
    assert!(kind.contains("unknown variant `imagenet`"), "{kind}");
    assert!(kind.contains("line 9"), "{kind}");

    let batch = error_of(&GOOD.replace("  micro_batch: 4", "  micro_batch: 3"));
    assert!(batch.contains("multiple of micro_batch 3"), "{batch}");
    assert!(batch.contains("stage1.micro_batch"), "{batch}");
    assert!(batch.contains("line 15"), "{batch}");

    let text = error_of(&GOOD.replace("every: 5", "every: often"));
    assert!(text.contains("checkpoint.every"), "{text}");
    assert!(text.contains("invalid type"), "{text}");
}

#[test]
fn lpips_without_weights_and_inconsistent_workers_are_refused() {
    let lpips = error_of(&GOOD.replace("  lpips_weight: 0\nstage2", "  lpips_weight: 0.5\nstage2"));
    assert!(lpips.contains("lpips_weights"), "{lpips}");
    let workers = error_of(&format!("{GOOD}workers:\n  expected: 2\n  minimum: 3\n"));
    assert!(
        workers.contains("workers.minimum (3) exceeds workers.expected (2)"),
        "{workers}"
    );
    let malformed = error_of("job: [unclosed");
    assert!(malformed.contains("line 1"), "{malformed}");
    let missing = error_of(&GOOD.replace("checkpoint:\n  uri: /tmp/ckpt\n  every: 5\n", ""));
    assert!(missing.contains("missing field `checkpoint`"), "{missing}");
}

#[test]
fn a_token_variable_that_is_not_set_is_named() {
    let yaml = GOOD.replace(
        "  token: abc",
        "  token_env: XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET",
    );
    let config = ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap();
    let error = config.auth.resolve().unwrap_err().to_string();
    assert!(
        error.contains("XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET"),
        "{error}"
    );
}

#[test]
fn a_viewing_token_is_read_as_the_job_token_is() {
    let plain = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
    assert_eq!(plain.viewing, None);
    let inline = format!("{GOOD}viewing:\n  token: look-only\n");
    let config = ClusterConfig::from_yaml(&inline, "cluster.yaml").unwrap();
    let viewing = config.viewing.expect("a viewing token");
    assert_eq!(viewing.0.resolve().unwrap(), "look-only");
    let from_env = format!("{GOOD}viewing:\n  token_env: XFACTOR_TEST_VIEW_TOKEN_NOT_SET\n");
    let config = ClusterConfig::from_yaml(&from_env, "cluster.yaml").unwrap();
    let error = config.viewing.unwrap().0.resolve().unwrap_err().to_string();
    assert!(error.contains("XFACTOR_TEST_VIEW_TOKEN_NOT_SET"), "{error}");
    let unknown = error_of(&format!("{GOOD}viewing:\n  password: x\n"));
    assert!(unknown.contains("viewing"), "{unknown}");
}

#[test]
fn durations_and_counts_out_of_bounds_are_refused_with_key_and_line() {
    let huge = error_of(&format!("{GOOD}workers:\n  heartbeat_timeout_s: 1e20\n"));
    assert!(huge.contains("workers.heartbeat_timeout_s"), "{huge}");
    assert!(huge.contains("30 days"), "{huge}");
    assert!(huge.contains("line 26"), "{huge}");
    for key in [
        "heartbeat_interval_s",
        "heartbeat_timeout_s",
        "quorum_timeout_s",
        "regroup_grace_s",
        "stall_timeout_s",
        "exclusion_s",
    ] {
        let error = error_of(&format!("{GOOD}workers:\n  {key}: 1e300\n"));
        assert!(error.contains(&format!("workers.{key}")), "{error}");
    }
    let crowd = error_of(&format!("{GOOD}workers:\n  expected: 100000\n"));
    assert!(crowd.contains("workers.expected"), "{crowd}");
    let small = error_of(&format!("{GOOD}workers:\n  expected: 16\n"));
    assert!(small.contains("stage1.global_batch"), "{small}");
    assert!(small.contains("16 workers"), "{small}");
    assert!(small.contains("line 14"), "{small}");
}

#[test]
fn model_dimensions_override_the_preset_and_a_broken_rule_names_key_and_line() {
    let wide = GOOD.replace(
        "  image_size: 32\n",
        "  image_size: 32\n  width: 48\n  num_heads: 3\n  pose_layers: 2\n  pose_dim: 16\n",
    );
    let config = ClusterConfig::from_yaml(&wide, "cluster.yaml").unwrap();
    let model = config.model_config().unwrap();
    assert_eq!(
        (
            model.width,
            model.num_heads,
            model.pose_layers,
            model.pose_dim
        ),
        (48, 3, 2, 16)
    );
    assert_eq!(model.render_layers, XFactorConfig::tiny(32).render_layers);

    let heads = error_of(&GOOD.replace("  image_size: 32\n", "  image_size: 32\n  num_heads: 3\n"));
    assert!(heads.contains("model.num_heads"), "{heads}");
    assert!(heads.contains("divisible by 4 (2D RoPE)"), "{heads}");
    assert!(heads.contains("line 7"), "{heads}");

    let patch = error_of(&GOOD.replace("  image_size: 32\n", "  image_size: 30\n"));
    assert!(patch.contains("model.image_size"), "{patch}");
    assert!(patch.contains("line 6"), "{patch}");

    let layers = error_of(&GOOD.replace(
        "  image_size: 32\n",
        "  image_size: 32\n  render_layers: 0\n",
    ));
    assert!(layers.contains("model.render_layers"), "{layers}");
    assert!(layers.contains("must be positive"), "{layers}");
}

#[test]
fn the_erayzer_recipe_sets_its_schedule_and_skip_and_explicit_keys_win() {
    let erayzer = GOOD.replace(
        "stage1:\n  steps: 10\n",
        "stage1:\n  recipe: erayzer\n  steps: 10000\n",
    );
    let config = ClusterConfig::from_yaml(&erayzer, "cluster.yaml").unwrap();
    let schedule = &config.stage1.schedule;
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * b.abs().max(1e-9);
    assert_eq!(schedule.learning_rate(0), 0.0);
    assert!(close(schedule.learning_rate(1500), 2e-4));
    assert!(close(schedule.learning_rate(3000), 4e-4));
    assert!(close(schedule.learning_rate(6500), 2e-4));
    assert!(schedule.learning_rate(10_000).abs() < 1e-12);
    assert_eq!(config.stage1.optimizer.skip_norm_above, Some(5.0));
    assert_eq!(config.stage1.optimizer.clip_norm, Some(1.0));
    assert_eq!(
        config.stage2.optimizer.skip_norm_above, None,
        "stage 2 keeps XFactor's"
    );

    let short = GOOD.replace(
        "stage1:\n  steps: 10\n",
        "stage1:\n  recipe: erayzer\n  steps: 10\n",
    );
    let config = ClusterConfig::from_yaml(&short, "cluster.yaml").unwrap();
    assert_eq!(config.stage1.schedule.warmup_steps, 10);

    let explicit = erayzer.replace(
        "  lpips_weight: 0\nstage2",
        "  lpips_weight: 0\n  optimizer: {beta1: 0.9, beta2: 0.99, epsilon: 1.0e-8, weight_decay: 0.05, clip_norm: 1.0, skip_norm_above: null}\nstage2",
    );
    let config = ClusterConfig::from_yaml(&explicit, "cluster.yaml").unwrap();
    assert_eq!(config.stage1.optimizer.skip_norm_above, None);
    assert_eq!(config.stage1.schedule.peak_lr, 4e-4);

    let unknown = error_of(&GOOD.replace(
        "stage1:\n  steps: 10\n",
        "stage1:\n  recipe: rayzer\n  steps: 10\n",
    ));
    assert!(unknown.contains("unknown variant `rayzer`"), "{unknown}");
}

#[test]
fn extra_view_variants_draw_three_frames_in_stage_1_and_are_refused_in_stage_2() {
    let extra = GOOD.replace(
        "  lpips_weight: 0\nstage2",
        "  lpips_weight: 0\n  objective: {variant: extra_view_encoder_decoder}\nstage2",
    );
    let config = ClusterConfig::from_yaml(&extra, "cluster.yaml").unwrap();
    assert_eq!(config.sampler(Phase::Stage1).frames, 3);
    assert_eq!(config.sampler(Phase::Stage2).frames, 6);
    let refused = error_of(&GOOD.replace(
        "  lpips_weight: 0\ncheckpoint",
        "  lpips_weight: 0\n  objective: {variant: extra_view_decoder}\ncheckpoint",
    ));
    assert!(refused.contains("stage2.objective.variant"), "{refused}");
}

#[test]
fn stage_2_with_fewer_than_three_views_is_refused_naming_the_key() {
    let refused = error_of(&GOOD.replace(
        "  lpips_weight: 0\ncheckpoint",
        "  lpips_weight: 0\n  objective: {views: 2}\ncheckpoint",
    ));
    assert!(
        refused.contains("stage2.objective.views: 2 is fewer than 3"),
        "{refused}"
    );
}

#[test]
fn se3_plucker_in_either_stage_builds_a_ray_conditioned_model() {
    use settings::model::{CAMERA_VECTOR_VALUES, PoseConditioning};
    let plain = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
    assert_eq!(
        plain.model_config().unwrap().pose_conditioning,
        PoseConditioning::Latent
    );
    let in_stage1 = GOOD.replace(
        "  lpips_weight: 0\nstage2",
        "  lpips_weight: 0\n  objective: {variant: se3_plucker}\nstage2",
    );
    let in_stage2 = GOOD.replace(
        "  lpips_weight: 0\ncheckpoint",
        "  lpips_weight: 0\n  objective: {variant: se3_plucker}\ncheckpoint",
    );
    for text in [&in_stage1, &in_stage2] {
        let model = ClusterConfig::from_yaml(text, "cluster.yaml")
            .unwrap()
            .model_config()
            .unwrap();
        assert_eq!(model.pose_conditioning, PoseConditioning::PluckerRays);
        assert_eq!(model.pose_dim, CAMERA_VECTOR_VALUES);
    }
    let refused = error_of(&in_stage1.replace("preset: tiny", "preset: tiny\n  pose_dim: 16"));
    assert!(
        refused.contains("model.pose_dim: model config: pose_dim 16 must be 10")
            && refused.contains("se3_plucker"),
        "{refused}"
    );
}

#[test]
fn precision_and_devices_are_read_and_a_bad_device_set_is_named() {
    let yaml = GOOD.replace(
        "  image_size: 32\n",
        "  image_size: 32\n  precision: bf16\n",
    ) + "workers:\n  devices: [0, 2]\n";
    let config = ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap();
    assert_eq!(
        config.model_config().unwrap().precision,
        settings::model::Precision::Bf16
    );
    assert_eq!(config.workers.devices, DeviceSet::Ids(vec![0, 2]));
    let defaults = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
    assert_eq!(defaults.workers.devices, DeviceSet::All);
    assert_eq!(
        defaults.model_config().unwrap().precision,
        settings::model::Precision::F32
    );
    let bad = error_of(&(GOOD.to_string() + "workers:\n  devices: [1, 1]\n"));
    assert!(
        bad.contains("workers") && bad.contains("not a device set") && bad.contains("line 26"),
        "{bad}"
    );
    let bad = error_of(&GOOD.replace("  image_size: 32\n", "  image_size: 32\n  precision: f8\n"));
    assert!(bad.contains("model.precision"), "{bad}");
}

#[test]
fn the_compute_type_is_read_defaults_to_f32_and_a_bad_one_is_named() {
    let yaml = GOOD.replace("  image_size: 32\n", "  image_size: 32\n  compute: bf16\n");
    let config = ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap();
    let model = config.model_config().unwrap();
    assert_eq!(model.compute, settings::model::Precision::Bf16);
    assert_eq!(model.precision, settings::model::Precision::F32);
    let defaults = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
    assert_eq!(
        defaults.model_config().unwrap().compute,
        settings::model::Precision::F32
    );
    let bad = error_of(&GOOD.replace("  image_size: 32\n", "  image_size: 32\n  compute: f8\n"));
    assert!(bad.contains("model.compute"), "{bad}");
    let f16 = error_of(&GOOD.replace("  image_size: 32\n", "  image_size: 32\n  compute: f16\n"));
    assert!(
        f16.contains("model.compute") && f16.contains("loss scaling"),
        "{f16}"
    );
}

#[test]
fn the_data_path_settings_default_to_auto_checksums_and_a_float32_wire() {
    let config = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
    assert_eq!(config.workers.checksum_every, ChecksumEvery::Auto);
    assert_eq!(config.workers.allreduce_wire, WireFormat::F32);
    let yaml = format!("{GOOD}workers:\n  checksum_every: 4\n  allreduce_wire: bf16\n");
    let config = ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap();
    assert_eq!(config.workers.checksum_every, ChecksumEvery::Steps(4));
    assert_eq!(config.workers.allreduce_wire, WireFormat::Bf16);
    assert_eq!(config.workers.allreduce_lanes, 1);
    let yaml = format!("{GOOD}workers:\n  allreduce_lanes: 4\n");
    let lanes = ClusterConfig::from_yaml(&yaml, "cluster.yaml").unwrap();
    assert_eq!(lanes.workers.allreduce_lanes, 4);
    let too_many = error_of(&format!("{GOOD}workers:\n  allreduce_lanes: 65\n"));
    assert!(
        too_many.contains("workers.allreduce_lanes") && too_many.contains("at most 64"),
        "{too_many}"
    );
    let in_the_clear = error_of(&format!("{GOOD}workers:\n  allreduce_lanes: 0\n"));
    assert!(
        in_the_clear.contains("workers.allreduce_lanes") && in_the_clear.contains("needs `tls:`"),
        "{in_the_clear}"
    );
    let wire = error_of(&format!("{GOOD}workers:\n  allreduce_wire: fp8\n"));
    assert!(
        wire.contains("workers.allreduce_wire") && wire.contains("line 26"),
        "{wire}"
    );
    let zero = error_of(&format!("{GOOD}workers:\n  checksum_every: 0\n"));
    assert!(zero.contains("checksum_every"), "{zero}");
}

#[test]
fn stop_after_takes_either_stage_and_names_itself_when_wrong() {
    let both = ClusterConfig::from_yaml(GOOD, "cluster.yaml").unwrap();
    assert_eq!(both.stop_after, LastStage::Stage2);
    let first = ClusterConfig::from_yaml(&format!("{GOOD}stop_after: stage1\n"), "c.yaml").unwrap();
    assert_eq!(first.stop_after, LastStage::Stage1);
    let wrong = error_of(&format!("{GOOD}stop_after: stage3\n"));
    assert!(wrong.contains("stop_after"), "{wrong}");
    assert!(wrong.contains("unknown variant `stage3`"), "{wrong}");
}
