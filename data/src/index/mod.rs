//! Indexers for the dataset layouts: XFactor's four as the authors' release reads them, and
//! the three more of E-RayZer's mixture:
//!
//! - RE10K: `{split}/images/{sequence}/*` (split `train` / `test`); camera files
//!   `{split}/cameras/{sequence}.txt` when present.
//! - DL3DV: `training_256/{part}/{sequence}/images_8/*` with `transforms.json` beside
//!   `images_8` (sequences without it are skipped); ids present under
//!   `test_256/benchmark_960p/` are the test split and never train.
//! - MVImgNet: `{category}/{scene}/images/NNN.jpg` (three-digit names); every scene counts (the
//!   release's COLMAP `sparse/` filter is switched off); the first 90% of scenes per category
//!   (sorted) train.
//! - CO3Dv2: `{category}/{sequence}/images/frameNNNNNN.jpg`, only the release's 51 categories
//!   ([`CO3DV2_CATEGORIES`]), sequences whose name starts with a digit; the first 90% per
//!   category train; `{category}/frame_annotations.jgz` when present.
//!
//! - ACID: RE10K's layout.
//! - ARKitScenes and WildRGB-D: see [`erayzer`].
//!
//! Frames are ordered by the number in their names (ARKitScenes: by timestamp); sequences
//! shorter than [`MIN_FRAMES`] are dropped everywhere.

use std::collections::{BTreeMap, BTreeSet};

use settings::data::DatasetKind;

use crate::frame_order::sort_frames;
use crate::manifest::{Manifest, Sequence, Split};
use crate::store::{DataRoot, StoreError};

mod erayzer;

/// Folder under a dataset root that holds the cached manifests: it belongs to this crate, not
/// to the dataset, so indexing never reads it as data.
pub const CACHE_DIR: &str = ".xfactor";

/// Sequences with fewer frames are dropped.
pub const MIN_FRAMES: usize = 10;
/// Share of each category's sequences (sorted) that trains, for MVImgNet and CO3Dv2.
const TRAIN_SHARE: f64 = 0.9;
/// The CO3Dv2 categories the release trains on (its `CO3DV2_SEQ_NAMES`); others are skipped.
pub const CO3DV2_CATEGORIES: [&str; 51] = [
    "apple",
    "tv",
    "microwave",
    "parkingmeter",
    "baseballglove",
    "baseballbat",
    "hotdog",
    "frisbee",
    "pizza",
    "kite",
    "toybus",
    "sandwich",
    "toyplane",
    "car",
    "skateboard",
    "cup",
    "donut",
    "stopsign",
    "bicycle",
    "banana",
    "handbag",
    "motorcycle",
    "cake",
    "toytrain",
    "couch",
    "broccoli",
    "bottle",
    "toaster",
    "wineglass",
    "hairdryer",
    "bowl",
    "carrot",
    "laptop",
    "hydrant",
    "umbrella",
    "bench",
    "suitcase",
    "toytruck",
    "ball",
    "orange",
    "keyboard",
    "cellphone",
    "toilet",
    "vase",
    "backpack",
    "mouse",
    "chair",
    "plant",
    "teddybear",
    "remote",
    "book",
];

/// Why a dataset could not be indexed.
#[derive(Debug, thiserror::Error)]
pub enum IndexError {
    /// The root could not be listed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The root holds nothing at all.
    #[error("{dataset} root `{uri}` is empty")]
    Empty {
        /// Dataset being indexed.
        dataset: &'static str,
        /// The root.
        uri: String,
    },
    /// Objects exist, but none forms a usable sequence of this layout.
    #[error(
        "{dataset} root `{uri}` holds {objects} objects but no sequence of the {dataset} layout ({layout}) with at least {MIN_FRAMES} frames ({skipped} candidates skipped)"
    )]
    NoSequences {
        /// Dataset being indexed.
        dataset: &'static str,
        /// Where the layout expects frames.
        layout: &'static str,
        /// The root.
        uri: String,
        /// Objects listed.
        objects: usize,
        /// Sequences dropped by the layout's rules.
        skipped: usize,
    },
}

/// A manifest and what its rules dropped.
#[derive(Debug, Clone, PartialEq)]
pub struct Indexed {
    /// The usable sequences.
    pub manifest: Manifest,
    /// `(sequence id, reason)` of every dropped candidate, for logs.
    pub skipped: Vec<(String, String)>,
}

