//! The few TensorFlow protobuf messages an event file needs (`event.proto`, `summary.proto`,
//! `tensor.proto`), written with prost's derive so no `protoc` or TensorFlow is needed. Field
//! numbers are TensorFlow's; fields TensorBoard does not read for scalars, images and text are
//! left out, which protobuf allows.

/// One record of an event file: a header (`file_version`) or a summary at a step.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Event {
    /// Seconds since the epoch when the event happened.
    #[prost(double, tag = "1")]
    pub wall_time: f64,
    /// The training step the event belongs to.
    #[prost(int64, tag = "2")]
    pub step: i64,
    /// What the event carries.
    #[prost(oneof = "EventKind", tags = "3, 5")]
    pub kind: Option<EventKind>,
}

/// The payload of an [`Event`].
#[derive(Clone, PartialEq, prost::Oneof)]
pub enum EventKind {
    /// The header every event file starts with, `brain.Event:2`.
    #[prost(string, tag = "3")]
    FileVersion(String),
    /// Values logged at a step.
    #[prost(message, tag = "5")]
    Summary(Summary),
}

/// Values logged together at one step.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Summary {
    /// The values, one per tag.
    #[prost(message, repeated, tag = "1")]
    pub value: Vec<SummaryValue>,
}

/// One tagged value.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryValue {
    /// The series name (`loss/total`, ...).
    #[prost(string, tag = "1")]
    pub tag: String,
    /// Which plugin shows it (text needs this; scalars and images do not).
    #[prost(message, optional, tag = "9")]
    pub metadata: Option<SummaryMetadata>,
    /// The value.
    #[prost(oneof = "ValueKind", tags = "2, 4, 8")]
    pub value: Option<ValueKind>,
}

/// The payload of a [`SummaryValue`].
#[derive(Clone, PartialEq, prost::Oneof)]
pub enum ValueKind {
    /// A scalar (TensorBoard's SCALARS tab).
    #[prost(float, tag = "2")]
    SimpleValue(f32),
    /// An encoded image (IMAGES tab).
    #[prost(message, tag = "4")]
    Image(SummaryImage),
    /// A tensor; here always strings for the TEXT tab.
    #[prost(message, tag = "8")]
    Tensor(TensorProto),
}

/// An image as PNG bytes with its size.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryImage {
    /// Rows.
    #[prost(int32, tag = "1")]
    pub height: i32,
    /// Columns.
    #[prost(int32, tag = "2")]
    pub width: i32,
    /// Channels: 1 grey, 3 RGB, 4 RGBA.
    #[prost(int32, tag = "3")]
    pub colorspace: i32,
    /// The PNG file's bytes.
    #[prost(bytes = "vec", tag = "4")]
    pub encoded_image_string: Vec<u8>,
}

/// Names the plugin that owns a value.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryMetadata {
    /// The plugin.
    #[prost(message, optional, tag = "1")]
    pub plugin_data: Option<PluginData>,
}

/// A plugin's name and its own settings (empty here).
#[derive(Clone, PartialEq, prost::Message)]
pub struct PluginData {
    /// `text` for the TEXT tab.
    #[prost(string, tag = "1")]
    pub plugin_name: String,
    /// Plugin-specific bytes.
    #[prost(bytes = "vec", tag = "2")]
    pub content: Vec<u8>,
}

/// A tensor of strings (`DT_STRING`), the form the text plugin reads.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TensorProto {
    /// The element type; [`DT_STRING`] here.
    #[prost(int32, tag = "1")]
    pub dtype: i32,
    /// The shape; no dimensions for a scalar.
    #[prost(message, optional, tag = "2")]
    pub tensor_shape: Option<TensorShape>,
    /// The strings.
    #[prost(bytes = "vec", repeated, tag = "8")]
    pub string_val: Vec<Vec<u8>>,
}

/// A tensor's dimensions.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TensorShape {
    /// Sizes, outermost first.
    #[prost(message, repeated, tag = "2")]
    pub dim: Vec<TensorDim>,
}

/// One dimension of a [`TensorShape`].
#[derive(Clone, PartialEq, prost::Message)]
pub struct TensorDim {
    /// Its size.
    #[prost(int64, tag = "1")]
    pub size: i64,
}

/// TensorFlow's `DataType` value for strings.
pub const DT_STRING: i32 = 7;
