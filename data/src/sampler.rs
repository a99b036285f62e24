//! Which frames of which sequence a training sample uses: the per-dataset window sampler with
//! its curriculum, the mixture over datasets, stage 2's long-baseline weighting, and an optional
//! reference band (off in both stages: the release's config defines one but never passes it to
//! its sampler).

use settings::data::{DatasetKind, DatasetSampling, SamplerConfig};

use crate::rng::Stream;

/// The sampler's draws from its settings (the settings live in `settings`, where the
/// coordinator resolves them without linking this crate's I/O).
pub trait WindowSampler {
    /// Draws a dataset with probability proportional to its weight, among `available` ones.
    fn choose_dataset(&self, available: &[DatasetKind], stream: &mut Stream)
    -> Option<DatasetKind>;
    /// The largest window length of `dataset` at `step` (linear ramp, then constant), truncated
    /// to a whole length as the release's `int(...)` does.
    fn max_window(&self, dataset: &DatasetSampling, step: u64) -> usize;
    /// Draws the frames of one sample from a sequence of `length` frames of `dataset` at `step`.
    /// Returns `None` when the sequence is shorter than `frames`.
    fn draw_window(
        &self,
        dataset: &DatasetSampling,
        length: usize,
        step: u64,
        stream: &mut Stream,
    ) -> Option<WindowDraw>;
}

impl WindowSampler for SamplerConfig {
    fn choose_dataset(
        &self,
        available: &[DatasetKind],
        stream: &mut Stream,
    ) -> Option<DatasetKind> {
        let candidates: Vec<&DatasetSampling> = self
            .datasets
            .iter()
            .filter(|d| d.weight > 0.0 && available.contains(&d.dataset))
            .collect();
        let total: f64 = candidates.iter().map(|d| d.weight).sum();
        let mut pick = stream.uniform() * total;
        for candidate in &candidates {
            if pick < candidate.weight {
                return Some(candidate.dataset);
            }
            pick -= candidate.weight;
        }
        candidates.last().map(|d| d.dataset)
    }

    fn max_window(&self, dataset: &DatasetSampling, step: u64) -> usize {
        let progress = if self.curriculum_steps == 0 {
            1.0
        } else {
            (step as f64 / self.curriculum_steps as f64).min(1.0)
        };
        let begin = dataset.window_begin as f64;
        let end = dataset.window_end as f64;
        (begin + (end - begin) * progress) as usize
    }

    fn draw_window(
        &self,
        dataset: &DatasetSampling,
        length: usize,
        step: u64,
        stream: &mut Stream,
    ) -> Option<WindowDraw> {
        let n = self.frames.max(2);
        if length < n {
            return None;
        }
        let largest = self.max_window(dataset, step).clamp(n, length);
        let window = if self.long_baseline {
            weighted_length(n, largest, stream)
        } else {
            n + stream.below((largest - n + 1) as u64) as usize
        };
        let start = stream.below((length - window + 1) as u64) as usize;
        let last = start + window - 1;
        let mut frames = vec![start, last];
        let interior: Vec<usize> = (start + 1..last).collect();
        let mut chosen: Vec<usize> = Vec::new();
        if let Some(band) = self.reference_band.filter(|_| n > 2) {
            let reach = band * window as f64 / 2.0;
            let central: Vec<usize> = interior
                .iter()
                .copied()
                .filter(|&f| ((f - start).max(last - f) as f64) <= reach)
                .collect();
            if !central.is_empty() {
                chosen.push(central[stream.below(central.len() as u64) as usize]);
            }
        }
        let mut remaining: Vec<usize> = interior
            .into_iter()
            .filter(|f| !chosen.contains(f))
            .collect();
        while chosen.len() < n - 2 {
            let pick = stream.below(remaining.len() as u64) as usize;
            chosen.push(remaining.swap_remove(pick));
        }
        frames.extend(chosen);
        frames.sort_unstable();
        if stream.bernoulli(self.reverse_probability) {
            frames.reverse();
        }
        Some(WindowDraw { window, frames })
    }
}

/// The frames drawn for one sample.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WindowDraw {
    /// Window length (frames spanned, ends included).
    pub window: usize,
    /// Frame indices in sample order (increasing, or decreasing when reversed).
    pub frames: Vec<usize>,
}

/// Stage 2's long-baseline weight of position `u` in `[0, 1]` along the allowed lengths.
pub fn long_baseline_weight(u: f64) -> f64 {
    0.8 * (-((u - 0.7) / 0.25).powi(2)).exp() + 0.2
}