/// Where `dataset`'s layout expects frames, for errors.
pub fn layout(dataset: DatasetKind) -> &'static str {
    match dataset {
        DatasetKind::Re10k | DatasetKind::Acid => "{train|test}/images/{sequence}/*.png|jpg",
        DatasetKind::Dl3dv => "training_256/{part}/{sequence}/images_8/* beside transforms.json",
        DatasetKind::Mvimgnet => "{category}/{scene}/images/NNN.jpg",
        DatasetKind::Co3dv2 => "{category}/{sequence}/images/frameNNNNNN.jpg",
        DatasetKind::Arkitscenes => {
            "{Training|Validation}/{video}/[{video}_frames/]lowres_wide/{video}_{seconds}.{ms}.png"
        }
        DatasetKind::Wildrgbd => "{category}/scenes/{scene}/rgb/NNNNN.png",
    }
}

fn is_image(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    [".jpg", ".jpeg", ".png"]
        .iter()
        .any(|ext| lower.ends_with(ext))
}

/// Lists `root` and indexes it as `dataset`.
pub async fn index(root: &DataRoot, dataset: DatasetKind) -> Result<Indexed, IndexError> {
    let listing = root.list().await?;
    let paths: Vec<&str> = listing
        .iter()
        .map(|l| l.path.as_str())
        .filter(|p| !p.starts_with(CACHE_DIR))
        .collect();
    check_indexed(root, dataset, &paths, index_paths(dataset, &paths))
}

/// Turns an empty listing or one without usable sequences into an error naming the root, and
/// logs every sequence the rules dropped.
pub(crate) fn check_indexed(
    root: &DataRoot,
    dataset: DatasetKind,
    paths: &[&str],
    indexed: Indexed,
) -> Result<Indexed, IndexError> {
    if paths.is_empty() {
        return Err(IndexError::Empty {
            dataset: dataset.name(),
            uri: root.uri().to_string(),
        });
    }
    if indexed.manifest.sequences.is_empty() {
        return Err(IndexError::NoSequences {
            dataset: dataset.name(),
            layout: layout(dataset),
            uri: root.uri().to_string(),
            objects: paths.len(),
            skipped: indexed.skipped.len(),
        });
    }
    for (id, reason) in &indexed.skipped {
        tracing::debug!(dataset = dataset.name(), sequence = %id, %reason, "sequence skipped");
    }
    Ok(indexed)
}

/// Indexes a listing (paths relative to the dataset root) as `dataset`.
pub fn index_paths(dataset: DatasetKind, paths: &[&str]) -> Indexed {
    let mut indexed = match dataset {
        DatasetKind::Re10k | DatasetKind::Acid => re10k_layout(paths, dataset),
        DatasetKind::Dl3dv => dl3dv(paths),
        DatasetKind::Mvimgnet => category_layout(paths, dataset, |scene, name| {
            !scene.is_empty() && name.len() == 7 && name[..3].bytes().all(|b| b.is_ascii_digit())
        }),
        DatasetKind::Co3dv2 => co3dv2(paths),
        DatasetKind::Arkitscenes => erayzer::arkitscenes(paths),
        DatasetKind::Wildrgbd => erayzer::wildrgbd(paths),
    };
    let (kept, short): (Vec<Sequence>, Vec<Sequence>) = indexed
        .manifest
        .sequences
        .into_iter()
        .partition(|s| s.frames.len() >= MIN_FRAMES);
    indexed.skipped.extend(short.into_iter().map(|s| {
        (
            s.id,
            format!("{} frames, fewer than {MIN_FRAMES}", s.frames.len()),
        )
    }));
    indexed.manifest.sequences = kept;
    indexed.manifest.sequences.sort_by(|a, b| a.id.cmp(&b.id));
    indexed
}

/// CO3Dv2 restricted to [`CO3DV2_CATEGORIES`]; every other top-level folder is skipped.
fn co3dv2(paths: &[&str]) -> Indexed {
    let category = |path: &str| path.split('/').next().unwrap_or_default().to_string();
    let (listed, other): (Vec<&str>, Vec<&str>) = paths
        .iter()
        .copied()
        .partition(|p| CO3DV2_CATEGORIES.contains(&category(p).as_str()));
    let mut indexed = category_layout(&listed, DatasetKind::Co3dv2, |sequence, name| {
        sequence.starts_with(|c: char| c.is_ascii_digit()) && name.starts_with("frame")
    });
    let unlisted: BTreeSet<String> = other
        .iter()
        .filter(|p| p.contains('/'))
        .map(|p| category(p))
        .collect();
    indexed.skipped.extend(unlisted.into_iter().map(|c| {
        (
            c,
            "not one of the release's 51 CO3Dv2 categories".to_string(),
        )
    }));
    indexed
}

