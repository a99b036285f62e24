//! The bounds of the duration histograms (Prometheus' cumulative `_bucket{le=...}`, `_sum` and
//! `_count` series), so a dashboard can show a duration's distribution and quantiles rather
//! than its last value.

/// Upper bounds for durations from half a millisecond (a small all-reduce on loopback) to ten
/// minutes (a paper-model checkpoint upload over a slow link), about 2.5x apart.
pub const SECONDS_BUCKETS: &[f64] = &[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
    60.0, 120.0, 300.0, 600.0,
];
