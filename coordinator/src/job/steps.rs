//! The coordinator's step bookkeeping, in memory that does not grow with the run.
//!
//! Every step report finds its record through an index by `(phase, step, generation)`, so a
//! report costs the same at step 10 and at step 300000. Records are handed to the history
//! writer once sealed (see [`StepLog::take_sealed`]) and then only the newest
//! [`RETAINED_RECORDS`] stay in memory, for the report; the whole history is in the store.
//! The loss curves keep at most [`CURVE_POINTS`] rows per phase, evenly spaced: the plot needs
//! no more, and the history in the store has every step.

use std::collections::{BTreeMap, HashMap};

use settings::Phase;

use super::StepRecord;

/// Sealed records kept in memory for the job report (`report.json`'s `steps`).
pub const RETAINED_RECORDS: usize = 2000;

/// Most rows a phase's loss curve keeps in memory; past it, every other row is dropped and the
/// spacing doubles.
pub const CURVE_POINTS: usize = 4096;

/// One row of a stage's curves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurveRow {
    /// Loss of the global batch.
    pub loss: f32,
    /// Its L1 term.
    pub l1: f32,
    /// Its LPIPS term before the weight, where the stage has one.
    pub lpips: Option<f32>,
    /// Learning rate.
    pub learning_rate: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
}

impl CurveRow {
    fn of(record: &StepRecord) -> Self {
        Self {
            loss: record.loss,
            l1: record.l1,
            lpips: record.lpips,
            learning_rate: record.learning_rate,
            grad_norm: record.grad_norm,
        }
    }
}

/// A loss curve thinned to at most [`CURVE_POINTS`] rows: the steps that are multiples of
/// `stride`.
#[derive(Debug, Clone)]
struct ThinnedCurve {
    rows: BTreeMap<u64, CurveRow>,
    stride: u64,
}

impl Default for ThinnedCurve {
    fn default() -> Self {
        Self {
            rows: BTreeMap::new(),
            stride: 1,
        }
    }
}

impl ThinnedCurve {
    /// Keeps `row` when `step` falls on the spacing (a re-run step replaces its row).
    fn insert(&mut self, step: u64, row: CurveRow) {
        if !step.is_multiple_of(self.stride) {
            return;
        }
        self.rows.insert(step, row);
        if self.rows.len() > CURVE_POINTS {
            self.stride *= 2;
            let stride = self.stride;
            self.rows.retain(|step, _| step.is_multiple_of(stride));
        }
    }
}

/// The index key of a record.
fn key(record: &StepRecord) -> (Phase, u64, u64) {
    (record.phase, record.step, record.generation)
}

/// Step records by `(phase, step, generation)`, the newest in memory, the rest in the store.
#[derive(Debug, Default)]
pub struct StepLog {
    /// The records in memory, oldest first.
    records: Vec<StepRecord>,
    /// Position in `records` of each `(phase, step, generation)`.
    index: HashMap<(Phase, u64, u64), usize>,
    /// Records before this position went to the history writer.
    sealed: usize,
    /// Loss and learning rate of sealed steps, thinned, by phase.
    curves: HashMap<Phase, ThinnedCurve>,
}

impl StepLog {
    /// The record of `step` of `phase` in `generation`, created on its first report.
    pub fn record(&mut self, phase: Phase, step: u64, generation: u64) -> &mut StepRecord {
        let records = &mut self.records;
        let position = *self
            .index
            .entry((phase, step, generation))
            .or_insert_with(|| {
                records.push(StepRecord::new(phase, step, generation));
                records.len() - 1
            });
        &mut self.records[position]
    }

    /// The record of `step` of `phase` in `generation`, if it is still in memory.
    pub fn get(&self, phase: Phase, step: u64, generation: u64) -> Option<&StepRecord> {
        let position = self.index.get(&(phase, step, generation))?;
        self.records.get(*position)
    }

    /// Records not handed out yet, oldest first: every one but the newest two, which may still
    /// gain other ranks' reports (a rank finishes step `s + 1` only after every rank finished
    /// `s`, in the all-reduce, but a report can be late by a step), or all of them once the
    /// job is over (`all`). Older records then leave memory, the newest
    /// [`RETAINED_RECORDS`] excepted.
    pub fn take_sealed(&mut self, all: bool) -> Vec<StepRecord> {
        let end = if all {
            self.records.len()
        } else {
            self.records.len().saturating_sub(2)
        };
        self.take_until(end)
    }

