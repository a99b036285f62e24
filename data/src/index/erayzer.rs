//! The layouts E-RayZer's mixture adds to XFactor's four (ACID shares RE10K's, see the parent
//! module):
//!
//! - ARKitScenes, as apple/ARKitScenes' `download_data.py` unpacks it: the `raw` assets
//!   `{Training|Validation}/{video}/lowres_wide/{video}_{seconds}.{ms}.png` with
//!   `lowres_wide.traj` beside `lowres_wide`, or the `3dod` assets, the same under
//!   `{Training|Validation}/{video}/{video}_frames/`. Any prefix above the split folder is
//!   allowed (`raw/`, `3dod/`). Frames are ordered by their timestamp; `Validation` is the
//!   test split.
//! - WildRGB-D, as wildrgbd/wildrgbd's `download.py` unpacks it:
//!   `{category}/scenes/{scene}/rgb/{NNNNN}.png` with `cam_poses.txt` beside `rgb`; the first
//!   90% of each category's scenes (sorted) train, as for MVImgNet and CO3Dv2 (a split file
//!   from the dataset's `nvs_list.json` can replace the rule).

use std::collections::{BTreeMap, BTreeSet};

use settings::data::DatasetKind;

use super::{Indexed, is_image, split_per_category};
use crate::frame_order::compare_frames;
use crate::manifest::{Manifest, Sequence, Split};

/// The timestamp of an ARKitScenes frame `{video}_{seconds}.{ms}.png`, in milliseconds.
fn arkit_timestamp_ms(name: &str) -> Option<u64> {
    let stem = name.rsplit_once('.')?.0;
    let (seconds, millis) = stem.rsplit_once('_')?.1.split_once('.')?;
    let millis: u64 = format!("{millis:0<3}").get(..3)?.parse().ok()?;
    Some(seconds.parse::<u64>().ok()? * 1000 + millis)
}

/// ARKitScenes frames grouped by video and by copy, with the trajectories and skipped files.
#[derive(Default)]
struct ArkitTree {
    /// (in the training split, video) -> the folder holding `lowres_wide/` -> frames.
    frames: BTreeMap<(bool, String), BTreeMap<String, Vec<String>>>,
    /// The folders holding a `lowres_wide.traj`.
    trajectories: BTreeSet<String>,
    /// `(video, reason)` of every file dropped.
    skipped: Vec<(String, String)>,
}

/// Sorts `paths` into ARKitScenes videos, keeping each unpacked copy of a video apart.
fn arkit_tree(paths: &[&str]) -> ArkitTree {
    let mut tree = ArkitTree::default();
    for path in paths {
        let parts: Vec<&str> = path.split('/').collect();
        if parts.last() == Some(&"lowres_wide.traj") {
            tree.trajectories.insert(parts[..parts.len() - 1].join("/"));
            continue;
        }
        let Some(at) = parts.iter().rposition(|p| *p == "lowres_wide") else {
            continue;
        };
        let (Some(name), true) = (parts.last(), at + 2 == parts.len()) else {
            continue;
        };
        // `{split}/{video}/lowres_wide` or `{split}/{video}/{video}_frames/lowres_wide`.
        let video_at = match at.checked_sub(1).map(|i| parts[i]) {
            Some(folder) if folder.ends_with("_frames") => at.checked_sub(2),
            _ => at.checked_sub(1),
        };
        let Some(video_at) = video_at.filter(|&i| i >= 1) else {
            continue;
        };
        let training = match parts[video_at - 1] {
            "Training" => true,
            "Validation" => false,
            _ => continue,
        };
        let video = parts[video_at];
        if !is_image(name) || arkit_timestamp_ms(name).is_none() {
            tree.skipped.push((
                video.to_string(),
                format!("`{name}` is not a frame named {video}_<seconds>.<ms>.png"),
            ));
            continue;
        }
        tree.frames
            .entry((training, video.to_string()))
            .or_default()
            .entry(parts[..at].join("/"))
            .or_default()
            .push(path.to_string());
    }
    tree
}

/// ARKitScenes' `raw` and `3dod` layouts.
pub(super) fn arkitscenes(paths: &[&str]) -> Indexed {
    let ArkitTree {
        frames,
        trajectories,
        mut skipped,
    } = arkit_tree(paths);
    let mut sequences = Vec::new();
    for ((training, video), mut copies) in frames {
        // A video unpacked twice (`raw` and `3dod`) trains once, from the copy listed first.
        let Some((prefix, mut files)) = copies.pop_first() else {
            continue;
        };
        for (other, _) in copies {
            skipped.push((
                video.clone(),
                format!("also under `{other}`; `{prefix}` is used"),
            ));
        }
        sequences.push({
            files.sort_by(|a, b| {
                let stamp = |p: &str| arkit_timestamp_ms(p.rsplit('/').next().unwrap_or(p));
                stamp(a).cmp(&stamp(b)).then_with(|| compare_frames(a, b))
            });
            Sequence {
                dataset: DatasetKind::Arkitscenes,
                split: if training { Split::Train } else { Split::Test },
                id: video,
                frames: files,
                poses: trajectories
                    .contains(&prefix)
                    .then(|| format!("{prefix}/lowres_wide.traj")),
            }
        });
    }
    skipped.sort();
    skipped.dedup_by(|a, b| a.0 == b.0);
    Indexed {
        manifest: Manifest { sequences },
        skipped,
    }
}

