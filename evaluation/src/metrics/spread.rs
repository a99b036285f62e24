//! How far a figure would move on another draw of the evaluated pairs: the standard deviation
//! of the figure over bootstrap resamples of its independent units (a sequence's frames, a
//! transfer's frame pairs, a held-out sequence's probe pairs). A lead smaller than a few
//! spreads is noise, so reports print figures with their spread and guards set margins above it.

use data::rng::Stream;

/// Bootstrap resamples per figure: enough for the spread's first digit, cheap beside a model.
const ROUNDS: u64 = 200;
/// Stream tag of the resampling draws.
const SPREAD_TAG: u64 = 0x5350_5244;

/// The bootstrap standard deviation of `statistic` over `units` resampled with replacement
/// (`ROUNDS` draws from `seed`); zero for fewer than two units, which have no spread to tell.
pub fn bootstrap_spread<T>(units: &[T], seed: u64, statistic: impl Fn(&[&T]) -> f64) -> f64 {
    if units.len() < 2 {
        return 0.0;
    }
    let values: Vec<f64> = (0..ROUNDS)
        .map(|round| {
            let mut stream = Stream::new(&[seed, SPREAD_TAG, round]);
            let sample: Vec<&T> = (0..units.len())
                .map(|_| &units[stream.below(units.len() as u64) as usize])
                .collect();
            statistic(&sample)
        })
        .collect();
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    let variance = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64;
    variance.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mean(sample: &[&f64]) -> f64 {
        sample.iter().copied().sum::<f64>() / sample.len().max(1) as f64
    }

    #[test]
    fn the_spread_of_a_mean_follows_the_standard_error() {
        // Values 0 and 1 alternating: standard deviation 0.5, so the mean of 100 has a standard
        // error of 0.05.
        let values: Vec<f64> = (0..100).map(|i| f64::from(i % 2)).collect();
        let spread = bootstrap_spread(&values, 3, mean);
        assert!((spread - 0.05).abs() < 0.01, "{spread}");
        assert_eq!(bootstrap_spread(&[2.0, 2.0, 2.0], 1, mean), 0.0);
        assert_eq!(bootstrap_spread(&[4.0], 1, mean), 0.0);
    }
}
