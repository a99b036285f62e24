//! E-RayZer's evaluation protocol on a tiny RE10K tree: the first test sequences long enough
//! for the fixed length, their frames equally spaced with first and last, shorter and
//! training sequences passed over; the evaluation reports each dataset's reconstruction.

mod common;

use std::path::Path;

use burn::tensor::Device;
use data::decode::decode_frame;
use evaluation::evaluate::CheckpointUnderTest;
use evaluation::run_evaluation;
use evaluation::sequences::load_protocol;
use settings::data::DatasetKind;
use settings::evaluation::{EvaluationSpec, ProbeSpec, SequenceProtocol};
use trainer_core::XFactorConfig;

const SIDE: u32 = 16;

/// A PNG frame whose colour encodes `(sequence, index)`, so a loaded frame names its source.
fn frame_png(sequence: u8, index: u32) -> Vec<u8> {
    let image = image::RgbImage::from_fn(SIDE, SIDE, |x, y| {
        image::Rgb([(index * 8) as u8, sequence * 40, ((x + y) * 4) as u8])
    });
    let mut bytes = Vec::new();
    image::DynamicImage::ImageRgb8(image)
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .unwrap();
    bytes
}

/// RE10K's layout: test sequences `a` (30 frames), `b` (11, shorter than the protocol's 12),
/// `c` (20) and `d` (25); a training sequence `t` (40).
fn re10k_tree(root: &Path) {
    for (split, name, frames, tag) in [
        ("test", "a", 30, 1u8),
        ("test", "b", 11, 2),
        ("test", "c", 20, 3),
        ("test", "d", 25, 4),
        ("train", "t", 40, 5),
    ] {
        let dir = root.join(split).join("images").join(name);
        std::fs::create_dir_all(&dir).unwrap();
        for i in 0..frames {
            std::fs::write(dir.join(format!("{i}.png")), frame_png(tag, i)).unwrap();
        }
    }
}

fn protocol(root: &Path, length: usize, count: usize) -> SequenceProtocol {
    SequenceProtocol {
        kind: DatasetKind::Re10k,
        uri: root.display().to_string(),
        length,
        count,
    }
}

#[test]
fn the_first_long_enough_test_sequences_give_equally_spaced_frames_with_first_and_last() {
    let dir = tempfile::tempdir().unwrap();
    re10k_tree(dir.path());
    let set = load_protocol(&protocol(dir.path(), 12, 2), SIDE as usize).unwrap();
    let ids: Vec<&str> = set.sequences.iter().map(|s| s.id.as_str()).collect();
    assert_eq!(
        ids,
        ["a", "c"],
        "b is too short, d beyond the count, t trains"
    );
    assert_eq!(set.skipped_short, 1);
    for (sequence, len, tag) in [(&set.sequences[0], 30u32, 1u8), (&set.sequences[1], 20, 3)] {
        let indices = &sequence.frame_indices;
        assert_eq!(indices.len(), 12);
        assert_eq!((indices[0], indices[11]), (0, len as usize - 1));
        let gaps: Vec<usize> = indices.windows(2).map(|w| w[1] - w[0]).collect();
        let (low, high) = (gaps.iter().min().unwrap(), gaps.iter().max().unwrap());
        assert!(high - low <= 1, "equally spaced: {indices:?}");
        for (&index, image) in indices.iter().zip(&sequence.frames) {
            let expected =
                decode_frame(&frame_png(tag, index as u32), "expected", SIDE as usize).unwrap();
            assert_eq!(
                image.pixels, expected.pixels,
                "{} frame {index}",
                sequence.id
            );
        }
    }

    let error = load_protocol(&protocol(dir.path(), 31, 2), SIDE as usize)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("no test sequence of at least 31 frames (4 test sequences)"),
        "{error}"
    );
}

#[test]
fn the_evaluation_reports_each_protocol_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("re10k");
    re10k_tree(&data);
    let config = XFactorConfig::tiny(SIDE as usize);
    let weights = common::untrained_checkpoint(&config, 1, dir.path());
    let spec = EvaluationSpec {
        scenes: 2,
        trajectories: 2,
        frames: 3,
        tps_pairs: 1,
        tps_frames: 2,
        reconstruction_sequences: 1,
        probe: ProbeSpec {
            steps: 1,
            batch: 2,
            test_scenes: 1,
            ..ProbeSpec::default()
        },
        compare_untrained: false,
        sequences: vec![protocol(&data, 12, 3)],
        ..EvaluationSpec::default()
    };
    let out = dir.path().join("report");
    let checkpoint = CheckpointUnderTest {
        label: "checkpoint".into(),
        weights,
        step: None,
        context_views: 1,
    };
    let report = run_evaluation(&spec, &[checkpoint], &out, &Device::flex()).unwrap();
    let sequences = &report.stages[0].trained.sequences;
    let [set] = sequences.as_slice() else {
        panic!("one dataset: {sequences:?}");
    };
    assert_eq!(
        (set.kind, set.length, set.sequences, set.skipped_short),
        (DatasetKind::Re10k, 12, 3, 1)
    );
    assert_eq!(
        set.reconstruction.frames,
        3 * 11,
        "every frame after the first"
    );
    assert!(set.reconstruction.psnr.is_finite() && set.reconstruction.psnr > 0.0);
    println!(
        "protocol_sequences={} frames={} psnr={:.2} ssim={:.4}",
        set.sequences, set.reconstruction.frames, set.reconstruction.psnr, set.reconstruction.ssim
    );
    let markdown = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        markdown.contains("| checkpoint, 1 context view(s) | trained | re10k | 12 | 3 | 1 | 33 |"),
        "{markdown}"
    );
    assert!(out.join("checkpoint_trained_sequences_re10k.png").is_file());
}
