//! Where a job is: the two training stages, the evaluation, the end.

use serde::{Deserialize, Deserializer, Serialize};

/// A job's phase, in the order it goes through them. Stage 1 and stage 2 train; the evaluation
/// runs only when the job has an `evaluate` section.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Stereo-monocular transferability training.
    Stage1,
    /// Multi-view fine-tune from stage 1's final weights.
    Stage2,
    /// One worker evaluates the final weights of the trained stages.
    Evaluate,
    /// Nothing left to do.
    Finished,
}

impl Phase {
    /// The training stage's number (1 or 2), as logs, paths and reports name it.
    pub fn stage_number(self) -> Option<u32> {
        match self {
            Self::Stage1 => Some(1),
            Self::Stage2 => Some(2),
            Self::Evaluate | Self::Finished => None,
        }
    }

    /// The phase's number as reports, `job.json` and commit manifests write it: 1 and 2 are the
    /// training stages, 3 the evaluation, 4 the end.
    pub fn number(self) -> u32 {
        match self {
            Self::Stage1 => 1,
            Self::Stage2 => 2,
            Self::Evaluate => 3,
            Self::Finished => 4,
        }
    }

    /// Whether this phase trains.
    pub fn is_training(self) -> bool {
        self.stage_number().is_some()
    }

    /// Short name for logs and the status line.
    pub fn name(self) -> &'static str {
        match self {
            Self::Stage1 => "stage1",
            Self::Stage2 => "stage2",
            Self::Evaluate => "evaluate",
            Self::Finished => "finished",
        }
    }
}

impl std::fmt::Display for Phase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Reads the name, or the number job states written before phases had names used (1 and 2
/// train, 3 evaluates, anything later is finished), so an older `job.json` still resumes.
impl<'de> Deserialize<'de> for Phase {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Written {
            Number(u32),
            Name(String),
        }
        match Written::deserialize(deserializer)? {
            Written::Number(0) => Err(serde::de::Error::custom("phase 0 does not exist")),
            Written::Number(1) => Ok(Self::Stage1),
            Written::Number(2) => Ok(Self::Stage2),
            Written::Number(3) => Ok(Self::Evaluate),
            Written::Number(_) => Ok(Self::Finished),
            Written::Name(name) => [Self::Stage1, Self::Stage2, Self::Evaluate, Self::Finished]
                .into_iter()
                .find(|phase| phase.name() == name)
                .ok_or_else(|| {
                    serde::de::Error::custom(format!(
                        "unknown phase `{name}`: expected stage1, stage2, evaluate or finished"
                    ))
                }),
        }
    }
}

/// `#[serde(with = "settings::phase::as_number")]`: a phase written as its [`Phase::number`],
/// so reports and job states keep the numeric `stage` field their readers know.
pub mod as_number {
    use serde::{Deserialize, Deserializer, Serializer};

    use super::Phase;

    /// Writes the number.
    pub fn serialize<S: Serializer>(phase: &Phase, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_u32(phase.number())
    }

    /// Reads a number or a name.
    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Phase, D::Error> {
        Phase::deserialize(deserializer)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phases_read_their_names_and_the_old_stage_numbers() {
        for phase in [
            Phase::Stage1,
            Phase::Stage2,
            Phase::Evaluate,
            Phase::Finished,
        ] {
            let json = serde_json::to_string(&phase).unwrap();
            assert_eq!(serde_json::from_str::<Phase>(&json).unwrap(), phase);
        }
        assert_eq!(serde_json::from_str::<Phase>("2").unwrap(), Phase::Stage2);
        assert_eq!(serde_json::from_str::<Phase>("4").unwrap(), Phase::Finished);
        assert!(serde_json::from_str::<Phase>("\"stage3\"").is_err());
        assert!(Phase::Stage1 < Phase::Evaluate);
        assert_eq!(Phase::Stage2.stage_number(), Some(2));
        assert!(!Phase::Evaluate.is_training());
    }
}