    /// Records not handed out yet up to and including that of `step` of `phase` in
    /// `generation` (none when it is not in memory): a commit's step and every one before it,
    /// which must be in the history before the commit is (every rank has reported the
    /// committed step: its checksums verified it).
    pub fn take_through(&mut self, phase: Phase, step: u64, generation: u64) -> Vec<StepRecord> {
        match self.index.get(&(phase, step, generation)) {
            Some(&position) => self.take_until(position + 1),
            None => Vec::new(),
        }
    }

    /// Hands out the records from the last handed out to `end` (exclusive).
    fn take_until(&mut self, end: usize) -> Vec<StepRecord> {
        let taken = self
            .records
            .get(self.sealed..end)
            .map(<[StepRecord]>::to_vec)
            .unwrap_or_default();
        for record in &taken {
            self.curves
                .entry(record.phase)
                .or_default()
                .insert(record.step, CurveRow::of(record));
        }
        self.sealed = self.sealed.max(end);
        // Dropped in batches, so re-indexing costs O(1) per step on average.
        if self.sealed >= 2 * RETAINED_RECORDS {
            self.forget(self.sealed - RETAINED_RECORDS);
        }
        taken
    }

    /// Takes back `records` read from the store's history (a restarted coordinator's
    /// predecessor's steps, oldest first) as if this log had sealed them: they join the curves
    /// and the report's retained records, and are not handed to the history writer again.
    /// Steps reported to this coordinator before the history was read back stay unsealed
    /// after them (they go to the history writer as any other), and win over a restored
    /// record of the same step and generation.
    pub fn restore(&mut self, records: Vec<StepRecord>) {
        let pending: Vec<StepRecord> = self.records.drain(self.sealed..).collect();
        for record in &pending {
            self.index.remove(&key(record));
        }
        let reported: std::collections::HashSet<_> = pending.iter().map(key).collect();
        for record in records.into_iter().filter(|r| !reported.contains(&key(r))) {
            match self.index.get(&key(&record)) {
                Some(&position) => self.records[position] = record,
                None => {
                    self.index.insert(key(&record), self.records.len());
                    self.records.push(record);
                }
            }
        }
        self.take_sealed(true);
        for record in pending {
            self.index.insert(key(&record), self.records.len());
            self.records.push(record);
        }
    }

    /// Drops the oldest `count` records from memory.
    fn forget(&mut self, count: usize) {
        self.records.drain(..count);
        self.sealed -= count;
        self.index.retain(|_, position| *position >= count);
        for position in self.index.values_mut() {
            *position -= count;
        }
    }

    /// The records in memory, oldest first.
    pub fn retained(&self) -> &[StepRecord] {
        &self.records
    }

