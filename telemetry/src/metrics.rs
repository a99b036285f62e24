//! Prometheus series through the `prometheus` crate: gauges, counters and histograms with
//! labels, declared as constants by the processes that export them, and exposed in Prometheus'
//! text format (0.0.4), which every Prometheus scrapes and `promtool check metrics` lints. Not
//! the `prometheus-client` crate: it writes only OpenMetrics text, whose counters (a family
//! `x` with samples `x_total`) Debian's promtool 2.42 reads as series without help.

use std::collections::BTreeMap;
use std::sync::{Mutex, PoisonError};

use prometheus::core::Collector;
use prometheus::{CounterVec, GaugeVec, HistogramOpts, HistogramVec, Opts, TextEncoder};

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

/// One family's labelled series, of its kind.
enum Series {
    Gauge(GaugeVec),
    Counter(CounterVec),
    Histogram(HistogramVec),
}

/// A registered family and the label names its series carry (fixed by its first update).
struct Family {
    series: Series,
    labels: Vec<String>,
}

impl Family {
    /// A family of `metric` with series labelled `labels`.
    fn new(metric: &Metric, labels: Vec<String>) -> prometheus::Result<Self> {
        let names: Vec<&str> = labels.iter().map(String::as_str).collect();
        let opts = Opts::new(metric.name, metric.help);
        let series = match metric.kind {
            Kind::Gauge => Series::Gauge(GaugeVec::new(opts, &names)?),
            Kind::Counter => Series::Counter(CounterVec::new(opts, &names)?),
            Kind::Histogram(bounds) => Series::Histogram(HistogramVec::new(
                HistogramOpts::from(opts).buckets(bounds.to_vec()),
                &names,
            )?),
        };
        Ok(Self { series, labels })
    }

    fn collector(&self) -> Box<dyn Collector> {
        match &self.series {
            Series::Gauge(vec) => Box::new(vec.clone()),
            Series::Counter(vec) => Box::new(vec.clone()),
            Series::Histogram(vec) => Box::new(vec.clone()),
        }
    }
}

/// The current value of every series a process exports. Cheap to update from any thread.
pub struct Registry {
    registry: prometheus::Registry,
    families: Mutex<BTreeMap<&'static str, Family>>,
}

