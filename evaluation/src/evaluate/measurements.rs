//! The measurements `evaluate_model` takes of one model, each with its figures.

use std::path::Path;

use data::Image;
use trainer_core::XFactor;

use super::reconstruction::{Renderer, reconstruct, reconstruction_set};
use super::{Baselines, Context, GRID_PAIRS};
use crate::error::EvalError;
use crate::figures::{save_camera_paths, save_sheet};
use crate::inference::{probe_features, render_along};
use crate::metrics::ReconstructionReport;
use crate::probe::{ProbeReport, ProbeSequence, no_motion, run_probe};
use crate::sequences::SequenceReport;
use crate::tps::{TpsPair, TpsReport, TpsSettings, draw_pairs, target_frames, transferability};

/// The figures written so far, by name relative to the output folder.
pub(super) struct Figures<'a> {
    /// The folder they are written into.
    pub(super) out_dir: &'a Path,
    /// Their names, in the order written.
    pub(super) names: &'a mut Vec<String>,
}

impl Figures<'_> {
    /// Writes figure `name` into the output folder with `write`, then lists it.
    fn save(
        &mut self,
        name: String,
        write: &dyn Fn(&Path) -> Result<(), EvalError>,
    ) -> Result<(), EvalError> {
        write(&self.out_dir.join(&name))?;
        self.names.push(name);
        Ok(())
    }
}

/// Autoencoding of sequences from every generated scene with `context_views` context views,
/// with its render-grid figure.
pub(super) fn generated_reconstruction(
    model: &XFactor,
    context_views: usize,
    context: &Context<'_>,
    prefix: &str,
    figures: &mut Figures<'_>,
) -> Result<ReconstructionReport, EvalError> {
    let (reconstruction, grid) = {
        let _span = tracing::info_span!("reconstruction", model = prefix).entered();
        let generated = reconstruction_set(&context.dataset, context.spec.reconstruction_sequences)
            .into_iter()
            .map(|s| s.frames.as_slice());
        reconstruct(Renderer::Model(model), generated, context_views, context)?
    };
    let sheet = sequence_rows(&grid);
    let columns = frame_columns(&sheet);
    figures.save(format!("{prefix}_reconstruction.png"), &|p| {
        let title = format!("{prefix}: held-out sequences and their renders ({context_views} context view(s) in place)");
        Ok(save_sheet(&title, &columns, &sheet, p)?)
    })?;
    Ok(reconstruction)
}

/// Reconstruction of each protocol's real test sequences, with a render-grid figure each.
pub(super) fn sequence_reconstructions(
    model: &XFactor,
    context: &Context<'_>,
    prefix: &str,
    figures: &mut Figures<'_>,
) -> Result<Vec<SequenceReport>, EvalError> {
    let mut sequences = Vec::new();
    for set in &context.protocol_sets {
        let protocol = &set.protocol;
        let _span =
            tracing::info_span!("sequences", model = prefix, dataset = ?protocol.kind).entered();
        let frames = set.sequences.iter().map(|s| s.frames.as_slice());
        let (reconstruction, grid) = reconstruct(Renderer::Model(model), frames, 1, context)?;
        let sheet = sequence_rows(&grid);
        let columns = frame_columns(&sheet);
        figures.save(
            format!("{prefix}_sequences_{}.png", protocol.kind.name()),
            &|p| {
                let title = format!(
                    "{prefix}: {} test sequences and their renders",
                    protocol.kind.name()
                );
                Ok(save_sheet(&title, &columns, &sheet, p)?)
            },
        )?;
        sequences.push(SequenceReport {
            kind: protocol.kind,
            uri: protocol.uri.clone(),
            length: protocol.length,
            sequences: set.sequences.len(),
            skipped_short: set.skipped_short,
            reconstruction,
        });
    }
    Ok(sequences)
}

