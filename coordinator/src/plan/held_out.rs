//! Evaluation data no training step reads: the plan refuses a job whose evaluation would score
//! scenes its training data holds, naming them, before any worker starts. A scene is the same
//! when its id is (same dataset kind and sequence id, whatever the root: a copied dataset is the
//! same data), or, for generated scenes, when its generated name is.

use std::collections::BTreeSet;

use data::Split;
use data::index::index as index_tree;
use data::store::DataRoot;
use data::synthetic::{scene_name, scene_of_sequence_id};
use settings::evaluation::EvaluationSpec;

use super::PlanError;
use super::datasets::TrainManifest;
use crate::config::{ClusterConfig, DataConfig};

/// Scenes named in an overlap error, at most.
const NAMED: usize = 5;

/// Checks that the evaluation of `config` (its generated held-out scenes and each real
/// protocol's test sequences) reads nothing `training` (the indexed train sequences) holds.
pub(super) async fn check_held_out(
    config: &ClusterConfig,
    training: &[TrainManifest],
) -> Result<(), PlanError> {
    let Some(spec) = &config.evaluate else {
        return Ok(());
    };
    let trained_scenes = generated_training_scenes(config, training);
    let evaluated: Vec<String> = (0..spec.scenes)
        .map(|scene| scene_name(spec.seed, Split::Test, scene))
        .filter(|name| trained_scenes.contains(name))
        .collect();
    if let Some(error) = overlap("evaluate (its generated scenes)".to_string(), evaluated) {
        return Err(error);
    }
    for (index, protocol) in spec.sequences.iter().enumerate() {
        let evaluated = protocol_overlap(spec, index, training).await?;
        let what = format!(
            "evaluate.sequences[{index}] ({} at {})",
            protocol.kind.name(),
            protocol.uri
        );
        if let Some(error) = overlap(what, evaluated) {
            return Err(error);
        }
    }
    Ok(())
}

/// The generated scenes the training data holds: the job's own draws for `data: generated`,
/// else every stored sequence whose id names a generated scene.
fn generated_training_scenes(
    config: &ClusterConfig,
    training: &[TrainManifest],
) -> BTreeSet<String> {
    match &config.data {
        DataConfig::Generated(generated) => (0..generated.scenes.0)
            .map(|scene| scene_name(config.seed, Split::Train, scene))
            .collect(),
        DataConfig::Datasets(_) => training
            .iter()
            .flat_map(|(_, _, manifest)| &manifest.sequences)
            .filter_map(|s| scene_of_sequence_id(&s.id).map(str::to_string))
            .collect(),
    }
}

/// The ids of protocol `index`'s evaluated test sequences that a training dataset of the same
/// kind also trains on.
async fn protocol_overlap(
    spec: &EvaluationSpec,
    index: usize,
    training: &[TrainManifest],
) -> Result<Vec<String>, PlanError> {
    let protocol = &spec.sequences[index];
    let trained: BTreeSet<&str> = training
        .iter()
        .filter(|(kind, _, _)| *kind == protocol.kind)
        .flat_map(|(_, _, manifest)| manifest.sequences.iter().map(|s| s.id.as_str()))
        .collect();
    if trained.is_empty() {
        return Ok(Vec::new());
    }
    let (kind, uri) = (protocol.kind.name(), protocol.uri.clone());
    let root = DataRoot::open(&uri).map_err(|source| PlanError::EvaluationOpen {
        index,
        kind,
        uri: uri.clone(),
        source,
    })?;
    // Indexed without writing a manifest cache: an evaluation dataset may be read-only.
    let indexed =
        index_tree(&root, protocol.kind)
            .await
            .map_err(|source| PlanError::EvaluationIndex {
                index,
                kind,
                uri,
                source,
            })?;
    let (evaluated, _) = indexed
        .manifest
        .evaluated_test_sequences(protocol.length, protocol.count);
    Ok(evaluated
        .into_iter()
        .filter(|s| trained.contains(s.id.as_str()))
        .map(|s| s.id.clone())
        .collect())
}

/// The error naming `what` and the first of `shared` when any scene is shared.
fn overlap(what: String, shared: Vec<String>) -> Option<PlanError> {
    (!shared.is_empty()).then(|| PlanError::EvaluationOverlap {
        what,
        count: shared.len(),
        named: shared
            .into_iter()
            .take(NAMED)
            .collect::<Vec<_>>()
            .join(", "),
    })
}
