//! `telemetry`: how the coordinator and the workers tell operators what they are doing.
//!
//! Log lines on stderr set up by [`logging`] (with the shared `--log-format` flag), Prometheus
//! series (gauges, counters, histograms) in a [`metrics::Registry`], served as text on
//! `/metrics` by [`http::serve`], loss curves written as CSV and drawn to PNG by [`curves`],
//! and grouped bar charts of results by [`bars`]. It knows nothing about the model or the job
//! protocol: callers name their series.

pub mod bars;
pub mod curves;
mod draw;
pub mod histogram;
pub mod http;
pub mod logging;
pub mod metrics;
pub mod training;

pub use metrics::{Metric, Registry};
