//! The photometric augmentation and the frame resize against `release-ops.*`, which the
//! authors' release computed with its own code and dm_pix.

mod common;

use data::Image;
use data::resize::center_crop_resize;
use safetensors::{Dtype, SafeTensors};
use trainer_core::augment::{
    ColorJitter, JitterOp, adjust_brightness, adjust_contrast, adjust_hue, adjust_saturation,
    from_unit, gaussian_blur, to_unit,
};

struct Fixture {
    bytes: Vec<u8>,
    json: serde_json::Value,
}

impl Fixture {
    fn read() -> Self {
        let path = common::shared_fixture("release-ops.safetensors");
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let json = std::fs::read_to_string(path.with_extension("json")).expect("release-ops.json");
        Self {
            bytes,
            json: serde_json::from_str(&json).expect("valid JSON"),
        }
    }

    fn tensor(&self, name: &str) -> (Vec<usize>, Dtype, Vec<u8>) {
        let file = SafeTensors::deserialize(&self.bytes).expect("valid safetensors");
        let view = file.tensor(name).unwrap_or_else(|e| panic!("{name}: {e}"));
        (view.shape().to_vec(), view.dtype(), view.data().to_vec())
    }

    /// The `(N, H, W, 3)` float32 tensor `name` as `N` images.
    fn images(&self, name: &str) -> Vec<Image> {
        let (shape, dtype, data) = self.tensor(name);
        assert_eq!(dtype, Dtype::F32, "{name}");
        let values: Vec<f32> = data
            .chunks_exact(4)
            .map(|w| f32::from_le_bytes([w[0], w[1], w[2], w[3]]))
            .collect();
        let per = shape[1] * shape[2] * 3;
        values
            .chunks_exact(per)
            .map(|pixels| Image {
                height: shape[1],
                width: shape[2],
                pixels: pixels.to_vec(),
            })
            .collect()
    }

    fn number(&self, path: &[&str]) -> f32 {
        let mut value = &self.json;
        for key in path {
            value = match (value.as_array(), key.parse::<usize>()) {
                (Some(items), Ok(index)) => &items[index],
                _ => &value[*key],
            };
        }
        value
            .as_f64()
            .unwrap_or_else(|| panic!("{path:?} is not a number")) as f32
    }
}

fn assert_close(label: &str, ours: &[Image], theirs: &[Image], tolerance: f32) {
    assert_eq!(ours.len(), theirs.len(), "{label}");
    let mut worst = 0.0f32;
    for (a, b) in ours.iter().zip(theirs) {
        for (x, y) in a.pixels.iter().zip(&b.pixels) {
            worst = worst.max((x - y).abs());
        }
    }
    println!("{label}: max_abs_err={worst:.2e}");
    assert!(worst <= tolerance, "{label}: off by {worst:e}");
}

fn single_op(image: &Image, op: &str, value: f32) -> Image {
    let mut unit = to_unit(image);
    match op {
        "brightness" => adjust_brightness(&mut unit, value),
        "contrast" => adjust_contrast(&mut unit, value),
        "saturation" => adjust_saturation(&mut unit, value),
        "hue" => adjust_hue(&mut unit, value),
        other => panic!("unknown op {other}"),
    }
    from_unit(image, &unit)
}

#[test]
fn every_jitter_op_and_the_composed_jitter_match_the_release() {
    let fixture = Fixture::read();
    let inputs = fixture.images("input.images");
    for op in ["brightness", "contrast", "saturation", "hue"] {
        for k in 0..2 {
            let value = fixture.number(&["single_ops", op, &k.to_string()]);
            let ours: Vec<Image> = inputs.iter().map(|x| single_op(x, op, value)).collect();
            let theirs = fixture.images(&format!("output.{op}_{k}"));
            assert_close(&format!("{op}_{k} ({value})"), &ours, &theirs, 1e-5);
        }
    }
    let composed = &fixture.json["jitter_composed"];
    let order: Vec<JitterOp> = composed["order"]
        .as_array()
        .expect("order list")
        .iter()
        .map(|op| match op.as_str() {
            Some("brightness") => JitterOp::Brightness,
            Some("contrast") => JitterOp::Contrast,
            Some("saturation") => JitterOp::Saturation,
            Some("hue") => JitterOp::Hue,
            other => panic!("unknown op {other:?}"),
        })
        .collect();
    let value = |op: &str| fixture.number(&["jitter_composed", "values", op]);
    let jitter = ColorJitter {
        brightness: value("brightness"),
        contrast: value("contrast"),
        saturation: value("saturation"),
        hue: value("hue"),
        order: order.try_into().expect("four ops"),
    };
    let ours: Vec<Image> = inputs.iter().map(|x| jitter.apply(x)).collect();
    assert_close(
        "jitter_composed",
        &ours,
        &fixture.images("output.jitter_composed"),
        1e-5,
    );
}

#[test]
fn blur_matches_the_release() {
    let fixture = Fixture::read();
    let inputs = fixture.images("input.images");
    let kernel = fixture.number(&["blur", "kernel_size"]) as usize;
    for k in 0..2 {
        let sigma = fixture.number(&["blur", "sigmas", &k.to_string()]);
        let ours: Vec<Image> = inputs
            .iter()
            .map(|x| gaussian_blur(x, kernel, sigma))
            .collect();
        let theirs = fixture.images(&format!("output.blur_{k}"));
        assert_close(&format!("blur_{k} (sigma {sigma})"), &ours, &theirs, 1e-5);
    }
}

#[test]
fn both_resizes_match_the_release_byte_for_byte() {
    let fixture = Fixture::read();
    for (input, output) in [
        ("resize.input_square", "resize.output_square_64"),
        ("resize.input_wide", "resize.output_wide_48"),
    ] {
        let (shape, dtype, source) = fixture.tensor(input);
        let (out_shape, _, expected) = fixture.tensor(output);
        assert_eq!(dtype, Dtype::U8);
        let ours = center_crop_resize(&source, shape[0], shape[1], out_shape[0]);
        let differing = ours
            .bytes
            .iter()
            .zip(&expected)
            .filter(|(a, b)| a != b)
            .count();
        println!("{output}: {differing} of {} bytes differ", expected.len());
        assert_eq!(ours.bytes.len(), expected.len(), "{output}");
        assert_eq!(differing, 0, "{output}");
    }
}
