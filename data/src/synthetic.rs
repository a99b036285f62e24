//! A dataset of generated scenes: every trajectory rendered in every scene, so the same camera
//! motion exists in many places. It feeds the trainer in tests, demos and evaluation.

use crate::batch::{BatchSource, SampleError, Samples};
use crate::frame::Image;
use crate::manifest::Split;
use crate::rng::Stream;
use crate::scenes::{CameraPose, Scene, SceneConfig, Trajectory};
use crate::store::{DataRoot, StoreError};

/// Tag of the sampling streams.
const SAMPLING_STREAM: u64 = 0x5359_4e54;
/// Scene and trajectory indices of the held-out (test) split start here, so no held-out scene
/// or camera path can be one a training job generated from the same seed (a job would need
/// 2^40 scenes to reach them).
pub const HELD_OUT_FIRST_INDEX: u64 = 1 << 40;

/// One trajectory rendered in one scene.
#[derive(Debug, Clone)]
pub struct SyntheticSequence {
    /// Index of the scene it was rendered in.
    pub scene: u64,
    /// Index of the camera trajectory.
    pub trajectory: u64,
    /// The rendered frames.
    pub frames: Vec<Image>,
    /// World-to-camera pose of each frame.
    pub poses: Vec<CameraPose>,
}

/// Every trajectory rendered in every scene.
#[derive(Debug, Clone)]
pub struct SyntheticDataset {
    /// Root of scene, trajectory and sampling draws.
    pub seed: u64,
    /// Largest frame gap between the two frames of a pair.
    pub max_gap: usize,
    /// Frames per sample: 2 gives stage-1 pairs, more gives stage-2 multi-view samples.
    pub views: usize,
    /// The split its scenes and paths were drawn for: training and held-out scenes never meet.
    pub split: Split,
    /// Sequences, scene-major.
    pub sequences: Vec<SyntheticSequence>,
}

/// The first scene (and trajectory) index of `split`'s draws.
fn first_index(split: Split) -> u64 {
    match split {
        Split::Train => 0,
        Split::Test => HELD_OUT_FIRST_INDEX,
    }
}

/// The name of generated scene `scene` of `split` under `seed` (`g{seed}-s{draw index}`): the
/// start of every sequence name [`SyntheticDataset::write_re10k`] writes, so a job can tell
/// which generated scenes a stored dataset holds.
pub fn scene_name(seed: u64, split: Split, scene: u64) -> String {
    format!("g{seed}-s{}", first_index(split) + scene)
}

