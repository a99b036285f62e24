//! AUC as the release computes it (`vggt/metrics/camera_metric.py`): `torch.histc(errors,
//! bins=31, min=0, max=30)`, so 31 bins of `30/31` degree with errors above 30 dropped, divided
//! by the pair count; AUC@t is the mean of its cumulative sum over the first `t` bins. The bins
//! are not 1 degree wide, so this differs slightly from an AUC over `[0, t]` degrees; the
//! paper's numbers are this one.

/// Bins of the release's histogram.
pub const AUC_BINS: usize = 31;
/// Upper end of the histogram, degrees.
pub const AUC_MAX_DEGREES: f64 = 30.0;

/// The histogram of `errors` (degrees) over `[0, 30]` in [`AUC_BINS`] bins, each count divided
/// by `pairs`; `NaN` and out-of-range errors count in no bin, and 30 itself falls in the last.
pub fn normalized_histogram(errors: impl Iterator<Item = f64>, pairs: usize) -> [f64; AUC_BINS] {
    let mut counts = [0usize; AUC_BINS];
    for error in errors {
        if !(0.0..=AUC_MAX_DEGREES).contains(&error) {
            continue;
        }
        let bin = (error * AUC_BINS as f64 / AUC_MAX_DEGREES) as usize;
        counts[bin.min(AUC_BINS - 1)] += 1;
    }
    counts.map(|count| {
        if pairs == 0 {
            0.0
        } else {
            count as f64 / pairs as f64
        }
    })
}

/// AUC@`threshold`: the mean of the cumulative sum of the first `threshold` bins.
pub fn auc(histogram: &[f64; AUC_BINS], threshold: u32) -> f64 {
    let bins = (threshold as usize).clamp(1, AUC_BINS);
    let mut running = 0.0;
    let mut total = 0.0;
    for share in &histogram[..bins] {
        running += share;
        total += running;
    }
    total / bins as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bins_are_thirty_one_of_thirty_over_thirty_one_degree() {
        // 0.96 < 30/31 lies in bin 0, 0.97 > 30/31 in bin 1; 30 in the last bin; 31 nowhere.
        let histogram = normalized_histogram([0.96, 0.97, 30.0, 31.0, f64::NAN].into_iter(), 5);
        assert_eq!(histogram[0], 0.2);
        assert_eq!(histogram[1], 0.2);
        assert_eq!(histogram[30], 0.2);
        assert!((histogram.iter().sum::<f64>() - 0.6).abs() < 1e-12);
        // Cumulative shares 0.2, 0.4, 0.4: AUC@3 = 1.0 / 3.
        assert!((auc(&histogram, 3) - 1.0 / 3.0).abs() < 1e-12);
    }
}