/// RE10K's layout, which ACID shares (the same camera files, the same split folders).
fn re10k_layout(paths: &[&str], dataset: DatasetKind) -> Indexed {
    let mut frames: BTreeMap<(String, String), Vec<String>> = BTreeMap::new();
    let cameras: BTreeSet<&str> = paths
        .iter()
        .copied()
        .filter(|p| p.contains("/cameras/"))
        .collect();
    for path in paths {
        let parts: Vec<&str> = path.split('/').collect();
        if let [split @ ("train" | "test"), "images", sequence, name] = parts.as_slice()
            && is_image(name)
        {
            frames
                .entry((split.to_string(), sequence.to_string()))
                .or_default()
                .push(path.to_string());
        }
    }
    let sequences = frames
        .into_iter()
        .map(|((split, sequence), mut files)| {
            sort_frames(&mut files);
            let camera = format!("{split}/cameras/{sequence}.txt");
            Sequence {
                dataset,
                split: if split == "train" {
                    Split::Train
                } else {
                    Split::Test
                },
                id: sequence,
                frames: files,
                poses: cameras.contains(camera.as_str()).then_some(camera),
            }
        })
        .collect();
    Indexed {
        manifest: Manifest { sequences },
        skipped: Vec::new(),
    }
}

fn dl3dv(paths: &[&str]) -> Indexed {
    let mut frames: BTreeMap<(String, String), Vec<String>> = BTreeMap::new();
    let mut transforms: BTreeSet<(String, String)> = BTreeSet::new();
    let mut benchmark: BTreeSet<String> = BTreeSet::new();
    for path in paths {
        let parts: Vec<&str> = path.split('/').collect();
        match parts.as_slice() {
            ["training_256", part, sequence, "images_8", name] if is_image(name) => frames
                .entry((part.to_string(), sequence.to_string()))
                .or_default()
                .push(path.to_string()),
            ["training_256", part, sequence, "transforms.json"] => {
                transforms.insert((part.to_string(), sequence.to_string()));
            }
            ["test_256", "benchmark_960p", id, ..] => {
                benchmark.insert(id.to_string());
            }
            _ => {}
        }
    }
    let mut sequences = Vec::new();
    let mut skipped = Vec::new();
    for ((part, sequence), mut files) in frames {
        let id = format!("{part}/{sequence}");
        if !transforms.contains(&(part.clone(), sequence.clone())) {
            skipped.push((id, "no transforms.json beside images_8".to_string()));
            continue;
        }
        sort_frames(&mut files);
        sequences.push(Sequence {
            dataset: DatasetKind::Dl3dv,
            split: if benchmark.contains(&sequence) {
                Split::Test
            } else {
                Split::Train
            },
            id,
            frames: files,
            poses: Some(format!("training_256/{part}/{sequence}/transforms.json")),
        });
    }
    Indexed {
        manifest: Manifest { sequences },
        skipped,
    }
}

/// MVImgNet and CO3Dv2: `{category}/{sequence}/images/{frame}`, split 90/10 per category.
fn category_layout(
    paths: &[&str],
    dataset: DatasetKind,
    accepts: impl Fn(&str, &str) -> bool,
) -> Indexed {
    let mut frames: BTreeMap<(String, String), Vec<String>> = BTreeMap::new();
    let mut sparse: BTreeSet<(String, String)> = BTreeSet::new();
    let mut annotations: BTreeSet<String> = BTreeSet::new();
    let mut skipped = Vec::new();
    let mut rejected: BTreeSet<String> = BTreeSet::new();
    for path in paths {
        let parts: Vec<&str> = path.split('/').collect();
        match parts.as_slice() {
            [category, sequence, "images", name] if is_image(name) => {
                if accepts(sequence, name) {
                    frames
                        .entry((category.to_string(), sequence.to_string()))
                        .or_default()
                        .push(path.to_string());
                } else {
                    rejected.insert(format!("{category}/{sequence}"));
                }
            }
            [category, sequence, "sparse", ..] => {
                sparse.insert((category.to_string(), sequence.to_string()));
            }
            [category, "frame_annotations.jgz"] => {
                annotations.insert(category.to_string());
            }
            _ => {}
        }
    }
    for id in rejected {
        if !frames.keys().any(|(c, s)| format!("{c}/{s}") == id) {
            skipped.push((
                id,
                format!("not a {} sequence or frame name", dataset.name()),
            ));
        }
    }
    let sequences = split_per_category(frames, dataset, |category, sequence| match dataset {
        DatasetKind::Mvimgnet => sparse
            .contains(&(category.to_string(), sequence.to_string()))
            .then(|| format!("{category}/{sequence}/sparse")),
        _ => annotations
            .contains(category)
            .then(|| format!("{category}/frame_annotations.jgz")),
    });
    Indexed {
        manifest: Manifest { sequences },
        skipped,
    }
}

