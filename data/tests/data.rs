//! Indexing through object_store (in-memory, plain path, `file://`), error cases, and sampling
//! batches from the two real example videos laid out as RE10K.

#[path = "../../trainer-core/tests/common/mod.rs"]
mod common;

use std::path::Path;

use data::SamplerConfig;
use data::index::{IndexError, index};
use data::source::{DatasetSource, IndexedDataset};
use data::store::DataRoot;
use data::{BatchSource, Samples};
use data::{DatasetKind, Manifest, Split};
use image::{ImageFormat, RgbImage};

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

fn png(seed: u8) -> Vec<u8> {
    let image = RgbImage::from_fn(24, 16, |x, y| image::Rgb([x as u8 * 9, y as u8 * 13, seed]));
    let mut bytes = std::io::Cursor::new(Vec::new());
    image.write_to(&mut bytes, ImageFormat::Png).unwrap();
    bytes.into_inner()
}

/// Writes a tiny tree of each layout into `root`.
async fn write_trees(roots: &[(DatasetKind, &DataRoot)]) {
    for (kind, root) in roots {
        let mut files: Vec<String> = Vec::new();
        match kind {
            DatasetKind::Re10k => {
                files.extend((0..10).map(|i| format!("train/images/abc/{i:03}.png")));
                files.extend((0..4).map(|i| format!("train/images/tiny/{i:03}.png")));
            }
            DatasetKind::Dl3dv => {
                files.extend((0..10).map(|i| format!("training_256/1K/seq/images_8/f{i:02}.png")));
                files.push("training_256/1K/seq/transforms.json".into());
            }
            DatasetKind::Mvimgnet => {
                files.extend((0..10).map(|i| format!("cup/s1/images/{i:03}.png")));
                files.push("cup/s1/sparse/0/points3D.bin".into());
            }
            DatasetKind::Co3dv2 => {
                files.extend((0..10).map(|i| format!("cup/1_2_3/images/frame{i:06}.png")));
            }
            DatasetKind::Arkitscenes => {
                files.extend(
                    (0..10)
                        .map(|i| format!("raw/Training/4106/lowres_wide/4106_{}.250.png", 8 + i)),
                );
                files.push("raw/Training/4106/lowres_wide.traj".into());
            }
            DatasetKind::Wildrgbd => {
                files.extend((0..10).map(|i| format!("cup/scenes/scene_001/rgb/{i:05}.png")));
                files.push("cup/scenes/scene_001/cam_poses.txt".into());
            }
            DatasetKind::Acid => {
                files.extend((0..10).map(|i| format!("train/images/0a1b2c/{}.png", 1000 * i)));
                files.push("train/cameras/0a1b2c.txt".into());
            }
        }
        for (i, file) in files.iter().enumerate() {
            root.write(file, png(i as u8)).await.unwrap();
        }
    }
}

#[test]
fn every_layout_indexes_through_the_in_memory_store() {
    let rt = runtime();
    let roots: Vec<(DatasetKind, DataRoot)> = DatasetKind::ALL
        .iter()
        .map(|&k| (k, DataRoot::in_memory(k.name())))
        .collect();
    let refs: Vec<(DatasetKind, &DataRoot)> = roots.iter().map(|(k, r)| (*k, r)).collect();
    rt.block_on(write_trees(&refs));
    for (kind, root) in &roots {
        let indexed = rt.block_on(index(root, *kind)).unwrap();
        assert_eq!(indexed.manifest.sequences.len(), 1, "{kind:?}");
        assert_eq!(indexed.manifest.sequences[0].frames.len(), 10);
    }
}

#[test]
fn local_paths_and_file_uris_index_the_same_tree() {
    let rt = runtime();
    let dir = tempfile::tempdir().unwrap();
    let plain = DataRoot::open(dir.path().to_str().unwrap()).unwrap();
    rt.block_on(write_trees(&[(DatasetKind::Re10k, &plain)]));
    let uri = url::Url::from_directory_path(dir.path())
        .unwrap()
        .to_string();
    let via_uri = DataRoot::open(&uri).unwrap();
    let a = rt.block_on(index(&plain, DatasetKind::Re10k)).unwrap();
    let b = rt.block_on(index(&via_uri, DatasetKind::Re10k)).unwrap();
    assert_eq!(a.manifest, b.manifest);
    assert_eq!(a.skipped.len(), 1, "the 4-frame sequence");
}

