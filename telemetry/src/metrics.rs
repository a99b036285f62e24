//! A small Prometheus registry: gauges, counters and histograms with labels, rendered in the
//! text exposition format (version 0.0.4). Hand-written because the processes export a few dozen
//! series and a client library would add a dependency tree for no gain.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::{Mutex, PoisonError};

use crate::exposition::format_value;
use crate::histogram::Histogram;

/// Whether a series can go down (gauge), only up (counter), or counts observations into
/// buckets (histogram).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kind {
    /// A value that is set: step, loss, learning rate.
    Gauge,
    /// A running total: heartbeats, restarts, skipped frames.
    Counter,
    /// A distribution of observations: step and all-reduce durations. The bounds are the
    /// buckets' upper limits, increasing; `+Inf` is implied.
    Histogram(&'static [f64]),
}

/// A series family: its name, help text and kind. Declared as constants by the processes that
/// export them, so the name is spelled once.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Metric {
    /// Prometheus name, e.g. `xfactor_step`.
    pub name: &'static str,
    /// One line for `# HELP`.
    pub help: &'static str,
    /// Gauge, counter or histogram.
    pub kind: Kind,
}

impl Metric {
    /// A gauge family.
    pub const fn gauge(name: &'static str, help: &'static str) -> Self {
        Self {
            name,
            help,
            kind: Kind::Gauge,
        }
    }

    /// A counter family.
    pub const fn counter(name: &'static str, help: &'static str) -> Self {
        Self {
            name,
            help,
            kind: Kind::Counter,
        }
    }

    /// A histogram family with buckets at `bounds` (increasing; e.g.
    /// [`crate::histogram::SECONDS_BUCKETS`]).
    pub const fn histogram(name: &'static str, help: &'static str, bounds: &'static [f64]) -> Self {
        Self {
            name,
            help,
            kind: Kind::Histogram(bounds),
        }
    }
}

/// One labelled series: a gauge's or counter's value, or a histogram's buckets.
enum Series {
    Value(f64),
    Histogram(Histogram),
}

struct Family {
    metric: Metric,
    series: BTreeMap<String, Series>,
}

/// The current value of every series a process exports. Cheap to update from any thread.
#[derive(Default)]
pub struct Registry {
    families: Mutex<BTreeMap<&'static str, Family>>,
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    fn series<R>(
        &self,
        metric: &Metric,
        labels: &[(&str, &str)],
        apply: impl FnOnce(&mut Series) -> R,
    ) -> R {
        let mut families = self.families.lock().unwrap_or_else(PoisonError::into_inner);
        let family = families.entry(metric.name).or_insert_with(|| Family {
            metric: *metric,
            series: BTreeMap::new(),
        });
        let series = family
            .series
            .entry(render_labels(labels))
            .or_insert_with(|| match metric.kind {
                Kind::Histogram(bounds) => Series::Histogram(Histogram::new(bounds)),
                Kind::Gauge | Kind::Counter => Series::Value(0.0),
            });
        apply(series)
    }

    /// Applies `apply` to a gauge's or counter's value; a histogram is left alone (a caller
    /// mixing up kinds must not corrupt it).
    fn update(&self, metric: &Metric, labels: &[(&str, &str)], apply: impl FnOnce(&mut f64)) {
        self.series(metric, labels, |series| {
            if let Series::Value(value) = series {
                apply(value);
            }
        });
    }

    /// Counts `value` (seconds, for the duration histograms) into a histogram's buckets; a
    /// gauge or counter is left alone.
    pub fn observe(&self, metric: &Metric, labels: &[(&str, &str)], value: f64) {
        if let Kind::Histogram(bounds) = metric.kind {
            self.series(metric, labels, |series| {
                if let Series::Histogram(histogram) = series {
                    histogram.observe(bounds, value);
                }
            });
        }
    }

    /// Sets a gauge.
    pub fn set(&self, metric: &Metric, labels: &[(&str, &str)], value: f64) {
        self.update(metric, labels, |slot| *slot = value);
    }

    /// Adds `delta` (non-negative) to a counter.
    pub fn add(&self, metric: &Metric, labels: &[(&str, &str)], delta: f64) {
        self.update(metric, labels, |slot| *slot += delta.max(0.0));
    }

    /// Raises a counter to `total` when a peer reports a running total (never lowers it, so
    /// a restarted peer does not make the counter go backwards).
    pub fn raise_to(&self, metric: &Metric, labels: &[(&str, &str)], total: f64) {
        self.update(metric, labels, |slot| *slot = slot.max(total));
    }

    /// A series' current value, if it was ever set (for tests of what was recorded).
    #[cfg(test)]
    fn value(&self, metric: &Metric, labels: &[(&str, &str)]) -> Option<f64> {
        let families = self.families.lock().unwrap_or_else(PoisonError::into_inner);
        families.get(metric.name).and_then(|family| {
            match family.series.get(&render_labels(labels)) {
                Some(Series::Value(value)) => Some(*value),
                _ => None,
            }
        })
    }