/// The generated scene a stored sequence id names (`g7-s3` of `g7-s3_t2`), or `None` when the
/// id is no generated sequence's.
pub fn scene_of_sequence_id(id: &str) -> Option<&str> {
    let (scene, trajectory) = id.rsplit_once("_t")?;
    let (seed, index) = scene.strip_prefix('g')?.split_once("-s")?;
    let numbers = [seed, index, trajectory];
    numbers
        .iter()
        .all(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
        .then_some(scene)
}

impl SyntheticDataset {
    /// Renders `trajectories` camera paths of `frames` frames in each of `scenes` training
    /// scenes.
    pub fn generate(
        seed: u64,
        scenes: u64,
        trajectories: u64,
        frames: usize,
        config: &SceneConfig,
    ) -> Self {
        Self::generate_split(seed, Split::Train, scenes, trajectories, frames, config)
    }

    /// Renders `trajectories` camera paths of `frames` frames in each of `scenes` scenes drawn
    /// for `split`: held-out (test) scenes and paths come from their own draw indices, so an
    /// evaluation on them never sees a scene or path a training job generated.
    pub fn generate_split(
        seed: u64,
        split: Split,
        scenes: u64,
        trajectories: u64,
        frames: usize,
        config: &SceneConfig,
    ) -> Self {
        let first = first_index(split);
        let paths: Vec<Trajectory> = (0..trajectories)
            .map(|t| Trajectory::random(seed, first + t, frames))
            .collect();
        let mut sequences = Vec::new();
        for scene_index in 0..scenes {
            let scene = Scene::random(seed, first + scene_index, config);
            for (trajectory, path) in paths.iter().enumerate() {
                sequences.push(SyntheticSequence {
                    scene: scene_index,
                    trajectory: trajectory as u64,
                    frames: scene.render_trajectory(path),
                    poses: path.poses.clone(),
                });
            }
        }
        Self {
            seed,
            max_gap: frames.saturating_sub(1).max(1),
            views: 2,
            split,
            sequences,
        }
    }

    /// Every sequence's path rendered in its scene at `subdivisions` evenly spaced poses per
    /// gap between consecutive frames (the frames themselves among them), with those poses:
    /// the candidates that let the ground-truth oracle read the pose of an image that lies
    /// between two generated frames. Scenes and paths are drawn again from the dataset's seed
    /// and split; `config` must be the one the dataset was generated with.
    pub fn views_between_frames(
        &self,
        subdivisions: usize,
        config: &SceneConfig,
    ) -> Vec<(Image, CameraPose)> {
        let first = first_index(self.split);
        let subdivisions = subdivisions.max(1);
        let mut views = Vec::new();
        let mut scene: Option<(u64, Scene)> = None;
        for sequence in &self.sequences {
            if scene
                .as_ref()
                .is_none_or(|(index, _)| *index != sequence.scene)
            {
                let drawn = Scene::random(self.seed, first + sequence.scene, config);
                scene = Some((sequence.scene, drawn));
            }
            let Some((_, drawn)) = &scene else { continue };
            let path = Trajectory::random_between_frames(
                self.seed,
                first + sequence.trajectory,
                sequence.poses.len(),
                subdivisions,
            );
            views.extend(drawn.render_trajectory(&path).into_iter().zip(path.poses));
        }
        views
    }

    /// The stored name of `sequence`: its scene's [`scene_name`], then `_t` and its path's draw
    /// index.
    pub fn sequence_name(&self, sequence: &SyntheticSequence) -> String {
        format!(
            "{}_t{}",
            scene_name(self.seed, self.split, sequence.scene),
            first_index(self.split) + sequence.trajectory
        )
    }

    /// The sequence of `trajectory` rendered in `scene`.
    pub fn sequence(&self, scene: u64, trajectory: u64) -> Option<&SyntheticSequence> {
        self.sequences
            .iter()
            .find(|s| s.scene == scene && s.trajectory == trajectory)
    }

    /// The `(sequence, first frame, second frame)` drawn for global sample `sample` of `step`:
    /// a uniformly chosen sequence, a gap in `1..=max_gap`, a uniform start, reversed half the
    /// time.
    pub fn draw_pair(&self, step: u64, sample: u64) -> (usize, usize, usize) {
        let mut stream = Stream::new(&[self.seed, SAMPLING_STREAM, step, sample]);
        let sequence = stream.below(self.sequences.len() as u64) as usize;
        let frames = self.sequences[sequence].frames.len();
        let gap = 1 + stream.below(self.max_gap.min(frames - 1) as u64) as usize;
        let start = stream.below((frames - gap) as u64) as usize;
        if stream.bernoulli(0.5) {
            (sequence, start + gap, start)
        } else {
            (sequence, start, start + gap)
        }
    }

    /// `(sequence, frame indices)` for a multi-view sample: `views` distinct frames of one
    /// uniformly chosen sequence, in increasing order.
    pub fn draw_views(&self, step: u64, sample: u64) -> (usize, Vec<usize>) {
        let mut stream = Stream::new(&[self.seed, SAMPLING_STREAM, step, sample]);
        let sequence = stream.below(self.sequences.len() as u64) as usize;
        let mut indices: Vec<usize> = (0..self.sequences[sequence].frames.len()).collect();
        for i in (1..indices.len()).rev() {
            indices.swap(i, stream.below(i as u64 + 1) as usize);
        }
        indices.truncate(self.views);
        indices.sort_unstable();
        (sequence, indices)
    }
}

/// Why a frame could not be encoded as PNG.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    /// The pixel buffer does not hold `height * width * 3` values.
    #[error("{values} values do not make a {width}x{height} RGB frame")]
    Size {
        /// Frame columns.
        width: usize,
        /// Frame rows.
        height: usize,
        /// Values in the pixel buffer.
        values: usize,
    },
    /// The PNG encoder failed.
    #[error("the PNG encoder failed")]
    Png(#[source] image::ImageError),
}

/// Why a generated dataset could not be written.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    /// Encoding a frame failed.
    #[error("encoding {path}")]
    Encode {
        /// Object being written.
        path: String,
        /// Why the frame could not be encoded.
        #[source]
        source: EncodeError,
    },
    /// The store refused a write.
    #[error(transparent)]
    Store(#[from] StoreError),
}

impl SyntheticDataset {
    /// Writes every sequence in the RE10K layout under `root`'s `split` folder:
    /// `{split}/images/{name}/NNN.png` and the camera file `{split}/cameras/{name}.txt`, named
    /// by [`SyntheticDataset::sequence_name`] (RE10K's format: a header line, then per
    /// frame `timestamp fx fy cx cy 0 0` with normalised intrinsics and the 3x4 world-to-camera
    /// matrix, row-major). Returns the number of frames written.
    pub async fn write_re10k(
        &self,
        root: &DataRoot,
        split: Split,
        fov_degrees: f64,
    ) -> Result<usize, WriteError> {
        let split = match split {
            Split::Train => "train",
            Split::Test => "test",
        };
        let focal = 0.5 / (fov_degrees.to_radians() / 2.0).tan();
        let mut written = 0;
        for sequence in &self.sequences {
            let name = self.sequence_name(sequence);
            let mut cameras = format!("generated://xfactor-dist/{name}\n");
            for (index, (frame, pose)) in sequence.frames.iter().zip(&sequence.poses).enumerate() {
                let path = format!("{split}/images/{name}/{index:03}.png");
                root.write(
                    &path,
                    encode_png(frame).map_err(|source| WriteError::Encode {
                        path: path.clone(),
                        source,
                    })?,
                )
                .await?;
                let matrix = pose.matrix();
                let values: Vec<String> = matrix[..3]
                    .iter()
                    .flat_map(|row| row.iter().map(|v| format!("{v:.9}")))
                    .collect();
                cameras.push_str(&format!(
                    "{index} {focal:.9} {focal:.9} 0.5 0.5 0 0 {}\n",
                    values.join(" ")
                ));
                written += 1;
            }
            root.write(&format!("{split}/cameras/{name}.txt"), cameras.into_bytes())
                .await?;
        }
        Ok(written)
    }
}

fn encode_png(frame: &Image) -> Result<Vec<u8>, EncodeError> {
    let bytes: Vec<u8> = frame
        .pixels
        .iter()
        .map(|v| ((v + 1.0) * 127.5).round().clamp(0.0, 255.0) as u8)
        .collect();
    let image = image::RgbImage::from_raw(frame.width as u32, frame.height as u32, bytes).ok_or(
        EncodeError::Size {
            width: frame.width,
            height: frame.height,
            values: frame.pixels.len(),
        },
    )?;
    let mut out = std::io::Cursor::new(Vec::new());
    image
        .write_to(&mut out, image::ImageFormat::Png)
        .map_err(EncodeError::Png)?;
    Ok(out.into_inner())
}

impl BatchSource for SyntheticDataset {
    fn samples(&self, step: u64, first_sample: u64, count: usize) -> Result<Samples, SampleError> {
        let needed = self.views.max(2);
        if let Some(short) = self.sequences.iter().find(|s| s.frames.len() < needed) {
            return Err(SampleError::SequenceTooShort {
                scene: short.scene,
                trajectory: short.trajectory,
                frames: short.frames.len(),
                needed,
            });
        }
        let samples = first_sample..first_sample + count as u64;
        if self.views > 2 {
            return Ok(Samples::Views(
                samples
                    .map(|sample| {
                        let (sequence, indices) = self.draw_views(step, sample);
                        let frames = &self.sequences[sequence].frames;
                        indices
                            .into_iter()
                            .map(|i| (i as u64, frames[i].clone()))
                            .collect()
                    })
                    .collect(),
            ));
        }
        Ok(Samples::Pairs(
            samples
                .map(|sample| {
                    let (sequence, first, second) = self.draw_pair(step, sample);
                    let frames = &self.sequences[sequence].frames;
                    (frames[first].clone(), frames[second].clone())
                })
                .collect(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_between_frames_hold_the_frames_and_the_poses_between_them() {
        let config = SceneConfig {
            image_size: 8,
            ..SceneConfig::default()
        };
        let dataset = SyntheticDataset::generate_split(5, Split::Test, 2, 2, 4, &config);
        let same = dataset.views_between_frames(1, &config);
        let frames: Vec<(&Image, &CameraPose)> = dataset
            .sequences
            .iter()
            .flat_map(|s| s.frames.iter().zip(&s.poses))
            .collect();
        assert_eq!(same.len(), frames.len());
        for ((image, pose), (frame, truth)) in same.iter().zip(&frames) {
            assert_eq!(image, *frame);
            assert_eq!(pose, *truth);
        }
        // Three views per gap: 3 * 3 + 1 per sequence, every third one a generated frame.
        let fine = dataset.views_between_frames(3, &config);
        assert_eq!(fine.len(), 4 * 10);
        let close = |a: &CameraPose, b: &CameraPose| {
            (0..3).all(|k| (a.translation[k] - b.translation[k]).abs() < 1e-9)
        };
        let sequence = &dataset.sequences[3];
        let views = &fine[30..40];
        for (frame, truth) in sequence.poses.iter().enumerate() {
            assert!(close(&views[3 * frame].1, truth), "frame {frame}");
        }
        // The views between two frames are new poses.
        assert!(!close(&views[1].1, &sequence.poses[0]) && !close(&views[1].1, &sequence.poses[1]));
    }

    #[test]
    fn pairs_stay_within_their_sequence_and_gap() {
        let config = SceneConfig {
            image_size: 16,
            ..SceneConfig::default()
        };
        let mut dataset = SyntheticDataset::generate(1, 2, 3, 6, &config);
        dataset.max_gap = 3;
        assert_eq!(dataset.sequences.len(), 6);
        let mut reversed = 0;
        for sample in 0..2000 {
            let (sequence, a, b) = dataset.draw_pair(4, sample);
            assert!(sequence < 6 && a < 6 && b < 6 && a != b);
            assert!(a.abs_diff(b) <= 3);
            reversed += usize::from(a > b);
        }
        assert!((reversed as f64 / 2000.0 - 0.5).abs() < 0.05);
        dataset.views = 4;
        for sample in 0..100 {
            let (_, indices) = dataset.draw_views(1, sample);
            assert_eq!(indices.len(), 4);
            assert!(indices.windows(2).all(|w| w[0] < w[1]));
        }
        dataset.views = 7;
        assert!(
            dataset
                .samples(0, 0, 1)
                .unwrap_err()
                .to_string()
                .contains("samples need 7")
        );
        let a = dataset.sequence(0, 2).unwrap();
        let b = dataset.sequence(1, 2).unwrap();
        assert_eq!(a.poses, b.poses);
        assert_ne!(a.frames, b.frames);
    }

    #[test]
    fn held_out_scenes_and_paths_are_none_of_the_training_ones() {
        let config = SceneConfig {
            image_size: 16,
            ..SceneConfig::default()
        };
        let train = SyntheticDataset::generate(5, 3, 2, 4, &config);
        let test = SyntheticDataset::generate_split(5, Split::Test, 3, 2, 4, &config);
        for held_out in &test.sequences {
            for seen in &train.sequences {
                assert_ne!(held_out.frames[0], seen.frames[0]);
                assert_ne!(held_out.poses, seen.poses);
            }
        }
        let name = test.sequence_name(&test.sequences[3]);
        assert_eq!(
            name,
            format!(
                "g5-s{}_t{}",
                HELD_OUT_FIRST_INDEX + 1,
                HELD_OUT_FIRST_INDEX + 1
            )
        );
        assert_eq!(
            scene_of_sequence_id(&name),
            Some(scene_name(5, Split::Test, 1).as_str())
        );
        assert_eq!(train.sequence_name(&train.sequences[0]), "g5-s0_t0");
        for foreign in [
            "s0_t0", "g5-s1", "gx-s1_t0", "g5-s_t1", "5-s1_t1", "g5-s1_tx",
        ] {
            assert_eq!(scene_of_sequence_id(foreign), None, "{foreign}");
        }
    }
}