/// Sequences of `(category, sequence) -> frames`, frames sorted, with the first
/// [`TRAIN_SHARE`] of each category's sequences (sorted by name) in the training split and
/// the rest in the test split; `poses` names each sequence's camera file, if any.
fn split_per_category(
    frames: BTreeMap<(String, String), Vec<String>>,
    dataset: DatasetKind,
    poses: impl Fn(&str, &str) -> Option<String>,
) -> Vec<Sequence> {
    let mut per_category: BTreeMap<String, Vec<(String, Vec<String>)>> = BTreeMap::new();
    for ((category, sequence), mut files) in frames {
        sort_frames(&mut files);
        per_category
            .entry(category)
            .or_default()
            .push((sequence, files));
    }
    let mut sequences = Vec::new();
    for (category, members) in per_category {
        let train = (members.len() as f64 * TRAIN_SHARE) as usize;
        for (position, (sequence, files)) in members.into_iter().enumerate() {
            sequences.push(Sequence {
                dataset,
                split: if position < train {
                    Split::Train
                } else {
                    Split::Test
                },
                poses: poses(&category, &sequence),
                id: format!("{category}/{sequence}"),
                frames: files,
            });
        }
    }
    sequences
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frames(prefix: &str, count: usize, name: impl Fn(usize) -> String) -> Vec<String> {
        (0..count)
            .map(|i| format!("{prefix}/{}", name(i)))
            .collect()
    }

    fn index_strings(dataset: DatasetKind, paths: &[String]) -> Indexed {
        let refs: Vec<&str> = paths.iter().map(String::as_str).collect();
        index_paths(dataset, &refs)
    }

    #[test]
    fn re10k_splits_sorts_and_drops_short_sequences() {
        let mut paths = frames("train/images/seqA", 12, |i| format!("{:03}.jpg", 11 - i));
        paths.extend(frames("test/images/seqB", 10, |i| format!("{i:03}.png")));
        paths.extend(frames("train/images/short", 9, |i| format!("{i:03}.jpg")));
        paths.push("train/cameras/seqA.txt".to_string());
        paths.push("train/images/seqA/notes.txt".to_string());
        let indexed = index_strings(DatasetKind::Re10k, &paths);
        let seqs = &indexed.manifest.sequences;
        assert_eq!(seqs.len(), 2);
        assert_eq!((seqs[0].id.as_str(), seqs[0].split), ("seqA", Split::Train));
        assert_eq!(seqs[0].frames.len(), 12);
        assert_eq!(seqs[0].frames[0], "train/images/seqA/000.jpg");
        assert_eq!(seqs[0].poses.as_deref(), Some("train/cameras/seqA.txt"));
        assert_eq!((seqs[1].id.as_str(), seqs[1].split), ("seqB", Split::Test));
        assert_eq!(seqs[1].poses, None);
        assert_eq!(
            indexed.skipped,
            vec![("short".to_string(), "9 frames, fewer than 10".to_string())]
        );
    }

    #[test]
    fn acid_shares_the_re10k_layout_under_its_own_name() {
        let mut paths = frames("test/images/coast", 10, |i| format!("{i:05}.png"));
        paths.push("test/cameras/coast.txt".to_string());
        let indexed = index_strings(DatasetKind::Acid, &paths);
        let seqs = &indexed.manifest.sequences;
        assert_eq!(seqs.len(), 1);
        assert_eq!(
            (seqs[0].dataset, seqs[0].id.as_str(), seqs[0].split),
            (DatasetKind::Acid, "coast", Split::Test)
        );
        assert_eq!(seqs[0].poses.as_deref(), Some("test/cameras/coast.txt"));
    }

    #[test]
    fn dl3dv_needs_transforms_and_excludes_the_benchmark_from_train() {
        let mut paths = Vec::new();
        for (sequence, with_transforms) in [("aaa", true), ("bbb", true), ("ccc", false)] {
            paths.extend(frames(
                &format!("training_256/1K/{sequence}/images_8"),
                10,
                |i| format!("frame_{i:05}.png"),
            ));
            if with_transforms {
                paths.push(format!("training_256/1K/{sequence}/transforms.json"));
            }
        }
        paths.push("test_256/benchmark_960p/bbb/images/x.png".to_string());
        let indexed = index_strings(DatasetKind::Dl3dv, &paths);
        let seqs = &indexed.manifest.sequences;
        assert_eq!(seqs.len(), 2);
        assert_eq!(
            (seqs[0].id.as_str(), seqs[0].split),
            ("1K/aaa", Split::Train)
        );
        assert_eq!(
            (seqs[1].id.as_str(), seqs[1].split),
            ("1K/bbb", Split::Test)
        );
        assert_eq!(
            seqs[0].poses.as_deref(),
            Some("training_256/1K/aaa/transforms.json")
        );
        assert_eq!(indexed.skipped[0].0, "1K/ccc");
    }

    #[test]
    fn mvimgnet_counts_scenes_without_sparse_and_splits_ninety_ten_per_category() {
        let mut paths = Vec::new();
        for scene in 0..10 {
            paths.extend(frames(&format!("chair/s{scene:02}/images"), 10, |i| {
                format!("{i:03}.jpg")
            }));
        }
        paths.push("chair/s03/sparse/0/cameras.bin".to_string());
        paths.extend(frames("chair/badnames/images", 10, |i| {
            format!("img{i}.jpg")
        }));
        let indexed = index_strings(DatasetKind::Mvimgnet, &paths);
        let seqs = &indexed.manifest.sequences;
        assert_eq!(seqs.len(), 10, "scenes without sparse/ count too");
        assert_eq!(seqs.iter().filter(|s| s.split == Split::Train).count(), 9);
        assert_eq!(seqs[9].id, "chair/s09");
        assert_eq!(seqs[9].split, Split::Test);
        assert_eq!(seqs[3].poses.as_deref(), Some("chair/s03/sparse"));
        assert_eq!(seqs[4].poses, None);
        let skipped: Vec<&str> = indexed.skipped.iter().map(|(id, _)| id.as_str()).collect();
        assert_eq!(skipped, vec!["chair/badnames"]);
    }

    #[test]
    fn frames_are_ordered_by_the_number_in_their_name() {
        let paths = frames("train/images/seq", 12, |i| format!("frame{}.png", 11 - i));
        let indexed = index_strings(DatasetKind::Re10k, &paths);
        let order: Vec<&str> = indexed.manifest.sequences[0]
            .frames
            .iter()
            .map(|f| f.rsplit('/').next().unwrap_or_default())
            .collect();
        assert_eq!(order[9], "frame9.png");
        assert_eq!(order[10], "frame10.png");
        assert_eq!(order[11], "frame11.png");
    }

    #[test]
    fn co3d_reads_only_the_release_categories() {
        let mut paths = Vec::new();
        for category in ["apple", "unicorn"] {
            paths.extend(frames(&format!("{category}/100_1_2/images"), 12, |i| {
                format!("frame{i:06}.jpg")
            }));
        }
        let indexed = index_strings(DatasetKind::Co3dv2, &paths);
        let ids: Vec<&str> = indexed
            .manifest
            .sequences
            .iter()
            .map(|s| s.id.as_str())
            .collect();
        assert_eq!(ids, vec!["apple/100_1_2"]);
        assert_eq!(indexed.skipped[0].0, "unicorn");
        assert_eq!(CO3DV2_CATEGORIES.len(), 51);
    }

    #[test]
    fn co3d_keeps_digit_sequences_and_finds_annotations() {
        let mut paths = Vec::new();
        for sequence in ["106_12650_23736", "110_13051_23361", "aux_data"] {
            paths.extend(frames(&format!("apple/{sequence}/images"), 12, |i| {
                format!("frame{i:06}.jpg")
            }));
        }
        paths.push("apple/frame_annotations.jgz".to_string());
        let indexed = index_strings(DatasetKind::Co3dv2, &paths);
        let seqs = &indexed.manifest.sequences;
        assert_eq!(seqs.len(), 2);
        assert_eq!(seqs[0].id, "apple/106_12650_23736");
        assert_eq!(seqs[0].split, Split::Train);
        assert_eq!(seqs[1].split, Split::Test, "first 90% of 2 is 1 sequence");
        assert_eq!(
            seqs[0].poses.as_deref(),
            Some("apple/frame_annotations.jgz")
        );
        assert_eq!(indexed.skipped[0].0, "apple/aux_data");
    }
}
