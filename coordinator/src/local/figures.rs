//! Headline figures read out of an evaluation's `report.json` (the coordinator links no tensor
//! library, so it reads the report as JSON, not through the evaluation's types): the first
//! run's summary line and its guard read them the same way.

use serde_json::Value;

/// `SE3_Auc@30` of a camera-metrics object of the report and its bootstrap spread; `None`
/// where either is missing.
pub fn auc30(metrics: &Value) -> Option<(f64, f64)> {
    let value = metrics["thresholds"]
        .as_array()?
        .iter()
        .find(|s| s["threshold"] == 30)?["auc"]
        .as_f64()?;
    Some((value, metrics["spread"]["auc30"].as_f64()?))
}

/// A reconstruction object's PSNR and its spread; `None` where either is missing.
pub fn psnr(reconstruction: &Value) -> Option<(f64, f64)> {
    Some((
        reconstruction["psnr"].as_f64()?,
        reconstruction["psnr_spread"].as_f64()?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_come_with_their_spreads_or_not_at_all() {
        let metrics = serde_json::json!({
            "thresholds": [{"threshold": 20, "auc": 0.1}, {"threshold": 30, "auc": 0.25}],
            "spread": {"auc20": 0.01, "auc30": 0.02}
        });
        assert_eq!(auc30(&metrics), Some((0.25, 0.02)));
        assert_eq!(auc30(&serde_json::json!({"thresholds": []})), None);
        let reconstruction = serde_json::json!({"psnr": 16.0, "psnr_spread": 0.13});
        assert_eq!(psnr(&reconstruction), Some((16.0, 0.13)));
        assert_eq!(psnr(&serde_json::json!({"psnr": 16.0})), None);
    }
}