#[test]
fn missing_empty_and_unreadable_roots_are_clear_errors() {
    let rt = runtime();
    let missing = DataRoot::open("/nonexistent/xfactor-data")
        .unwrap_err()
        .to_string();
    assert!(missing.contains("/nonexistent/xfactor-data"), "{missing}");
    let scheme = DataRoot::open("ftp://host/data").unwrap_err().to_string();
    assert!(scheme.contains("ftp://host/data"), "{scheme}");
    let dir = tempfile::tempdir().unwrap();
    let empty = DataRoot::open(dir.path().to_str().unwrap()).unwrap();
    let error = rt.block_on(index(&empty, DatasetKind::Co3dv2)).unwrap_err();
    assert!(matches!(error, IndexError::Empty { .. }), "{error}");
    let wrong = DataRoot::in_memory("memory://wrong-layout");
    rt.block_on(write_trees(&[(DatasetKind::Re10k, &wrong)]));
    let error = rt
        .block_on(index(&wrong, DatasetKind::Dl3dv))
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("memory://wrong-layout") && error.contains("no sequence"),
        "{error}"
    );
    // Frames one folder too shallow for each of E-RayZer's layouts: the error names the root
    // and the layout it looked for.
    for (kind, misplaced, expected) in [
        (
            DatasetKind::Arkitscenes,
            "Training/4106/4106_8.250.png",
            "lowres_wide/{video}_{seconds}.{ms}.png",
        ),
        (
            DatasetKind::Wildrgbd,
            "cup/scene_001/rgb/00000.png",
            "{category}/scenes/{scene}/rgb",
        ),
        (
            DatasetKind::Acid,
            "train/0a1b2c/00000.png",
            "{train|test}/images/{sequence}",
        ),
    ] {
        let root = DataRoot::in_memory(&format!("memory://malformed-{}", kind.name()));
        rt.block_on(async {
            for i in 0..10 {
                let path = misplaced
                    .replace("00000", &format!("{i:05}"))
                    .replace("8.250", &format!("{}.250", 8 + i));
                root.write(&path, png(i as u8)).await.unwrap();
            }
        });
        let error = rt.block_on(index(&root, kind)).unwrap_err().to_string();
        assert!(
            error.contains(&format!("malformed-{}", kind.name())) && error.contains(expected),
            "{error}"
        );
    }
}

/// The example videos as `train/images/{target,transfer}/NNN.jpg` of an RE10K root.
fn example_videos_as_re10k(rt: &tokio::runtime::Runtime) -> DataRoot {
    let root = DataRoot::in_memory("memory://example-videos");
    let videos = common::shared_fixture("example_videos");
    for video in ["target", "transfer"] {
        let mut names: Vec<_> = std::fs::read_dir(videos.join(video))
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        for name in names {
            let bytes = std::fs::read(Path::new(&videos).join(video).join(&name)).unwrap();
            rt.block_on(root.write(&format!("train/images/{video}/{name}"), bytes))
                .unwrap();
        }
    }
    root
}

/// A stage-1 training source over one RE10K root, at `size x size`.
fn stage1_re10k_source(root: DataRoot, manifest: Manifest, size: usize) -> DatasetSource {
    let dataset = IndexedDataset {
        kind: DatasetKind::Re10k,
        root,
        manifest,
    };
    DatasetSource::new(
        vec![dataset],
        SamplerConfig::stage1(),
        Split::Train,
        size,
        0,
    )
    .unwrap()
}

#[test]
fn example_videos_index_as_re10k_and_sample_into_batches() {
    let rt = runtime();
    let root = example_videos_as_re10k(&rt);
    let indexed = rt.block_on(index(&root, DatasetKind::Re10k)).unwrap();
    let ids: Vec<&str> = indexed
        .manifest
        .sequences
        .iter()
        .map(|s| s.id.as_str())
        .collect();
    assert_eq!(ids, vec!["target", "transfer"]);
    assert!(
        indexed
            .manifest
            .sequences
            .iter()
            .all(|s| s.frames.len() == 30 && s.split == Split::Train)
    );

    let source = stage1_re10k_source(root, indexed.manifest, 64);
    let Samples::Pairs(pairs) = source.samples(0, 0, 4).unwrap() else {
        panic!("stage-1 sampler gives pairs");
    };
    assert_eq!(pairs.len(), 4);
    for (a, b) in &pairs {
        assert_eq!((a.height, a.width, a.pixels.len()), (64, 64, 64 * 64 * 3));
        assert_ne!(a.pixels, b.pixels, "two different frames");
    }
    let again = source.samples(0, 0, 4).unwrap();
    let Samples::Pairs(again) = again else {
        unreachable!()
    };
    assert_eq!(pairs[3].0.pixels, again[3].0.pixels, "deterministic");
    assert_eq!(source.skipped_frames(), 0);
}

#[test]
fn corrupt_frames_are_skipped_and_counted() {
    let rt = runtime();
    let root = DataRoot::in_memory("memory://corrupt");
    for i in 0..12 {
        let bytes = if i % 3 == 0 {
            b"garbage".to_vec()
        } else {
            png(i)
        };
        rt.block_on(root.write(&format!("train/images/seq/{i:03}.png"), bytes))
            .unwrap();
    }
    let indexed = rt.block_on(index(&root, DatasetKind::Re10k)).unwrap();
    let source = stage1_re10k_source(root, indexed.manifest, 16);
    let Samples::Pairs(pairs) = source.samples(0, 0, 8).unwrap() else {
        unreachable!()
    };
    assert_eq!(pairs.len(), 8);
    assert!(
        source.skipped_frames() > 0,
        "some draws hit a corrupt frame"
    );
    for (a, _) in &pairs {
        assert!(
            a.pixels.iter().any(|&v| v != a.pixels[0]),
            "never a blank image"
        );
    }
}

