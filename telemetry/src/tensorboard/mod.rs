//! TensorBoard event files, written without TensorFlow: the [`messages`] a scalar, an image
//! and a text summary need, framed as TFRecords (little-endian length, masked CRC-32C of the
//! length, the data, masked CRC-32C of the data), which is what `tensorboard --logdir` and its
//! `EventAccumulator` read.
//!
//! Object stores cannot append, so a writer keeps its events as segments: an [`EventSegment`]
//! is a complete event file (header first) that the caller stores whole and rewrites as it
//! grows, starting a new file (a new [`event_file_name`] sequence number) when it is full.
//! TensorBoard reads every `*tfevents*` file of a run directory in name order.

mod messages;

use prost::Message;

pub use messages::{
    DT_STRING, Event, EventKind, PluginData, Summary, SummaryImage, SummaryMetadata, SummaryValue,
    TensorProto, TensorShape, ValueKind,
};

/// Why a value could not be added.
#[derive(Debug, thiserror::Error)]
pub enum EventError {
    /// The bytes given as an image are not a PNG file.
    #[error("image {tag:?} at step {step} is not a PNG file ({bytes} bytes)")]
    NotPng {
        /// The image's tag.
        tag: String,
        /// Its step.
        step: u64,
        /// How many bytes were given.
        bytes: usize,
    },
}