fn weighted_length(shortest: usize, longest: usize, stream: &mut Stream) -> usize {
    if longest <= shortest {
        return shortest;
    }
    let span = (longest - shortest) as f64;
    let weights: Vec<f64> = (shortest..=longest)
        .map(|l| long_baseline_weight((l - shortest) as f64 / span))
        .collect();
    let total: f64 = weights.iter().sum();
    let mut pick = stream.uniform() * total;
    for (offset, weight) in weights.iter().enumerate() {
        if pick < *weight {
            return shortest + offset;
        }
        pick -= weight;
    }
    longest
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage1_windows_respect_bounds_and_the_curriculum() {
        let config = SamplerConfig::stage1();
        let re10k = config.dataset(DatasetKind::Re10k).unwrap();
        assert_eq!(config.max_window(re10k, 0), 40);
        assert_eq!(config.max_window(re10k, 25_000), 70);
        assert_eq!(config.max_window(re10k, 50_000), 100);
        assert_eq!(config.max_window(re10k, 200_000), 100);
        let mut reversed = 0;
        let draws = 10_000u64;
        let mut longest_seen = 0;
        for sample in 0..draws {
            let mut stream = Stream::new(&[1, sample]);
            let draw = config.draw_window(re10k, 300, 25_000, &mut stream).unwrap();
            assert!((2..=70).contains(&draw.window));
            assert_eq!(draw.frames.len(), 2);
            assert_eq!(draw.frames[0].abs_diff(draw.frames[1]) + 1, draw.window);
            assert!(draw.frames.iter().all(|&f| f < 300));
            reversed += usize::from(draw.frames[0] > draw.frames[1]);
            longest_seen = longest_seen.max(draw.window);
        }
        assert_eq!(longest_seen, 70);
        assert!((reversed as f64 / draws as f64 - 0.5).abs() < 0.02);
        let short = config
            .draw_window(re10k, 30, 50_000, &mut Stream::new(&[2]))
            .unwrap();
        assert!(short.window <= 30);
        assert!(
            config
                .draw_window(re10k, 1, 0, &mut Stream::new(&[2]))
                .is_none()
        );
    }

    #[test]
    fn mixture_frequencies_follow_the_weights() {
        let config = SamplerConfig::stage2();
        let draws = 40_000u64;
        let mut counts = std::collections::HashMap::new();
        for sample in 0..draws {
            let chosen = config
                .choose_dataset(&DatasetKind::ALL, &mut Stream::new(&[3, sample]))
                .unwrap();
            *counts.entry(chosen).or_insert(0usize) += 1;
        }
        for (dataset, expected) in [
            (DatasetKind::Co3dv2, 2.0 / 12.0),
            (DatasetKind::Dl3dv, 5.0 / 12.0),
            (DatasetKind::Re10k, 3.0 / 12.0),
            (DatasetKind::Mvimgnet, 2.0 / 12.0),
        ] {
            let share = counts[&dataset] as f64 / draws as f64;
            assert!((share - expected).abs() < 0.01, "{dataset:?}: {share}");
        }
        let only = config
            .choose_dataset(&[DatasetKind::Re10k], &mut Stream::new(&[0]))
            .unwrap();
        assert_eq!(only, DatasetKind::Re10k);
    }

    #[test]
    fn the_curriculum_ramp_truncates() {
        let config = SamplerConfig::stage1();
        let co3d = config.dataset(DatasetKind::Co3dv2).unwrap();
        // 9 + 11 * 0.3 = 12.3 -> 12; 9 + 11 * 0.5 = 14.5 -> 14 (rounding would give 15).
        assert_eq!(config.max_window(co3d, 15_000), 12);
        assert_eq!(config.max_window(co3d, 25_000), 14);
    }

    /// Whether the most central interior frame of a stage-2 draw lies within
    /// `1.25 * window / 2` of both ends (what a reference band would enforce).
    fn central_reference(draw: &WindowDraw) -> bool {
        let mut sorted = draw.frames.clone();
        sorted.sort_unstable();
        let (first, last) = (sorted[0], sorted[sorted.len() - 1]);
        let best = sorted[1..sorted.len() - 1]
            .iter()
            .map(|&f| (f - first).max(last - f))
            .min()
            .unwrap_or(0);
        best as f64 <= 1.25 * draw.window as f64 / 2.0
    }

    #[test]
    fn stage2_favours_long_windows_with_uniform_interior_frames() {
        let config = SamplerConfig::stage2();
        assert_eq!(config.reference_band, None);
        let dl3dv = config.dataset(DatasetKind::Dl3dv).unwrap();
        let (mut long, mut short, mut off_band) = (0, 0, 0);
        let draws = 20_000u64;
        for sample in 0..draws {
            let draw = config
                .draw_window(dl3dv, 100, 60_000, &mut Stream::new(&[4, sample]))
                .unwrap();
            assert_eq!(draw.frames.len(), 6);
            let mut sorted = draw.frames.clone();
            sorted.sort_unstable();
            sorted.dedup();
            assert_eq!(sorted.len(), 6, "distinct frames");
            assert_eq!(sorted[5] - sorted[0] + 1, draw.window);
            off_band += usize::from(!central_reference(&draw));
            // Allowed lengths 6..=20: u = 0.7 is length 15.8, u = 0 is length 6.
            long += usize::from(draw.window == 16);
            short += usize::from(draw.window == 6);
        }
        let ratio = long as f64 / short as f64;
        let expected = long_baseline_weight(10.0 / 14.0) / long_baseline_weight(0.0);
        assert!(
            (ratio - expected).abs() < 0.25 * expected,
            "{ratio} vs {expected}"
        );
        // Without a band, four uniform interior frames all miss the central zone now and then.
        assert!(off_band > draws as usize / 200, "{off_band} of {draws}");

        // With the band switched on, every draw keeps a central reference.
        let banded = SamplerConfig {
            reference_band: Some(1.25),
            ..SamplerConfig::stage2()
        };
        for sample in 0..2_000u64 {
            let draw = banded
                .draw_window(dl3dv, 100, 60_000, &mut Stream::new(&[4, sample]))
                .unwrap();
            assert!(central_reference(&draw), "{draw:?}");
        }
    }
}