/// A reconstruction grid's rows (a sequence's frames, then its renders) named for a sheet.
fn sequence_rows(grid: &[Vec<Image>]) -> Vec<(String, Vec<Image>)> {
    grid.iter()
        .enumerate()
        .map(|(index, row)| {
            let what = if index % 2 == 0 { "frames" } else { "renders" };
            (format!("sequence {}: {what}", index / 2 + 1), row.clone())
        })
        .collect()
}

/// `frame 1`, `frame 2`, ... for the longest row of `rows`.
fn frame_columns(rows: &[(String, Vec<Image>)]) -> Vec<String> {
    let longest = rows.iter().map(|(_, row)| row.len()).max().unwrap_or(0);
    (1..=longest).map(|i| format!("frame {i}")).collect()
}

/// How TPS is drawn for `context_views` context views.
fn tps_settings(context_views: usize, context: &Context<'_>) -> TpsSettings {
    TpsSettings {
        frames_per_pair: context.spec.tps_frames,
        context_views,
        seed: context.spec.seed,
    }
}

/// Transferability over freshly drawn pairs, with the renders and first pair's paths figures.
pub(super) fn evaluate_tps(
    model: &XFactor,
    context_views: usize,
    context: &Context<'_>,
    prefix: &str,
    figures: &mut Figures<'_>,
) -> Result<TpsReport, EvalError> {
    let spec = context.spec;
    let pairs = draw_pairs(spec.seed, spec.scenes, spec.trajectories, spec.tps_pairs)?;
    let mut sheet = Vec::new();
    let tps = {
        let _span =
            tracing::info_span!("tps", model = prefix, oracle = context.oracle.name()).entered();
        transferability(
            &context.dataset,
            &pairs,
            tps_settings(context_views, context),
            context.oracle.as_ref(),
            |frames| {
                let renders =
                    render_along(model, &frames.source, 0, &frames.contexts, &context.device)?;
                let pair = sheet.len() / 4 + 1;
                if pair <= GRID_PAIRS {
                    let row = |what: &str, images: &[Image]| {
                        (format!("pair {pair}: {what}"), images.to_vec())
                    };
                    sheet.push(row("source video", &frames.source));
                    sheet.push(row("target scene's context", &frames.contexts));
                    sheet.push(row("our render", &renders));
                    sheet.push(row("truth along source path", &frames.ideal));
                }
                Ok(renders)
            },
        )?
    };
    let columns = frame_columns(&sheet);
    figures.save(format!("{prefix}_tps_renders.png"), &|p| {
        let title = format!("{prefix}: the source video's camera path rendered in another scene");
        Ok(save_sheet(&title, &columns, &sheet, p)?)
    })?;
    if let Some(pair) = pairs.first() {
        save_tps_paths(model, context_views, context, prefix, pair, figures)?;
    }
    Ok(tps)
}

/// The oracle's camera paths of `pair`'s source video and of its transfer; where the oracle
/// cannot read the renders, the source's path alone, the title saying why.
fn save_tps_paths(
    model: &XFactor,
    context_views: usize,
    context: &Context<'_>,
    prefix: &str,
    pair: &TpsPair,
    figures: &mut Figures<'_>,
) -> Result<(), EvalError> {
    let spec = context.spec;
    let indices = target_frames(spec.frames, spec.tps_frames);
    let frames = crate::tps::pair_frames(&context.dataset, pair, &indices, context_views)?;
    let renders = render_along(model, &frames.source, 0, &frames.contexts, &context.device)?;
    let oracle = context.oracle.as_ref();
    let Ok(reference) = oracle.estimate(&frames.source) else {
        return Ok(());
    };
    let (title, rendered) = match oracle.estimate(&renders) {
        Ok(rendered) => (format!("{prefix}: transferred camera path"), rendered),
        Err(error) => (
            format!(
                "{prefix}: transferred camera path (the oracle could not read the renders: {error})"
            ),
            Vec::new(),
        ),
    };
    figures.save(format!("{prefix}_tps_paths.png"), &|p| {
        let mut paths = vec![("source video (oracle poses)", &reference[..])];
        if !rendered.is_empty() {
            paths.push(("renders (oracle poses)", &rendered[..]));
        }
        Ok(save_camera_paths(&title, &paths, p)?)
    })
}

