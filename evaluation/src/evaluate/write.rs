//! The evaluation's last phase: the figures of every model scored, then `report.json` and
//! `report.md`, written into the output folder. Each model keeps only what its figures draw
//! ([`FigureSet`]) from the time it is scored until everything is written.

use std::path::Path;

use data::Image;

use super::gather::{Gathered, layout};
use super::infer::ModelOutputs;
use super::markdown;
use super::score::TransferPaths;
use super::{EvaluationReport, GRID_PAIRS};
use crate::error::{EvalError, io_error};
use crate::figures::{save_camera_paths, save_sheet};
use crate::probe::ProbePath;

/// Named rows of images: one figure's sheet.
type Sheet = Vec<(String, Vec<Image>)>;

/// What one model's figures draw: the first few reconstructions and transfers, and the poses
/// read from them.
pub(super) struct FigureSet {
    /// Names the figures (`stage1_trained`).
    prefix: String,
    /// Context views the model rendered from.
    views: usize,
    /// Generated sequences above their renders.
    reconstruction: Sheet,
    /// Real test sequences above their renders, by dataset name.
    sequences: Vec<(String, Sheet)>,
    /// Transfers: the source video, the target scene's context, the render, the truth.
    transfers: Sheet,
    /// The oracle's reading of the first transfer.
    transfer_paths: Option<TransferPaths>,
    /// The first held-out probe sequence's true and predicted path.
    probe_path: Option<ProbePath>,
}

impl FigureSet {
    /// Keeps what the figures of the model named `prefix` draw out of its outputs and scores.
    pub(super) fn new(
        prefix: String,
        views: usize,
        outputs: &ModelOutputs,
        (transfer_paths, probe_paths): (Option<TransferPaths>, Vec<ProbePath>),
        gathered: &Gathered<'_>,
    ) -> Result<Self, EvalError> {
        let frames: Vec<&[Image]> = gathered.reconstructed_frames().collect();
        let reconstruction = sequence_sheet(&frames, &outputs.reconstruction, views);
        let sequences = gathered
            .protocol_sets
            .iter()
            .zip(&outputs.sequences)
            .map(|(set, renders)| {
                let frames: Vec<&[Image]> =
                    set.sequences.iter().map(|s| s.frames.as_slice()).collect();
                let name = set.protocol.kind.name().to_string();
                (name, sequence_sheet(&frames, renders, 1))
            })
            .collect();
        let mut transfers = Sheet::new();
        let pairs = gathered.transfers(views)?.iter().zip(&outputs.transfers);
        for (index, (frames, renders)) in pairs.take(GRID_PAIRS).enumerate() {
            let row = |what: &str, images: &[Image]| {
                (format!("pair {}: {what}", index + 1), images.to_vec())
            };
            transfers.push(row("source video", &frames.source));
            transfers.push(row("target scene's context", &frames.contexts));
            transfers.push(row("our render", renders));
            transfers.push(row("truth along source path", &frames.ideal));
        }
        Ok(Self {
            prefix,
            views,
            reconstruction,
            sequences,
            transfers,
            transfer_paths,
            probe_path: probe_paths.into_iter().next(),
        })
    }
}

/// The first [`GRID_PAIRS`] sequences with targets: each one's frames, then the same frames
/// with its targets replaced by their renders (context views in place).
fn sequence_sheet(frames: &[&[Image]], renders: &[Vec<Image>], views: usize) -> Sheet {
    let mut sheet = Sheet::new();
    let with_targets = frames
        .iter()
        .zip(renders)
        .filter(|(frames, _)| !layout(frames.len(), views).1.is_empty());
    for (index, (frames, renders)) in with_targets.take(GRID_PAIRS).enumerate() {
        let (_, targets) = layout(frames.len(), views);
        let mut rendered = frames.to_vec();
        for (&t, image) in targets.iter().zip(renders) {
            rendered[t] = image.clone();
        }
        let name = |what: &str| format!("sequence {}: {what}", index + 1);
        sheet.push((name("frames"), frames.to_vec()));
        sheet.push((name("renders"), rendered));
    }
    sheet
}

/// `frame 1`, `frame 2`, ... for the longest row of `rows`.
fn frame_columns(rows: &Sheet) -> Vec<String> {
    let longest = rows.iter().map(|(_, row)| row.len()).max().unwrap_or(0);
    (1..=longest).map(|i| format!("frame {i}")).collect()
}

/// The figures written so far, by name relative to the output folder.
struct Figures<'a> {
    out_dir: &'a Path,
    names: Vec<String>,
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

    /// A sheet of named rows of images.
    fn sheet(&mut self, name: String, title: &str, rows: &Sheet) -> Result<(), EvalError> {
        let columns = frame_columns(rows);
        self.save(name, &|p| Ok(save_sheet(title, &columns, rows, p)?))
    }
}

/// Writes every set's figures, lists them in `report`, then writes `report.json` and
/// `report.md` into `out_dir`.
pub(super) fn write(
    report: &mut EvaluationReport,
    sets: &[FigureSet],
    out_dir: &Path,
) -> Result<(), EvalError> {
    let mut figures = Figures {
        out_dir,
        names: Vec::new(),
    };
    for set in sets {
        write_set(set, &mut figures)?;
    }
    report.figures = figures.names;
    let json_path = out_dir.join("report.json");
    let json = serde_json::to_string_pretty(report).map_err(|e| io_error(&json_path, e))?;
    std::fs::write(&json_path, json).map_err(|e| io_error(&json_path, e))?;
    let md_path = out_dir.join("report.md");
    std::fs::write(&md_path, markdown(report)).map_err(|e| io_error(&md_path, e))?;
    Ok(())
}

/// One model's figures, in the report's order: reconstructions, real sequences, transfers and
/// their camera paths, the probe's path.
fn write_set(set: &FigureSet, figures: &mut Figures<'_>) -> Result<(), EvalError> {
    let prefix = &set.prefix;
    let title = format!(
        "{prefix}: held-out sequences and their renders ({} context view(s) in place)",
        set.views
    );
    figures.sheet(
        format!("{prefix}_reconstruction.png"),
        &title,
        &set.reconstruction,
    )?;
    for (name, sheet) in &set.sequences {
        let title = format!("{prefix}: {name} test sequences and their renders");
        figures.sheet(format!("{prefix}_sequences_{name}.png"), &title, sheet)?;
    }
    let title = format!("{prefix}: the source video's camera path rendered in another scene");
    figures.sheet(format!("{prefix}_tps_renders.png"), &title, &set.transfers)?;
    if let Some(paths) = &set.transfer_paths {
        let (title, rendered) = match &paths.renders {
            Ok(rendered) => (format!("{prefix}: transferred camera path"), &rendered[..]),
            Err(error) => (
                format!(
                    "{prefix}: transferred camera path (the oracle could not read the renders: {error})"
                ),
                &[][..],
            ),
        };
        figures.save(format!("{prefix}_tps_paths.png"), &|p| {
            let mut drawn = vec![("source video (oracle poses)", &paths.source[..])];
            if !rendered.is_empty() {
                drawn.push(("renders (oracle poses)", rendered));
            }
            Ok(save_camera_paths(&title, &drawn, p)?)
        })?;
    }
    if let Some((reference, predicted)) = &set.probe_path {
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
    Ok(())
}
