//! `telemetry`: how the coordinator and the workers tell operators what they are doing.
//!
//! Log lines on stderr set up by [`logging`] (with the shared `--log-format` flag), Prometheus
//! series (gauges, counters, histograms) in a [`Registry`], served as text on
//! `/metrics` by [`http::serve`], training curves written as CSV and drawn to PNG and SVG by
//! [`curves`], grouped bar charts of results by [`bars`] (both through [`plot`], on plotters),
//! and TensorBoard event files by [`tensorboard`]. It knows nothing about the model or the job
//! protocol: callers name their series.

pub mod bars;
pub mod curves;
pub mod histogram;
pub mod http;
pub mod logging;
mod metrics;
pub mod plot;
pub mod tensorboard;
pub mod tiles;
pub mod training;

pub use metrics::{Kind, Metric, Registry};

/// What every binary's `--version` prints: the release and the git commit it was built from.
pub const VERSION: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    " (commit ",
    env!("XFACTOR_GIT_COMMIT"),
    ")"
);
