//! No cluster YAML can panic the loader: every value of a good file and of a full one (every
//! `workers:` timing, the evaluation, the model's sizes) is replaced in turn by extreme
//! numbers and wrong types, and the text is mutated character by character; the loader must
//! return a configuration or an error each time. Deterministic: the mutations come from a
//! fixed seed.

use std::panic::{AssertUnwindSafe, catch_unwind};

use super::ClusterConfig;

/// Values that have panicked loaders elsewhere: too large for a clock or a count, not a
/// number at all, negative, or of another type.
const EXTREMES: [&str; 14] = [
    "1e300",
    "-1",
    ".nan",
    ".inf",
    "-.inf",
    "18446744073709551616",
    "0",
    "-0.0",
    "4294967297",
    "[]",
    "{}",
    "~",
    "\"\"",
    "1e-320",
];

const FULL: &str = "job: demo
seed: 7
auth:
  token: abc
model:
  preset: tiny
  image_size: 32
  width: 48
  num_heads: 3
  pose_dim: 16
  global_tokens: 4
data:
  generated: {scenes: 4, trajectories: 4, frames: 12}
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
workers:
  expected: 2
  minimum: 1
  threads: 1
  heartbeat_interval_s: 0.5
  heartbeat_timeout_s: 5
  quorum_timeout_s: 300
  regroup_grace_s: 2
  stall_timeout_s: 120
  exclusion_s: 30
  checksum_every: 1
evaluate:
  seed: 7
  scenes: 3
  trajectories: 4
  frames: 6
  tps_pairs: 8
  reconstruction_sequences: 4
  probe: {steps: 10, batch: 4, width: 64, test_scenes: 1}
";

/// Loads `yaml`; a panic fails the test with the text that caused it.
fn loads_or_refuses(yaml: &str) {
    let outcome = catch_unwind(AssertUnwindSafe(|| {
        let _ = ClusterConfig::from_yaml(yaml, "cluster.yaml");
    }));
    assert!(outcome.is_ok(), "the loader panicked on:\n{yaml}");
}

#[test]
fn the_full_file_loads() {
    ClusterConfig::from_yaml(FULL, "cluster.yaml").expect("the full file is valid");
}

#[test]
fn every_value_replaced_by_an_extreme_is_loaded_or_refused() {
    for text in [super::tests::GOOD, FULL] {
        let lines: Vec<&str> = text.lines().collect();
        for (index, line) in lines.iter().enumerate() {
            let Some((key, value)) = line.split_once(": ") else {
                continue;
            };
            for extreme in EXTREMES {
                let mut changed = lines.clone();
                let replaced = format!("{key}: {extreme}");
                changed[index] = &replaced;
                loads_or_refuses(&(changed.join("\n") + "\n"));
                let inline = value.replace(|c: char| c.is_ascii_digit(), "9");
                let replaced_digits = format!("{key}: {inline}");
                changed[index] = &replaced_digits;
                loads_or_refuses(&(changed.join("\n") + "\n"));
            }
        }
    }
}

#[test]
fn character_mutations_are_loaded_or_refused() {
    let mut state: u64 = 0x5eed;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let alphabet: Vec<char> = ":-{}[], \n9.e\"'#&*!|>".chars().collect();
    for _ in 0..2000 {
        let mut chars: Vec<char> = FULL.chars().collect();
        for _ in 0..1 + next() % 4 {
            let at = (next() % chars.len() as u64) as usize;
            let with = alphabet[(next() % alphabet.len() as u64) as usize];
            match next() % 3 {
                0 => chars[at] = with,
                1 => chars.insert(at, with),
                _ => {
                    chars.remove(at);
                }
            }
        }
        loads_or_refuses(&chars.into_iter().collect::<String>());
    }
}
