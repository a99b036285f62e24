//! How far a figure would move on another draw of the evaluated pairs: the standard deviation
//! of the figure over bootstrap resamples of its independent units (a sequence's frames, a
//! transfer's frame pairs, a held-out sequence's probe pairs). A lead smaller than a few
//! spreads is noise, so reports print figures with their spread and guards set margins above it.

use data::rng::Stream;
use serde::{Deserialize, Serialize};

use super::camera::{CameraMetrics, PairError};

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

/// Spreads of the headline camera figures.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraSpread {
    /// Spread of `SE3_Auc@20`.
    pub auc20: f64,
    /// Spread of `SE3_Auc@30`.
    pub auc30: f64,
}

/// The spreads of `SE3_Auc@20` and `@30` over `groups`, each group the pair errors of one
/// independent unit (a transfer, a held-out sequence).
pub fn camera_spread(groups: &[Vec<PairError>], seed: u64) -> CameraSpread {
    let auc = |threshold: u32| {
        bootstrap_spread(groups, seed, move |sample| {
            let errors: Vec<PairError> = sample.iter().flat_map(|g| g.iter().copied()).collect();
            CameraMetrics::from_errors(&errors)
                .at(threshold)
                .map_or(0.0, |s| s.auc)
        })
    };
    CameraSpread {
        auc20: auc(20),
        auc30: auc(30),
    }
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

    #[test]
    fn camera_spread_is_zero_for_agreeing_units_and_not_for_mixed_ones() {
        let exact = PairError {
            rotation: 0.0,
            translation: 0.0,
        };
        let wrong = PairError {
            rotation: 180.0,
            translation: 90.0,
        };
        let same = vec![vec![exact; 4]; 6];
        assert_eq!(camera_spread(&same, 0), CameraSpread::default());
        let mixed: Vec<Vec<PairError>> = (0..6)
            .map(|i| vec![if i % 2 == 0 { exact } else { wrong }; 4])
            .collect();
        let spread = camera_spread(&mixed, 0);
        assert!(spread.auc30 > 0.05 && spread.auc30 < 0.4, "{spread:?}");
    }
}