/// `crc` masked as TFRecord stores it, so a CRC of data that holds CRCs stays distinct.
fn masked_crc(data: &[u8]) -> u32 {
    let crc = crc32c::crc32c(data);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// `data` framed as one TFRecord.
pub fn frame(data: &[u8]) -> Vec<u8> {
    let length = (data.len() as u64).to_le_bytes();
    let mut record = Vec::with_capacity(data.len() + 16);
    record.extend_from_slice(&length);
    record.extend_from_slice(&masked_crc(&length).to_le_bytes());
    record.extend_from_slice(data);
    record.extend_from_slice(&masked_crc(data).to_le_bytes());
    record
}

/// The name TensorBoard recognises (`events.out.tfevents.` + a timestamp + a host), with a
/// sequence number so a run's segments sort in the order they were written.
pub fn event_file_name(started_unix_s: u64, host: &str, sequence: u64) -> String {
    format!("events.out.tfevents.{started_unix_s:010}.{host}.{sequence:06}")
}

/// Width, height and channels of a PNG from its header, or `None` for other bytes.
fn png_size(png: &[u8]) -> Option<(i32, i32, i32)> {
    const SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
    if png.len() < 26 || !png.starts_with(SIGNATURE) || &png[12..16] != b"IHDR" {
        return None;
    }
    let word = |at: usize| i32::from_be_bytes([png[at], png[at + 1], png[at + 2], png[at + 3]]);
    let channels = match png[25] {
        0 => 1,
        4 => 2,
        6 => 4,
        _ => 3,
    };
    Some((word(16), word(20), channels))
}

/// One event file being filled: the header, then framed summaries.
#[derive(Debug, Clone)]
pub struct EventSegment {
    bytes: Vec<u8>,
    events: usize,
}

impl EventSegment {
    /// An event file holding only its header, dated `wall_time` (seconds since the epoch).
    pub fn new(wall_time: f64) -> Self {
        let header = Event {
            wall_time,
            step: 0,
            kind: Some(EventKind::FileVersion("brain.Event:2".into())),
        };
        Self {
            bytes: frame(&header.encode_to_vec()),
            events: 0,
        }
    }

    /// Summaries added so far (the header not counted).
    pub fn events(&self) -> usize {
        self.events
    }

    /// The whole file as it stands.
    pub fn bytes(&self) -> &[u8] {
        &self.bytes
    }

    fn push(
        &mut self,
        wall_time: f64,
        step: u64,
        tag: &str,
        metadata: Option<SummaryMetadata>,
        value: ValueKind,
    ) {
        let value = SummaryValue {
            tag: tag.into(),
            metadata,
            value: Some(value),
        };
        let event = Event {
            wall_time,
            step: i64::try_from(step).unwrap_or(i64::MAX),
            kind: Some(EventKind::Summary(Summary { value: vec![value] })),
        };
        self.bytes.extend(frame(&event.encode_to_vec()));
        self.events += 1;
    }

    /// A scalar (stored as f32, as TensorBoard's simple values are).
    pub fn scalar(&mut self, wall_time: f64, step: u64, tag: &str, value: f64) {
        let value = ValueKind::SimpleValue(value as f32);
        self.push(wall_time, step, tag, None, value);
    }

    /// A PNG image; its size is read from its header.
    pub fn image(
        &mut self,
        wall_time: f64,
        step: u64,
        tag: &str,
        png: Vec<u8>,
    ) -> Result<(), EventError> {
        let Some((width, height, colorspace)) = png_size(&png) else {
            return Err(EventError::NotPng {
                tag: tag.into(),
                step,
                bytes: png.len(),
            });
        };
        let image = ValueKind::Image(SummaryImage {
            height,
            width,
            colorspace,
            encoded_image_string: png,
        });
        self.push(wall_time, step, tag, None, image);
        Ok(())
    }

    /// Text (TensorBoard renders it as Markdown).
    pub fn text(&mut self, wall_time: f64, step: u64, tag: &str, text: &str) {
        let metadata = SummaryMetadata {
            plugin_data: Some(PluginData {
                plugin_name: "text".into(),
                content: Vec::new(),
            }),
        };
        let strings = ValueKind::Tensor(TensorProto {
            dtype: DT_STRING,
            tensor_shape: Some(TensorShape { dim: Vec::new() }),
            string_val: vec![text.as_bytes().to_vec()],
        });
        self.push(wall_time, step, tag, Some(metadata), strings);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Splits an event file into its records, checking both CRCs of each.
    fn records(mut bytes: &[u8]) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        while !bytes.is_empty() {
            let length_bytes = &bytes[..8];
            let length = u64::from_le_bytes(length_bytes.try_into().unwrap()) as usize;
            let crc = u32::from_le_bytes(bytes[8..12].try_into().unwrap());
            assert_eq!(crc, masked_crc(length_bytes));
            let data = &bytes[12..12 + length];
            let crc = u32::from_le_bytes(bytes[12 + length..16 + length].try_into().unwrap());
            assert_eq!(crc, masked_crc(data));
            out.push(data.to_vec());
            bytes = &bytes[16 + length..];
        }
        out
    }

    #[test]
    fn the_masked_crc_matches_tensorflows_for_a_known_input() {
        // CRC-32C of "123456789" is 0xE3069283 (RFC 3720's check value); TensorFlow masks it
        // as ((crc >> 15) | (crc << 17)) + 0xa282ead8, which is 0xC78AB0E5 (worked out by hand
        // in Python).
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
        assert_eq!(masked_crc(b"123456789"), 0xC78A_B0E5);
    }

    #[test]
    fn a_segment_is_a_header_then_one_event_per_value() {
        let mut segment = EventSegment::new(10.0);
        segment.scalar(11.0, 3, "loss/total", 0.25);
        segment.text(12.0, 0, "config", "a: 1");
        let records = records(segment.bytes());
        assert_eq!(records.len(), 3);
        assert_eq!(segment.events(), 2);
        let header = Event::decode(&records[0][..]).unwrap();
        assert_eq!(
            header.kind,
            Some(EventKind::FileVersion("brain.Event:2".into()))
        );
        let scalar = Event::decode(&records[1][..]).unwrap();
        assert_eq!(scalar.step, 3);
        let Some(EventKind::Summary(summary)) = scalar.kind else {
            panic!("not a summary: {scalar:?}");
        };
        assert_eq!(summary.value[0].tag, "loss/total");
        assert_eq!(summary.value[0].value, Some(ValueKind::SimpleValue(0.25)));
    }

    #[test]
    fn an_image_carries_its_png_size_and_other_bytes_are_refused() {
        let mut png = Vec::new();
        image::RgbImage::new(5, 3)
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let mut segment = EventSegment::new(0.0);
        segment.image(1.0, 2, "grid", png.clone()).unwrap();
        let event = Event::decode(&records(segment.bytes())[1][..]).unwrap();
        let Some(EventKind::Summary(summary)) = event.kind else {
            panic!("not a summary");
        };
        let Some(ValueKind::Image(image)) = &summary.value[0].value else {
            panic!("not an image");
        };
        assert_eq!((image.width, image.height, image.colorspace), (5, 3, 3));
        assert_eq!(image.encoded_image_string, png);
        let refused = segment.image(1.0, 2, "grid", b"GIF89a".to_vec());
        assert!(
            matches!(refused, Err(EventError::NotPng { bytes: 6, .. })),
            "{refused:?}"
        );
    }

    #[test]
    fn file_names_sort_in_writing_order() {
        let names: Vec<String> = [0, 9, 10, 123]
            .iter()
            .map(|&n| event_file_name(1_700_000_000, "coordinator", n))
            .collect();
        let mut sorted = names.clone();
        sorted.sort();
        assert_eq!(names, sorted);
        assert!(names[0].starts_with("events.out.tfevents.1700000000.coordinator."));
    }
}
