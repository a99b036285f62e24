//! The step history as it happens, in JSON lines under the checkpoint URI:
//! `history/steps-NNNNNN.jsonl`, one record per finished step (loss, learning rate, checksums
//! by rank, step and all-reduce times). Object stores cannot append, so the newest segment is
//! rewritten as it grows and a new one is started every [`SEGMENT_RECORDS`] records; a
//! coordinator that starts over an existing history begins a new segment after the last one.
//! A SIGKILLed coordinator thus loses at most the records of its last tick, not the run's.

use data::store::{DataRoot, StoreError};

use crate::job::StepRecord;

/// Records per segment: a rewrite stays below about 300 KB.
pub const SEGMENT_RECORDS: usize = 1000;

/// Where the history goes.
const PREFIX: &str = "history/steps-";

/// The segment being written and the records that are not in the store yet.
pub struct History {
    root: DataRoot,
    segment: u64,
    lines: Vec<String>,
    /// Whether `lines` holds records the store has not seen.
    unwritten: bool,
}

/// The object of segment `segment`.
pub fn segment_path(segment: u64) -> String {
    format!("{PREFIX}{segment:06}.jsonl")
}

/// The segment number of a history object's path, if it is one.
fn segment_number(path: &str) -> Option<u64> {
    path.strip_prefix(PREFIX)?
        .strip_suffix(".jsonl")?
        .parse::<u64>()
        .ok()
}

impl History {
    /// Continues the history under `root`: the first segment after any already there.
    pub async fn open(root: DataRoot) -> Result<Self, StoreError> {
        let next = root
            .list()
            .await?
            .iter()
            .filter_map(|object| segment_number(&object.path))
            .max()
            .map_or(0, |last| last + 1);
        Ok(Self {
            root,
            segment: next,
            lines: Vec::new(),
            unwritten: false,
        })
    }

    /// Adds `records` and writes what changed: every segment they completed, then the one
    /// still growing. On a failed write every record not yet written stays, in order, and
    /// goes with the next call (none is dropped at a segment's end).
    pub async fn append(&mut self, records: &[StepRecord]) -> Result<(), StoreError> {
        // A StepRecord is plain numbers and maps: serialising it cannot fail.
        self.lines.extend(
            records
                .iter()
                .map(|record| serde_json::to_string(record).unwrap_or_default()),
        );
        self.unwritten |= !records.is_empty();
        while self.lines.len() > SEGMENT_RECORDS {
            self.write(SEGMENT_RECORDS).await?;
            self.lines.drain(..SEGMENT_RECORDS);
            self.segment += 1;
        }
        if self.unwritten {
            self.write(self.lines.len()).await?;
            self.unwritten = false;
        }
        Ok(())
    }

    /// Every record of the history under `root`, segment by segment, oldest first: what a
    /// restarted coordinator's report and curves start from. A line that does not parse (a
    /// segment cut short mid-write) is skipped with a warning.
    pub async fn read_all(root: &DataRoot) -> Result<Vec<StepRecord>, StoreError> {
        let mut segments: Vec<u64> = root
            .list()
            .await?
            .iter()
            .filter_map(|object| segment_number(&object.path))
            .collect();
        segments.sort_unstable();
        let mut records = Vec::new();
        for segment in segments {
            let path = segment_path(segment);
            let bytes = root.read(&path).await?;
            for line in String::from_utf8_lossy(&bytes).lines() {
                match serde_json::from_str::<StepRecord>(line) {
                    Ok(record) => records.push(record),
                    Err(error) => tracing::warn!(%path, %error, "history line skipped"),
                }
            }
        }
        Ok(records)
    }

    /// Writes the first `count` lines as the current segment.
    async fn write(&self, count: usize) -> Result<(), StoreError> {
        let mut text = self.lines[..count].join("\n");
        text.push('\n');
        self.root
            .write(&segment_path(self.segment), text.into_bytes())
            .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use settings::Phase;

    fn records(steps: std::ops::Range<u64>) -> Vec<StepRecord> {
        steps
            .map(|step| StepRecord::new(Phase::Stage1, step, 1))
            .collect()
    }

    async fn lines(root: &DataRoot, segment: u64) -> Vec<serde_json::Value> {
        let bytes = root.read(&segment_path(segment)).await.unwrap();
        String::from_utf8(bytes)
            .unwrap()
            .lines()
            .map(|line| serde_json::from_str(line).unwrap())
            .collect()
    }

    #[tokio::test]
    async fn segments_fill_in_order_and_a_restart_starts_the_next() {
        let root = DataRoot::in_memory("history");
        let mut history = History::open(root.clone()).await.unwrap();
        history.append(&records(0..3)).await.unwrap();
        assert_eq!(lines(&root, 0).await.len(), 3);
        let total = SEGMENT_RECORDS as u64 + 7;
        history.append(&records(3..total)).await.unwrap();
        let first = lines(&root, 0).await;
        assert_eq!(first.len(), SEGMENT_RECORDS);
        assert_eq!(first[5]["step"], 5);
        let second = lines(&root, 1).await;
        assert_eq!(second.len(), 7);
        assert_eq!(second[0]["step"], SEGMENT_RECORDS as u64);

        let mut restarted = History::open(root.clone()).await.unwrap();
        restarted.append(&records(0..1)).await.unwrap();
        assert_eq!(lines(&root, 2).await.len(), 1);
        assert_eq!(lines(&root, 1).await.len(), 7, "earlier segments stay");

        let mut cut = String::from_utf8(root.read(&segment_path(2)).await.unwrap()).unwrap();
        cut.push_str("{\"stage\": 1, \"st");
        root.write(&segment_path(2), cut.into_bytes())
            .await
            .unwrap();
        let all = History::read_all(&root).await.unwrap();
        let steps: Vec<u64> = all.iter().map(|r| r.step).collect();
        let expected: Vec<u64> = (0..total).chain(0..1).collect();
        assert_eq!(
            steps, expected,
            "every segment in order, the cut line skipped"
        );
    }
}