#[test]
fn generated_scenes_write_an_re10k_tree_that_indexes_and_decodes() {
    use data::scenes::SceneConfig;
    use data::synthetic::SyntheticDataset;
    let rt = runtime();
    let config = SceneConfig {
        image_size: 32,
        ..SceneConfig::default()
    };
    let dataset = SyntheticDataset::generate(3, 2, 3, 12, &config);
    let root = DataRoot::in_memory("memory://generated");
    let written = rt
        .block_on(dataset.write_re10k(&root, Split::Train, config.fov_degrees))
        .unwrap();
    assert_eq!(written, 2 * 3 * 12);
    let indexed = rt.block_on(index(&root, DatasetKind::Re10k)).unwrap();
    assert_eq!(indexed.manifest.sequences.len(), 6);
    let sequence = &indexed.manifest.sequences[0];
    assert_eq!(sequence.id, "g3-s0_t0");
    assert_eq!(
        sequence.poses.as_deref(),
        Some("train/cameras/g3-s0_t0.txt")
    );
    let cameras = String::from_utf8(
        rt.block_on(root.read("train/cameras/g3-s0_t0.txt"))
            .unwrap(),
    )
    .unwrap();
    assert_eq!(cameras.lines().count(), 13, "header + one line per frame");
    assert_eq!(cameras.lines().nth(1).unwrap().split(' ').count(), 19);
    let bytes = rt.block_on(root.read(&sequence.frames[5])).unwrap();
    let frame = data::decode::decode_frame(&bytes, &sequence.frames[5], 32).unwrap();
    let original = &dataset.sequence(0, 0).unwrap().frames[5];
    let worst = frame
        .pixels
        .iter()
        .zip(&original.pixels)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(worst <= 1.0 / 255.0 + 1e-6, "PNG round trip off by {worst}");
}

#[test]
fn manifest_caches_are_reused_until_the_listing_changes() {
    use data::cache::{CacheError, CacheUse, load_or_index, read_cached};
    let rt = runtime();
    let root = DataRoot::in_memory("memory://cached");
    rt.block_on(write_trees(&[(DatasetKind::Re10k, &root)]));
    let (first, used) = rt
        .block_on(load_or_index(&root, DatasetKind::Re10k))
        .unwrap();
    assert_eq!(used, CacheUse::Rebuilt);
    let (again, used) = rt
        .block_on(load_or_index(&root, DatasetKind::Re10k))
        .unwrap();
    assert_eq!(used, CacheUse::Reused);
    assert_eq!(again, first);
    let read = rt
        .block_on(read_cached(&root, DatasetKind::Re10k, first.fingerprint))
        .unwrap();
    assert_eq!(read, first.manifest);
    let sequence = &first.manifest.sequences[0];
    let extra = sequence.frames[0].replace("000", "999");
    rt.block_on(root.write(&extra, png(9))).unwrap();
    let (changed, used) = rt
        .block_on(load_or_index(&root, DatasetKind::Re10k))
        .unwrap();
    assert_eq!(used, CacheUse::Rebuilt, "a new frame makes the cache stale");
    assert_ne!(changed.fingerprint, first.fingerprint);
    assert_eq!(
        changed.manifest.sequences[0].frames.len(),
        sequence.frames.len() + 1
    );
    let stale = rt
        .block_on(read_cached(&root, DatasetKind::Re10k, first.fingerprint))
        .unwrap_err();
    assert!(matches!(stale, CacheError::Stale { .. }), "{stale}");
    assert!(stale.to_string().contains("memory://cached"), "{stale}");
}

#[test]
fn a_read_that_never_returns_times_out_and_names_the_object() {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("stuck.png");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    let root = DataRoot::open(dir.path().to_str().unwrap())
        .unwrap()
        .with_read_timeout(std::time::Duration::from_millis(200));
    let started = std::time::Instant::now();
    let error = rt.block_on(root.read("stuck.png")).unwrap_err();
    let seconds = started.elapsed().as_secs_f64();
    let mut chain = error.to_string();
    let mut cause = std::error::Error::source(&error);
    while let Some(inner) = cause {
        chain.push_str(&format!(": {inner}"));
        cause = inner.source();
    }
    assert!(chain.contains("`stuck.png`"), "{chain}");
    assert!(chain.contains("no answer within 0.2 s"), "{chain}");
    // Three attempts of 0.2 s and the back-off between them, not forever.
    assert!(seconds < 10.0, "{seconds} s");
    // The blocked reads give up once a writer comes and goes; do not wait for them.
    drop(
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&fifo)
            .unwrap(),
    );
    rt.shutdown_background();
}