/// WildRGB-D's `{category}/scenes/{scene}/rgb/*` layout.
pub(super) fn wildrgbd(paths: &[&str]) -> Indexed {
    let mut frames: BTreeMap<(String, String), Vec<String>> = BTreeMap::new();
    let mut poses: BTreeSet<(String, String)> = BTreeSet::new();
    for path in paths {
        let parts: Vec<&str> = path.split('/').collect();
        match parts.as_slice() {
            [category, "scenes", scene, "rgb", name] if is_image(name) => frames
                .entry((category.to_string(), scene.to_string()))
                .or_default()
                .push(path.to_string()),
            [category, "scenes", scene, "cam_poses.txt"] => {
                poses.insert((category.to_string(), scene.to_string()));
            }
            _ => {}
        }
    }
    let sequences = split_per_category(frames, DatasetKind::Wildrgbd, |category, scene| {
        poses
            .contains(&(category.to_string(), scene.to_string()))
            .then(|| format!("{category}/scenes/{scene}/cam_poses.txt"))
    });
    Indexed {
        manifest: Manifest { sequences },
        skipped: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::super::index_paths;
    use super::*;

    #[test]
    fn arkit_timestamps_order_frames_across_digit_counts() {
        assert_eq!(arkit_timestamp_ms("41069021_305.244.png"), Some(305_244));
        assert_eq!(arkit_timestamp_ms("41069021_99.5.png"), Some(99_500));
        assert_eq!(arkit_timestamp_ms("cover.png"), None);
    }

    #[test]
    fn arkitscenes_reads_raw_and_3dod_trees_with_their_splits_and_trajectories() {
        let mut paths = Vec::new();
        // raw: 10 frames from 95.000 s to 104.000 s, so a text sort would misplace 100..104.
        for i in 0..10 {
            paths.push(format!(
                "raw/Training/111/lowres_wide/111_{}.{:03}.png",
                95 + i,
                0
            ));
        }
        paths.push("raw/Training/111/lowres_wide.traj".into());
        paths.push("raw/Training/111/lowres_wide_intrinsics/111_95.000.pincam".into());
        for i in 0..10 {
            paths.push(format!(
                "3dod/Validation/222/222_frames/lowres_wide/222_7.{:03}.png",
                100 * i
            ));
        }
        paths.push("raw/Training/333/lowres_wide/notes.png".into());
        paths.push("raw/Validation/222/lowres_wide/222_7.000.png".into());
        let refs: Vec<&str> = paths.iter().map(String::as_str).collect();
        let indexed = index_paths(DatasetKind::Arkitscenes, &refs);
        let seqs = &indexed.manifest.sequences;
        assert_eq!(seqs.len(), 2, "{indexed:?}");
        assert_eq!((seqs[0].id.as_str(), seqs[0].split), ("111", Split::Train));
        assert_eq!(
            seqs[0].frames[4],
            "raw/Training/111/lowres_wide/111_99.000.png"
        );
        assert_eq!(
            seqs[0].frames[5],
            "raw/Training/111/lowres_wide/111_100.000.png"
        );
        assert_eq!(
            seqs[0].poses.as_deref(),
            Some("raw/Training/111/lowres_wide.traj")
        );
        assert_eq!((seqs[1].id.as_str(), seqs[1].split), ("222", Split::Test));
        assert_eq!(seqs[1].poses, None);
        assert_eq!(indexed.skipped[0].0, "222", "{indexed:?}");
        assert!(
            indexed.skipped[0]
                .1
                .contains("also under `raw/Validation/222`")
        );
        assert_eq!(indexed.skipped[1].0, "333");
    }

    #[test]
    fn wildrgbd_scenes_split_ninety_ten_per_category_with_their_poses() {
        let mut paths = Vec::new();
        for scene in 0..10 {
            for i in 0..10 {
                paths.push(format!("apple/scenes/scene_{scene:03}/rgb/{i:05}.png"));
            }
            paths.push(format!("apple/scenes/scene_{scene:03}/cam_poses.txt"));
            paths.push(format!("apple/scenes/scene_{scene:03}/depth/00000.png"));
        }
        paths.push("apple/nvs_list.json".into());
        let refs: Vec<&str> = paths.iter().map(String::as_str).collect();
        let indexed = index_paths(DatasetKind::Wildrgbd, &refs);
        let seqs = &indexed.manifest.sequences;
        assert_eq!(seqs.len(), 10);
        assert_eq!(seqs[0].id, "apple/scene_000");
        assert_eq!(seqs[0].frames.len(), 10, "depth maps are not frames");
        assert_eq!(
            seqs[0].poses.as_deref(),
            Some("apple/scenes/scene_000/cam_poses.txt")
        );
        let test: Vec<_> = seqs.iter().filter(|s| s.split == Split::Test).collect();
        assert_eq!(test.len(), 1);
        assert_eq!(test[0].id, "apple/scene_009");
    }
}