/// The pose probe trained on the first of the evaluation's held-out scenes (none of which the
/// model trained on) and scored on the rest, with its path figure.
pub(super) fn evaluate_probe(
    model: &XFactor,
    context: &Context<'_>,
    prefix: &str,
    figures: &mut Figures<'_>,
) -> Result<ProbeReport, EvalError> {
    let spec = context.spec;
    let (probe, paths) = {
        let _span = tracing::info_span!("probe", model = prefix).entered();
        let (train, test) = probe_sequences(model, context)?;
        run_probe(
            &train,
            &test,
            &spec.probe,
            spec.seed,
            &context.device.clone().autodiff(),
        )?
    };
    if let Some((reference, predicted)) = paths.first() {
        figures.save(format!("{prefix}_probe_paths.png"), &|p| {
            Ok(save_camera_paths(
                &format!("{prefix}: pose probe, held-out path"),
                &[
                    ("ground truth", &reference[..]),
                    ("probe prediction", &predicted[..]),
                ],
                p,
            )?)
        })?;
    }
    Ok(probe)
}

/// The first scene the probe is tested on: the last `probe.test_scenes` are held out of its
/// training.
fn first_probe_test_scene(context: &Context<'_>) -> u64 {
    context
        .spec
        .scenes
        .saturating_sub(context.spec.probe.test_scenes)
}

/// PoseEnc's probe features of every generated sequence, split into the probe's training and
/// test sequences.
fn probe_sequences(
    model: &XFactor,
    context: &Context<'_>,
) -> Result<(Vec<ProbeSequence>, Vec<ProbeSequence>), EvalError> {
    let first_test_scene = first_probe_test_scene(context);
    let (mut train, mut test) = (Vec::new(), Vec::new());
    for sequence in &context.dataset.sequences {
        let latents = probe_features(
            model,
            &sequence.frames[0],
            &sequence.frames,
            &context.device,
        )?;
        let item = ProbeSequence {
            latents,
            poses: sequence.poses.clone(),
        };
        if sequence.scene < first_test_scene {
            train.push(item);
        } else {
            test.push(item);
        }
    }
    Ok((train, test))
}

/// The pose-free baselines with `context_views` context views, on the frames and pairs the
/// models are scored on.
pub(super) fn baselines(
    context_views: usize,
    context: &Context<'_>,
) -> Result<Baselines, EvalError> {
    let _span = tracing::info_span!("baselines", context_views).entered();
    let spec = context.spec;
    let sequences = || {
        reconstruction_set(&context.dataset, spec.reconstruction_sequences)
            .into_iter()
            .map(|s| s.frames.as_slice())
    };
    let (copy, _) = reconstruct(
        Renderer::CopyNearestContext,
        sequences(),
        context_views,
        context,
    )?;
    let (mean_colour, _) = reconstruct(Renderer::MeanColour, sequences(), context_views, context)?;
    let pairs = draw_pairs(spec.seed, spec.scenes, spec.trajectories, spec.tps_pairs)?;
    let still = transferability(
        &context.dataset,
        &pairs,
        tps_settings(context_views, context),
        context.oracle.as_ref(),
        |frames| Ok(vec![frames.contexts[0].clone(); frames.source.len()]),
    )?;
    let first_test_scene = first_probe_test_scene(context);
    let held_out: Vec<_> = context
        .dataset
        .sequences
        .iter()
        .filter(|s| s.scene >= first_test_scene)
        .map(|s| s.poses.clone())
        .collect();
    Ok(Baselines {
        copy,
        mean_colour,
        tps_no_motion: still.model,
        probe_no_motion: no_motion(&held_out, spec.seed),
    })
}
