//! Splitting a manifest's sequences across ranks so no two ranks read the same sequence in an
//! epoch, balanced by frame count and reshuffled every epoch.

use crate::rng::Stream;

/// Tag of the shuffling streams.
const SHARD_STREAM: u64 = 0x0053_4841_5244;

/// Assigns each sequence (by index into `frame_counts`) to one of `world_size` ranks for
/// `epoch`: sequences are shuffled from `(seed, epoch)`, then each goes to the rank holding the
/// fewest frames so far (ties to the lowest rank). Every rank computes the same answer.
pub fn shard_sequences(
    frame_counts: &[usize],
    world_size: usize,
    seed: u64,
    epoch: u64,
) -> Vec<Vec<usize>> {
    let world_size = world_size.max(1);
    let mut order: Vec<usize> = (0..frame_counts.len()).collect();
    let mut stream = Stream::new(&[seed, SHARD_STREAM, epoch]);
    for i in (1..order.len()).rev() {
        order.swap(i, stream.below(i as u64 + 1) as usize);
    }
    let mut shards = vec![Vec::new(); world_size];
    let mut load = vec![0usize; world_size];
    for sequence in order {
        let rank = (0..world_size).min_by_key(|&r| (load[r], r)).unwrap_or(0);
        load[rank] += frame_counts[sequence];
        shards[rank].push(sequence);
    }
    shards
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_partition_balance_and_reshuffle() {
        let counts: Vec<usize> = (0..200).map(|i| 10 + (i * 37) % 90).collect();
        let largest = *counts.iter().max().unwrap();
        let shards = shard_sequences(&counts, 3, 7, 0);
        let mut all: Vec<usize> = shards.iter().flatten().copied().collect();
        all.sort_unstable();
        assert_eq!(
            all,
            (0..200).collect::<Vec<_>>(),
            "every sequence exactly once"
        );
        let loads: Vec<usize> = shards
            .iter()
            .map(|s| s.iter().map(|&i| counts[i]).sum())
            .collect();
        let spread = loads.iter().max().unwrap() - loads.iter().min().unwrap();
        assert!(spread <= largest, "{loads:?}");
        assert_eq!(shards, shard_sequences(&counts, 3, 7, 0));
        assert_ne!(shards, shard_sequences(&counts, 3, 7, 1));
        assert_eq!(shard_sequences(&counts, 1, 7, 0)[0].len(), 200);
    }
}
