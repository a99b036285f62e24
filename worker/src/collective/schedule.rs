//! Where a ring's chunks lie: the same cut of a buffer for both transports (the gRPC stream
//! and the TCP lanes), so every rank agrees on what each chunk holds.
//!
//! The buffer is cut into one segment per rank. Reduce-scatter step `s` (0 .. n-1) has rank
//! `r` receive segment `r - s - 1` and add it into its own values; all-gather step `n - 1 + s`
//! has it receive segment `r - s`, fully reduced, and keep it. Segments travel as chunks of at
//! most `chunk_values` values.

/// The cut of one rank's buffer of `len` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Schedule {
    /// Ranks in the ring.
    pub(super) world: usize,
    /// This rank.
    pub(super) rank: usize,
    /// Values per chunk (at least 1).
    pub(super) chunk_values: usize,
    /// Values in the buffer.
    pub(super) len: usize,
}

/// One chunk the ring delivers to this rank.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Delivery {
    /// Its ring step.
    pub(super) step: usize,
    /// Its segment.
    pub(super) segment: usize,
    /// Its first value.
    pub(super) begin: usize,
    /// One past its last value.
    pub(super) end: usize,
}

impl Schedule {
    /// Ring steps of one all-reduce: `n - 1` reduce-scatter, then `n - 1` all-gather.
    pub(super) fn steps(&self) -> usize {
        2 * (self.world - 1)
    }

    /// Values `begin..end` of segment `index`.
    pub(super) fn segment(&self, index: usize) -> (usize, usize) {
        (
            index * self.len / self.world,
            (index + 1) * self.len / self.world,
        )
    }

    /// The segment this rank receives at `step`.
    pub(super) fn received_segment(&self, step: usize) -> usize {
        let (n, r) = (self.world, self.rank);
        if step < n - 1 {
            (r + n - step - 1) % n
        } else {
            (r + n - (step - (n - 1))) % n
        }
    }

    /// The chunks of values `begin..end`, in order.
    pub(super) fn chunks(
        &self,
        begin: usize,
        end: usize,
    ) -> impl Iterator<Item = (usize, usize)> + use<> {
        let step = self.chunk_values.max(1);
        (begin..end)
            .step_by(step)
            .map(move |start| (start, (start + step).min(end)))
    }

    /// The chunks this rank sends before it has received anything: its own segment's.
    pub(super) fn first_sends(&self) -> impl Iterator<Item = (usize, usize)> + use<> {
        let (begin, end) = self.segment(self.rank);
        self.chunks(begin, end)
    }

    /// Every chunk this rank receives, in the order its left neighbour sends them.
    pub(super) fn deliveries(&self) -> impl Iterator<Item = Delivery> + use<> {
        let schedule = *self;
        (0..self.steps()).flat_map(move |step| {
            let segment = schedule.received_segment(step);
            let (begin, end) = schedule.segment(segment);
            schedule
                .chunks(begin, end)
                .map(move |(begin, end)| Delivery {
                    step,
                    segment,
                    begin,
                    end,
                })
        })
    }

    /// Whether a chunk received at `step` is added (reduce-scatter) rather than kept.
    pub(super) fn adds(&self, step: usize) -> bool {
        step < self.world - 1
    }

    /// Whether this rank owns a chunk once it has received it at `step` (the last
    /// reduce-scatter step: the sum is complete here and travels on from here).
    pub(super) fn completes(&self, step: usize) -> bool {
        step + 2 == self.world
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_phase_delivers_every_segment_but_one_once() {
        let world = 4;
        for rank in 0..world {
            let schedule = Schedule {
                world,
                rank,
                chunk_values: 3,
                len: 23,
            };
            let segments_of = |phase: std::ops::Range<usize>| {
                let mut segments: Vec<usize> =
                    phase.map(|step| schedule.received_segment(step)).collect();
                segments.sort_unstable();
                segments
            };
            let all_but =
                |skipped: usize| -> Vec<usize> { (0..world).filter(|&s| s != skipped).collect() };
            // Reduce-scatter: every segment but the rank's own (which it sends first).
            assert_eq!(segments_of(0..world - 1), all_but(rank), "rank {rank}");
            // All-gather: every segment but the one this rank completed.
            let completed = schedule.received_segment(world - 2);
            assert!(schedule.completes(world - 2));
            assert_eq!(completed, (rank + 1) % world);
            assert_eq!(segments_of(world - 1..2 * world - 2), all_but(completed));
            let delivered: Vec<Delivery> = schedule.deliveries().collect();
            assert!(
                delivered
                    .iter()
                    .all(|d| d.end - d.begin <= 3 && d.begin < d.end)
            );
            let values: usize = delivered.iter().map(|d| d.end - d.begin).sum();
            let (own, done) = (schedule.segment(rank), schedule.segment(completed));
            assert_eq!(values, 2 * 23 - (own.1 - own.0) - (done.1 - done.0));
        }
    }

    #[test]
    fn a_buffer_shorter_than_the_ring_has_empty_segments() {
        let schedule = Schedule {
            world: 4,
            rank: 1,
            chunk_values: 8,
            len: 2,
        };
        let segments: Vec<(usize, usize)> = (0..4).map(|s| schedule.segment(s)).collect();
        assert_eq!(segments, [(0, 0), (0, 1), (1, 1), (1, 2)]);
        assert_eq!(schedule.deliveries().count(), 3);
    }
}
