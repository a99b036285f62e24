//! `transfer` on the example videos: the camera path of `target/` rendered in the first frame
//! of `transfer/` writes one PNG per frame, a strip and a GIF of the right sizes, and the frames
//! change along the trajectory.

mod common;

use burn::tensor::Device;
use evaluation::{TransferRequest, run_transfer};
use image::AnimationDecoder;
use trainer_core::XFactorConfig;

#[test]
fn transfer_writes_frames_strip_and_gif_for_the_example_videos() {
    let videos = common::shared_fixture("example_videos");
    let scratch = tempfile::tempdir().unwrap();
    let config = XFactorConfig::tiny(32);
    let checkpoint = common::untrained_checkpoint(&config, 5, scratch.path());
    let out_dir = scratch.path().join("out");
    let request = TransferRequest {
        checkpoint,
        trajectory: videos.join("target").to_string_lossy().into_owned(),
        scene: videos
            .join("transfer/000.jpg")
            .to_string_lossy()
            .into_owned(),
        reference: 0,
        out_dir: out_dir.clone(),
    };
    let output = run_transfer(&request, &Device::flex()).unwrap();
    assert_eq!(output.frames.len(), 30);
    let frames: Vec<image::RgbImage> = output
        .frames
        .iter()
        .map(|p| image::open(p).unwrap().into_rgb8())
        .collect();
    assert!(frames.iter().all(|f| f.dimensions() == (32, 32)));
    let difference = |a: &image::RgbImage, b: &image::RgbImage| -> u64 {
        a.as_raw()
            .iter()
            .zip(b.as_raw())
            .map(|(x, y)| u64::from(x.abs_diff(*y)))
            .sum()
    };
    let changed = frames
        .windows(2)
        .filter(|w| difference(&w[0], &w[1]) > 0)
        .count();
    assert!(
        difference(&frames[0], &frames[29]) > 0,
        "first and last frames are identical"
    );
    assert!(
        changed >= 15,
        "only {changed} of 29 consecutive frames differ"
    );
    let strip = image::open(&output.strip).unwrap();
    assert_eq!((strip.width(), strip.height()), (8 * 34 + 2, 2 * 34 + 2));
    let gif = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(
        std::fs::File::open(&output.gif).unwrap(),
    ))
    .unwrap();
    let gif_frames = gif.into_frames().collect_frames().unwrap();
    assert_eq!(gif_frames.len(), 30);
    assert_eq!(gif_frames[0].buffer().dimensions(), (32, 32));
}
