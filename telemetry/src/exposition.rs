//! Numbers as Prometheus' text exposition format writes them, shared by plain series and
//! histogram buckets.

/// A sample value or `le` bound as Prometheus writes it (`NaN`, `+Inf`, shortest decimal).
pub(crate) fn format_value(value: f64) -> String {
    if value.is_nan() {
        "NaN".into()
    } else if value.is_infinite() {
        if value > 0.0 { "+Inf" } else { "-Inf" }.into()
    } else {
        format!("{value}")
    }
}
