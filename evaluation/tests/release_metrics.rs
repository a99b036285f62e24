//! Rac/Tac and the release's AUCs against `release-ops.*`: 45 pairs of errors and the figures
//! the release's `get_camera_metrics` computed from them.

mod common;

use evaluation::metrics::{CameraMetrics, PairError};

/// The float64 tensor `name` of a safetensors file, read from its JSON header directly.
fn f64_tensor(bytes: &[u8], name: &str) -> Vec<f64> {
    let header_len = u64::from_le_bytes(bytes[..8].try_into().expect("8-byte length")) as usize;
    let header: serde_json::Value =
        serde_json::from_slice(&bytes[8..8 + header_len]).expect("JSON header");
    let entry = &header[name];
    assert_eq!(entry["dtype"], "F64", "{name}");
    let offsets = entry["data_offsets"].as_array().expect("offsets");
    let (start, end) = (
        offsets[0].as_u64().expect("start") as usize,
        offsets[1].as_u64().expect("end") as usize,
    );
    bytes[8 + header_len + start..8 + header_len + end]
        .chunks_exact(8)
        .map(|w| f64::from_le_bytes(w.try_into().expect("8 bytes")))
        .collect()
}

#[test]
fn every_accuracy_and_auc_matches_the_release() {
    let path = common::shared_fixture("release-ops.safetensors");
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(path.with_extension("json")).expect("release-ops.json"),
    )
    .expect("valid JSON");
    let rotation = f64_tensor(&bytes, "metrics.rot_err_deg");
    let translation = f64_tensor(&bytes, "metrics.trans_err_deg");
    let errors: Vec<PairError> = rotation
        .iter()
        .zip(&translation)
        .map(|(&rotation, &translation)| PairError {
            rotation,
            translation,
        })
        .collect();
    let ours: std::collections::BTreeMap<String, f64> = CameraMetrics::from_errors(&errors)
        .release_figures()
        .into_iter()
        .collect();
    let expected = json["metrics"].as_object().expect("metrics object");
    let mut worst = 0.0f64;
    for (name, value) in expected {
        let theirs = value.as_f64().expect("number");
        let mine = *ours
            .get(name)
            .unwrap_or_else(|| panic!("we report no `{name}`"));
        worst = worst.max((mine - theirs).abs());
        assert!(
            (mine - theirs).abs() <= 1e-9,
            "{name}: ours {mine}, release {theirs}"
        );
    }
    println!(
        "release metrics: {} figures, max_abs_err={worst:.2e}",
        expected.len()
    );
    assert_eq!(expected.len(), 30);
}