    /// Loss and learning rate of `phase`'s steps by step number: the sealed steps on the
    /// curve's spacing (every step until [`CURVE_POINTS`]), and the records not sealed yet.
    pub fn curve(&self, phase: Phase) -> BTreeMap<u64, CurveRow> {
        let mut rows = self
            .curves
            .get(&phase)
            .map(|curve| curve.rows.clone())
            .unwrap_or_default();
        for record in self.records[self.sealed..]
            .iter()
            .filter(|r| r.phase == phase)
        {
            rows.insert(record.step, CurveRow::of(record));
        }
        rows
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_stays_bounded_while_every_record_is_handed_out_once() {
        let mut log = StepLog::default();
        let mut handed = Vec::new();
        let steps = 5 * RETAINED_RECORDS as u64 + 17;
        for step in 0..steps {
            log.record(Phase::Stage1, step, 1).loss = step as f32;
            // A second rank's report of the same step finds the same record.
            log.record(Phase::Stage1, step, 1).checksums.insert(1, 7);
            handed.extend(log.take_sealed(false).into_iter().map(|r| r.step));
            assert!(
                log.retained().len() < 2 * RETAINED_RECORDS + 2,
                "step {step}"
            );
            assert!(log.index.len() == log.records.len());
        }
        handed.extend(log.take_sealed(true).into_iter().map(|r| r.step));
        assert_eq!(handed, (0..steps).collect::<Vec<_>>());
        let curve = log.curve(Phase::Stage1);
        assert!(curve.len() <= CURVE_POINTS + 2, "{}", curve.len());
        assert_eq!(curve[&(steps - 1)].loss, (steps - 1) as f32);
        let last = log.retained().last().unwrap();
        assert_eq!((last.step, last.checksums.len()), (steps - 1, 1));
    }

    #[test]
    fn a_commits_step_and_every_one_before_it_are_handed_out_at_once_and_only_once() {
        let mut log = StepLog::default();
        for step in 0..10 {
            log.record(Phase::Stage1, step, 1).loss = step as f32;
        }
        let through: Vec<u64> = log
            .take_through(Phase::Stage1, 9, 1)
            .iter()
            .map(|r| r.step)
            .collect();
        assert_eq!(
            through,
            (0..10).collect::<Vec<_>>(),
            "the newest two are not held back"
        );
        assert!(
            log.take_sealed(true).is_empty(),
            "nothing is handed out twice"
        );
        assert!(
            log.take_through(Phase::Stage1, 3, 2).is_empty(),
            "another generation's step is not in memory"
        );
        log.record(Phase::Stage1, 10, 1);
        let rest: Vec<u64> = log.take_sealed(true).iter().map(|r| r.step).collect();
        assert_eq!(rest, [10]);
    }

    #[test]
    fn steps_reported_before_the_history_is_read_back_are_still_written() {
        let mut log = StepLog::default();
        log.record(Phase::Stage1, 5, 2).loss = 0.5;
        log.record(Phase::Stage1, 6, 2).loss = 0.6;
        let earlier: Vec<StepRecord> = (0..5)
            .map(|step| {
                let mut record = StepRecord::new(Phase::Stage1, step, 1);
                record.loss = step as f32;
                record
            })
            .collect();
        log.restore(earlier);
        let written: Vec<u64> = log.take_sealed(true).iter().map(|r| r.step).collect();
        assert_eq!(
            written,
            [5, 6],
            "the window's steps go to the history writer"
        );
        let curve = log.curve(Phase::Stage1);
        assert_eq!(
            curve.keys().copied().collect::<Vec<_>>(),
            [0, 1, 2, 3, 4, 5, 6]
        );
        assert_eq!(curve[&5].loss, 0.5);
        assert_eq!(log.retained().len(), 7);
        assert_eq!(log.index.len(), log.records.len());
    }

    /// A row whose loss is the step number.
    fn row(step: u64) -> CurveRow {
        CurveRow {
            loss: step as f32,
            l1: 0.0,
            lpips: None,
            learning_rate: 0.0,
            grad_norm: 0.0,
        }
    }

    #[test]
    fn a_curve_keeps_every_step_until_full_then_thins_evenly() {
        let mut curve = ThinnedCurve::default();
        for step in 0..CURVE_POINTS as u64 {
            curve.insert(step, row(step));
        }
        assert_eq!((curve.rows.len(), curve.stride), (CURVE_POINTS, 1));
        let steps = 10 * CURVE_POINTS as u64;
        for step in CURVE_POINTS as u64..steps {
            curve.insert(step, row(step));
        }
        // 40960 steps: spacing 16 leaves 2560 rows, the first and every 16th step.
        assert_eq!(curve.stride, 16);
        assert_eq!(curve.rows.len() as u64, steps / 16);
        assert!(
            curve
                .rows
                .iter()
                .all(|(&step, row)| step % 16 == 0 && row.loss == step as f32)
        );
    }

    #[test]
    fn restored_history_joins_the_report_and_curves_and_is_not_written_again() {
        let mut before = StepLog::default();
        for step in 0..10 {
            before.record(Phase::Stage1, step, 1).loss = step as f32;
        }
        let history = before.take_sealed(true);
        let mut after = StepLog::default();
        after.restore(history.clone());
        assert_eq!(after.retained(), &history[..]);
        assert!(after.take_sealed(true).is_empty(), "already in the store");
        after.record(Phase::Stage1, 8, 2).loss = 80.0;
        let curve = after.curve(Phase::Stage1);
        assert_eq!(
            curve.keys().copied().collect::<Vec<_>>(),
            (0..10).collect::<Vec<_>>()
        );
        assert_eq!(curve[&8].loss, 80.0, "the re-run step replaces its row");
        let written: Vec<u64> = after.take_sealed(true).iter().map(|r| r.step).collect();
        assert_eq!(written, [8]);
    }
}
