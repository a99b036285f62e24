//! Histogram series for the registry: counts per upper bound (`le`), their sum and count,
//! rendered as Prometheus' cumulative `_bucket{le=...}`, `_sum` and `_count` lines, so a
//! dashboard can show a duration's distribution and quantiles rather than its last value.

use std::fmt::Write;

use crate::exposition::format_value;

/// Upper bounds for durations from half a millisecond (a small all-reduce on loopback) to ten
/// minutes (a paper-model checkpoint upload over a slow link), about 2.5x apart.
pub const SECONDS_BUCKETS: &[f64] = &[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
    60.0, 120.0, 300.0, 600.0,
];

/// One labelled histogram: how many observations fell at or below each bound.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Histogram {
    /// Observations per bucket (not cumulative); the last counts those above every bound.
    counts: Vec<u64>,
    sum: f64,
}

impl Histogram {
    pub(crate) fn new(bounds: &[f64]) -> Self {
        Self {
            counts: vec![0; bounds.len() + 1],
            sum: 0.0,
        }
    }

    /// Counts `value` in the first bucket whose bound is at least it. NaN is not counted: it
    /// would make the sum NaN forever.
    pub(crate) fn observe(&mut self, bounds: &[f64], value: f64) {
        if value.is_nan() {
            return;
        }
        let bucket = bounds.partition_point(|&bound| bound < value);
        if let Some(count) = self.counts.get_mut(bucket) {
            *count += 1;
        }
        self.sum += value;
    }

    /// Appends the `_bucket`, `_sum` and `_count` lines of series `name{labels}`, where
    /// `labels` is the rendered label set (`{a="b"}` or empty).
    pub(crate) fn render(&self, text: &mut String, name: &str, labels: &str, bounds: &[f64]) {
        let inner = labels.trim_start_matches('{').trim_end_matches('}');
        let separator = if inner.is_empty() { "" } else { "," };
        let mut cumulative = 0u64;
        let infinite = f64::INFINITY;
        for (bound, count) in bounds.iter().chain([&infinite]).zip(&self.counts) {
            cumulative += count;
            let le = format_value(*bound);
            let _ = writeln!(
                text,
                "{name}_bucket{{{inner}{separator}le=\"{le}\"}} {cumulative}"
            );
        }
        let _ = writeln!(text, "{name}_sum{labels} {}", format_value(self.sum));
        let _ = writeln!(text, "{name}_count{labels} {cumulative}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_land_in_the_first_bucket_at_or_above_them() {
        let bounds = [0.1, 1.0];
        let mut histogram = Histogram::new(&bounds);
        for value in [0.05, 0.1, 0.5, 3.0, f64::NAN] {
            histogram.observe(&bounds, value);
        }
        let mut text = String::new();
        histogram.render(&mut text, "t_seconds", "{rank=\"0\"}", &bounds);
        assert_eq!(
            text,
            "t_seconds_bucket{rank=\"0\",le=\"0.1\"} 2\n\
             t_seconds_bucket{rank=\"0\",le=\"1\"} 3\n\
             t_seconds_bucket{rank=\"0\",le=\"+Inf\"} 4\n\
             t_seconds_sum{rank=\"0\"} 3.65\n\
             t_seconds_count{rank=\"0\"} 4\n"
        );
    }

    #[test]
    fn the_seconds_bounds_increase() {
        assert!(SECONDS_BUCKETS.windows(2).all(|w| w[0] < w[1]));
    }
}