    /// Drops the series of `metric` whose `label` value fails `keep`: a process that labels
    /// series by peer removes the peers that are gone, so stale values do not linger.
    pub fn retain(&self, metric: &Metric, label: &str, keep: impl Fn(&str) -> bool) {
        let mut families = self.families.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(family) = families.get_mut(metric.name) {
            let prefix = format!("{label}=\"");
            family.series.retain(|labels, _| {
                labels
                    .split(&prefix)
                    .nth(1)
                    .and_then(|rest| rest.split('"').next())
                    .is_none_or(&keep)
            });
        }
    }

    /// Every series in the Prometheus text exposition format.
    pub fn render(&self) -> String {
        let families = self.families.lock().unwrap_or_else(PoisonError::into_inner);
        let mut text = String::new();
        for family in families.values() {
            let name = family.metric.name;
            let kind = match family.metric.kind {
                Kind::Gauge => "gauge",
                Kind::Counter => "counter",
                Kind::Histogram(_) => "histogram",
            };
            let _ = writeln!(text, "# HELP {name} {}", family.metric.help);
            let _ = writeln!(text, "# TYPE {name} {kind}");
            for (labels, series) in &family.series {
                match (series, family.metric.kind) {
                    (Series::Value(value), _) => {
                        let _ = writeln!(text, "{name}{labels} {}", format_value(*value));
                    }
                    (Series::Histogram(histogram), Kind::Histogram(bounds)) => {
                        histogram.render(&mut text, name, labels, bounds);
                    }
                    (Series::Histogram(_), _) => {}
                }
            }
        }
        text
    }
}

fn render_labels(labels: &[(&str, &str)]) -> String {
    if labels.is_empty() {
        return String::new();
    }
    let pairs: Vec<String> = labels
        .iter()
        .map(|(key, value)| {
            let escaped = value
                .replace('\\', "\\\\")
                .replace('"', "\\\"")
                .replace('\n', "\\n");
            format!("{key}=\"{escaped}\"")
        })
        .collect();
    format!("{{{}}}", pairs.join(","))
}

#[cfg(test)]
mod tests {
    use super::*;

    const STEP: Metric = Metric::gauge("xfactor_step", "Steps done.");
    const BEATS: Metric = Metric::counter("xfactor_heartbeats_total", "Heartbeats sent.");

    #[test]
    fn renders_help_type_and_labelled_series() {
        let registry = Registry::new();
        registry.set(&STEP, &[("stage", "1")], 3.0);
        registry.set(&STEP, &[("stage", "1")], 4.0);
        registry.add(&BEATS, &[], 2.0);
        registry.add(&BEATS, &[], 1.0);
        registry.add(&BEATS, &[], -5.0);
        let text = registry.render();
        assert!(text.contains("# TYPE xfactor_step gauge\n"), "{text}");
        assert!(text.contains("xfactor_step{stage=\"1\"} 4\n"), "{text}");
        assert!(
            text.contains("# TYPE xfactor_heartbeats_total counter\n"),
            "{text}"
        );
        assert!(text.contains("xfactor_heartbeats_total 3\n"), "{text}");
    }

    #[test]
    fn counters_raised_to_a_total_never_go_down() {
        let registry = Registry::new();
        registry.raise_to(&BEATS, &[("rank", "0")], 7.0);
        registry.raise_to(&BEATS, &[("rank", "0")], 2.0);
        assert_eq!(registry.value(&BEATS, &[("rank", "0")]), Some(7.0));
    }

    #[test]
    fn series_of_departed_peers_are_dropped() {
        let registry = Registry::new();
        for worker in ["1", "2", "3"] {
            registry.set(&STEP, &[("worker", worker)], 1.0);
        }
        registry.set(&STEP, &[], 5.0);
        registry.retain(&STEP, "worker", |w| w != "2");
        let text = registry.render();
        assert!(!text.contains("worker=\"2\""), "{text}");
        assert!(
            text.contains("worker=\"1\"") && text.contains("worker=\"3\""),
            "{text}"
        );
        assert!(text.contains("xfactor_step 5\n"), "{text}");
    }

    #[test]
    fn histograms_render_cumulative_buckets_sum_and_count() {
        const WAIT: Metric = Metric::histogram("xfactor_wait_seconds", "Waits.", &[0.5, 2.0]);
        let registry = Registry::new();
        for value in [0.25, 1.0, 1.5, 9.0] {
            registry.observe(&WAIT, &[], value);
        }
        registry.set(&WAIT, &[], 100.0);
        registry.observe(&STEP, &[], 1.0);
        let text = registry.render();
        assert!(
            text.contains("# TYPE xfactor_wait_seconds histogram\n"),
            "{text}"
        );
        for line in [
            "xfactor_wait_seconds_bucket{le=\"0.5\"} 1\n",
            "xfactor_wait_seconds_bucket{le=\"2\"} 3\n",
            "xfactor_wait_seconds_bucket{le=\"+Inf\"} 4\n",
            "xfactor_wait_seconds_sum 11.75\n",
            "xfactor_wait_seconds_count 4\n",
        ] {
            assert!(text.contains(line), "{line} missing from {text}");
        }
        assert!(!text.contains("xfactor_step"), "{text}");
    }

    #[test]
    fn label_values_are_escaped() {
        let registry = Registry::new();
        registry.set(&STEP, &[("job", "a\"b\\c")], f64::NAN);
        assert!(
            registry
                .render()
                .contains("xfactor_step{job=\"a\\\"b\\\\c\"} NaN")
        );
    }
}
