//! `ptv experiment import`: an OpenPTV/pyptv experiment (the legacy
//! `parameters/` folder or a pyptv YAML, read by
//! [`crate::formats::experiment`]) written as `ptv`'s files:
//!
//! - `calibration.json`: the calibration JSON, with the splitter if any
//!   (`POST /api/v1/calibrations` takes it as it is);
//! - `sequence.json`: the body of `POST /api/v1/sequences` without
//!   `calibration_id` (add the id of the calibration created from
//!   `calibration.json`): name, detection (per-camera `thresholds`) and
//!   matching settings;
//! - `experiment.json`: what the images are: the experiment's directory
//!   (absolute), per camera the image name pattern (`%d` = frame), the
//!   first and last frame, the masks, the splitter, the tracking settings
//!   of `track.par` (the body of `POST /api/v1/sequences/{id}/tracking`),
//!   and the settings not mapped.
//!
//! `ptv process-sequence` and `ptv upload --experiment` read the OpenPTV
//! experiment itself (the directory or YAML given here), so that there is
//! one source of truth; `experiment.json` records what they will read.
//! The settings that cannot be mapped are printed on standard error, one
//! line each, with the reason.

use std::io::Write;
use std::path::PathBuf;

use clap::{Args, Subcommand};
use serde::Serialize;

use super::{write_stderr_line, CliError};
use crate::formats::experiment::{read_experiment, UnmappedSetting};
use crate::formats::{self, FormatError};
use crate::photogrammetry::Splitter;
use crate::service::model::parameters::{experiment_settings, DetectionSettings, MatchingSettings};

/// The `experiment` subcommands.
#[derive(Debug, Subcommand)]
pub enum ExperimentCommand {
    /// Read an OpenPTV experiment (a directory with parameters/*.par, or a
    /// pyptv parameters_*.yaml) and write calibration.json, sequence.json
    /// and experiment.json; the settings it cannot map are listed on
    /// standard error.
    Import(ImportExperimentArgs),
}

/// Arguments of `ptv experiment import`.
#[derive(Debug, Args)]
pub struct ImportExperimentArgs {
    /// The experiment: a directory with parameters/ptv.par (or with one
    /// parameters_*.yaml), or a pyptv YAML file.
    #[arg(value_name = "DIR")]
    pub dir: PathBuf,
    /// Where to write the three files (created if missing).
    #[arg(short, long, value_name = "OUTDIR", default_value = ".")]
    pub output: PathBuf,
}

/// The body of `POST /api/v1/sequences` without `calibration_id`.
#[derive(Serialize)]
struct SequenceBody {
    name: String,
    detection: DetectionSettings,
    matching: MatchingSettings,
}

/// `experiment.json`.
#[derive(Serialize)]
struct ExperimentFile<'a> {
    root: String,
    images: Vec<&'a str>,
    first: u64,
    last: u64,
    masks: Option<Vec<String>>,
    splitter: Option<Splitter>,
    calibration: &'static str,
    sequence: &'static str,
    /// The tracking settings of track.par (the body of `POST
    /// /api/v1/sequences/{id}/tracking`, and what `ptv process-sequence
    /// --track` uses), where the experiment has them.
    tracking: Option<serde_json::Value>,
    unmapped: &'a [UnmappedSetting],
}

/// Runs `ptv experiment import`.
pub(super) fn import(args: &ImportExperimentArgs, stderr: &mut dyn Write) -> Result<(), CliError> {
    let experiment = read_experiment(&args.dir)?;
    std::fs::create_dir_all(&args.output).map_err(|reason| FormatError::Io {
        path: args.output.clone(),
        reason,
    })?;
    let calibration =
        formats::calibration::to_json_with_splitter(&experiment.cameras, experiment.splitter);
    let (detection, matching) = experiment_settings(&experiment);
    let root = std::path::absolute(&experiment.root).unwrap_or(experiment.root.clone());
    let name = root
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let sequence = SequenceBody {
        name,
        detection,
        matching,
    };
    let file = ExperimentFile {
        root: root.display().to_string(),
        images: experiment
            .sequence
            .base_names
            .iter()
            .map(|p| p.as_str())
            .collect(),
        first: experiment.sequence.first,
        last: experiment.sequence.last,
        masks: experiment
            .masks
            .as_ref()
            .map(|list| list.iter().map(|p| p.display().to_string()).collect()),
        splitter: experiment.splitter,
        calibration: "calibration.json",
        sequence: "sequence.json",
        tracking: experiment.tracking.as_ref().map(|t| {
            let p = &t.parameters;
            serde_json::json!({
                "max_velocity": p.max_velocity,
                "max_acceleration": p.max_acceleration,
                "max_gap": p.max_gap,
                "min_length": p.min_length,
                "fit_half_window": p.fit_half_window,
                "fit_order": p.fit_order,
                "first_frame": experiment.sequence.first,
                "recovery": t.recovery,
                // The run's default (on: docs/tracking.md; pyptv's
                // tracking back is a step of its own).
                "backward": crate::service::model::tracking_settings::BACKWARD_BY_DEFAULT,
            })
        }),
        unmapped: &experiment.unmapped,
    };
    let json = |value: &dyn erased::Json| value.pretty() + "\n";
    for (name, text) in [
        ("calibration.json", calibration),
        ("sequence.json", json(&sequence)),
        ("experiment.json", json(&file)),
    ] {
        formats::write_text(&args.output.join(name), &text)?;
    }
    for setting in &experiment.unmapped {
        write_stderr_line(stderr, &format!("not mapped: {setting}"))?;
    }
    Ok(())
}

/// Pretty JSON of either file's struct.
mod erased {
    pub trait Json {
        fn pretty(&self) -> String;
    }
    impl<T: serde::Serialize> Json for T {
        fn pretty(&self) -> String {
            serde_json::to_string_pretty(self).expect("plain data serialises")
        }
    }
}
