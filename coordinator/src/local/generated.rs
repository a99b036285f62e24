//! What a generated training dataset was made with, kept beside it, so a rerun with other
//! settings regenerates or refuses it instead of training on stale frames.

use data::store::DataRoot;

use super::LocalJob;

/// The file beside a generated dataset that says what it was made with.
pub(super) const GENERATED_WITH: &str = "generated-with.json";

/// The settings a generated training dataset was made with.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub(super) struct GeneratedWith {
    seed: u64,
    scenes: u64,
    trajectories: u64,
    frames: usize,
    image_size: usize,
}

/// What a data location holds.
pub(super) enum Found {
    /// Nothing yet.
    Nothing,
    /// A dataset generated as this job would.
    Same,
    /// Something else: another generation's settings, or no record of any.
    Other(Option<GeneratedWith>),
}

impl GeneratedWith {
    pub(super) fn of(job: &LocalJob) -> Self {
        Self {
            seed: job.seed,
            scenes: job.scenes,
            trajectories: job.trajectories,
            frames: job.frames,
            image_size: job.image_size,
        }
    }

    /// What `root` holds, compared with these settings.
    pub(super) async fn found(&self, root: &DataRoot) -> anyhow::Result<Found> {
        if root.list().await?.is_empty() {
            return Ok(Found::Nothing);
        }
        let recorded = match root.read(GENERATED_WITH).await {
            Ok(bytes) => serde_json::from_slice::<Self>(&bytes).ok(),
            Err(_) => None,
        };
        Ok(match recorded {
            Some(found) if found == *self => Found::Same,
            other => Found::Other(other),
        })
    }

    /// How `found` differs from these settings, key by key (`image_size 32, found 64`).
    pub(super) fn differences(&self, found: Option<&Self>) -> String {
        let Some(found) = found else {
            return format!("no {GENERATED_WITH}: not made by xfactor-local");
        };
        let pairs = [
            ("seed", self.seed, found.seed),
            ("scenes", self.scenes, found.scenes),
            ("trajectories", self.trajectories, found.trajectories),
            ("frames", self.frames as u64, found.frames as u64),
            (
                "image_size",
                self.image_size as u64,
                found.image_size as u64,
            ),
        ];
        pairs
            .iter()
            .filter(|(_, wanted, found)| wanted != found)
            .map(|(key, wanted, found)| format!("{key} {wanted}, found {found}"))
            .collect::<Vec<_>>()
            .join("; ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// The side of the first frame of the first generated sequence under `data`.
    fn frame_side(data: &Path) -> u32 {
        let images = data.join("train/images");
        let sequence = std::fs::read_dir(&images).unwrap().next().unwrap().unwrap();
        let frame = sequence.path().join("000.png");
        image::image_dimensions(&frame).unwrap().0
    }

    #[test]
    fn a_stale_generated_dataset_is_regenerated_here_and_refused_elsewhere() {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let mut job = LocalJob::new(dir.path(), 1);
        (job.scenes, job.trajectories, job.image_size) = (2, 2, 16);
        runtime.block_on(job.prepare()).unwrap();
        let data = dir.path().join("data");
        assert_eq!(frame_side(&data), 16);

        job.image_size = 24;
        runtime.block_on(job.prepare()).unwrap();
        assert_eq!(frame_side(&data), 24, "this job's own data is made again");

        let elsewhere = LocalJob {
            data_uri: Some(data.display().to_string()),
            image_size: 32,
            seed: 8,
            ..job.clone()
        };
        let error = runtime
            .block_on(elsewhere.prepare())
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("seed 8, found 7") && error.contains("image_size 32, found 24"),
            "{error}"
        );
        assert_eq!(frame_side(&data), 24, "data it did not make is left alone");

        let foreign = tempfile::tempdir().unwrap();
        std::fs::write(foreign.path().join("notes.txt"), "mine").unwrap();
        let unrecorded = LocalJob {
            data_uri: Some(foreign.path().display().to_string()),
            ..job
        };
        let error = runtime
            .block_on(unrecorded.prepare())
            .unwrap_err()
            .to_string();
        assert!(error.contains("not made by xfactor-local"), "{error}");
    }
}