impl Default for Registry {
    fn default() -> Self {
        Self::new()
    }
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self {
            registry: prometheus::Registry::new(),
            families: Mutex::new(BTreeMap::new()),
        }
    }

    /// Applies `apply` to the series of `metric` labelled `labels`, registering the family on
    /// its first update. An update whose label names differ from the family's first is dropped
    /// with a warning: series names and labels are the exporter's contract.
    fn with_series(
        &self,
        metric: &Metric,
        labels: &[(&str, &str)],
        apply: impl FnOnce(&Series, &[&str]),
    ) {
        let mut families = self.families.lock().unwrap_or_else(PoisonError::into_inner);
        let names: Vec<String> = labels.iter().map(|(key, _)| (*key).to_string()).collect();
        if !families.contains_key(metric.name) {
            let registered = Family::new(metric, names.clone()).and_then(|family| {
                self.registry.register(family.collector())?;
                Ok(family)
            });
            match registered {
                Ok(family) => {
                    families.insert(metric.name, family);
                }
                Err(error) => {
                    tracing::warn!(metric = metric.name, %error, "series not exported");
                    return;
                }
            }
        }
        let Some(family) = families.get(metric.name) else {
            return;
        };
        if family.labels != names {
            tracing::warn!(metric = metric.name, labels = ?names, expected = ?family.labels, "update with other labels dropped");
            return;
        }
        let values: Vec<&str> = labels.iter().map(|(_, value)| *value).collect();
        apply(&family.series, &values);
    }

    /// Counts `value` (seconds, for the duration histograms) into a histogram's buckets; a
    /// gauge or counter is left alone, and NaN is not counted (it would make the sum NaN
    /// forever).
    pub fn observe(&self, metric: &Metric, labels: &[(&str, &str)], value: f64) {
        if value.is_nan() {
            return;
        }
        self.with_series(metric, labels, |series, values| {
            if let Series::Histogram(vec) = series {
                vec.with_label_values(values).observe(value);
            }
        });
    }

    /// Sets a gauge (a counter is set to `value` where that does not lower it).
    pub fn set(&self, metric: &Metric, labels: &[(&str, &str)], value: f64) {
        self.with_series(metric, labels, |series, values| match series {
            Series::Gauge(vec) => vec.with_label_values(values).set(value),
            Series::Counter(vec) => raise(&vec.with_label_values(values), value),
            Series::Histogram(_) => {}
        });
    }

    /// Adds `delta` (non-negative) to a counter or gauge.
    pub fn add(&self, metric: &Metric, labels: &[(&str, &str)], delta: f64) {
        let delta = delta.max(0.0);
        self.with_series(metric, labels, |series, values| match series {
            Series::Gauge(vec) => vec.with_label_values(values).add(delta),
            Series::Counter(vec) => vec.with_label_values(values).inc_by(delta),
            Series::Histogram(_) => {}
        });
    }

    /// Raises a counter to `total` when a peer reports a running total (never lowers it, so
    /// a restarted peer does not make the counter go backwards).
    pub fn raise_to(&self, metric: &Metric, labels: &[(&str, &str)], total: f64) {
        self.with_series(metric, labels, |series, values| match series {
            Series::Counter(vec) => raise(&vec.with_label_values(values), total),
            Series::Gauge(vec) => {
                let gauge = vec.with_label_values(values);
                gauge.set(gauge.get().max(total));
            }
            Series::Histogram(_) => {}
        });
    }

    /// A series' current value, if it was ever set (for tests of what was recorded).
    #[cfg(test)]
    fn value(&self, metric: &Metric, labels: &[(&str, &str)]) -> Option<f64> {
        let values: Vec<&str> = labels.iter().map(|(_, value)| *value).collect();
        let families = self.families.lock().unwrap_or_else(PoisonError::into_inner);
        let family = families.get(metric.name)?;
        let exists = family_label_values(family)
            .iter()
            .any(|series| series.iter().map(String::as_str).eq(values.iter().copied()));
        match (&family.series, exists) {
            (Series::Gauge(vec), true) => Some(vec.with_label_values(&values).get()),
            (Series::Counter(vec), true) => Some(vec.with_label_values(&values).get()),
            _ => None,
        }
    }

    /// Drops the series of `metric` whose `label` value fails `keep`: a process that labels
    /// series by peer removes the peers that are gone, so stale values do not linger.
    pub fn retain(&self, metric: &Metric, label: &str, keep: impl Fn(&str) -> bool) {
        let families = self.families.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(family) = families.get(metric.name) else {
            return;
        };
        let Some(position) = family.labels.iter().position(|name| name == label) else {
            return;
        };
        for values in family_label_values(family) {
            if keep(&values[position]) {
                continue;
            }
            let removed = match &family.series {
                Series::Gauge(vec) => vec.remove_label_values(&values),
                Series::Counter(vec) => vec.remove_label_values(&values),
                Series::Histogram(vec) => vec.remove_label_values(&values),
            };
            if let Err(error) = removed {
                tracing::debug!(metric = metric.name, %error, "series already gone");
            }
        }
    }

    /// Every series in the Prometheus text exposition format (0.0.4).
    pub fn render(&self) -> String {
        let mut text = String::new();
        if let Err(error) = TextEncoder::new().encode_utf8(&self.registry.gather(), &mut text) {
            tracing::warn!(%error, "metrics not encoded");
        }
        text
    }
}

/// Raises `counter` to `total` (never lowers it).
fn raise(counter: &prometheus::Counter, total: f64) {
    let current = counter.get();
    if total > current {
        counter.inc_by(total - current);
    }
}

/// The label values of every series of `family`, in the family's label order.
fn family_label_values(family: &Family) -> Vec<Vec<String>> {
    family
        .collector()
        .collect()
        .iter()
        .flat_map(|collected| collected.get_metric())
        .map(|series| {
            let pairs = series.get_label();
            family
                .labels
                .iter()
                .map(|name| {
                    pairs
                        .iter()
                        .find(|pair| pair.name() == name)
                        .map_or_else(String::new, |pair| pair.value().to_string())
                })
                .collect()
        })
        .collect()
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
        registry.retain(&STEP, "worker", |w| w != "2");
        let text = registry.render();
        assert!(!text.contains("worker=\"2\""), "{text}");
        assert!(
            text.contains("xfactor_step{worker=\"1\"} 1\n") && text.contains("worker=\"3\""),
            "{text}"
        );
    }

    #[test]
    fn an_update_with_other_label_names_is_dropped() {
        let registry = Registry::new();
        registry.set(&STEP, &[("worker", "1")], 1.0);
        registry.set(&STEP, &[], 5.0);
        registry.set(&STEP, &[("rank", "0")], 6.0);
        let text = registry.render();
        assert!(text.contains("xfactor_step{worker=\"1\"} 1\n"), "{text}");
        assert!(!text.contains(" 5\n") && !text.contains(" 6\n"), "{text}");
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
