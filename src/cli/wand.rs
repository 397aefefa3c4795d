//! `ptv calibrate --wand`: wand (dumbbell) calibration
//! ([`crate::photogrammetry::selfcal::wand`]) from the wand's frames, as
//! targets per camera (`--wand-targets PATTERN`, once per camera) or as
//! images (`--wand-images PATTERN`, detected with the detection flags),
//! starting from `--calibration` (a rough rig or a plate calibration).
//! Writes the calibrated rig to `--output` and the report (JSON) to
//! standard output; a summary to standard error.

use std::io::Write;
use std::path::Path;

use clap::Args;

use super::{write_stderr_line, write_stdout, CliError};
use crate::formats::frames::{FramePattern, FrameRange, WithoutNumber};
use crate::formats::{self, control};
use crate::photogrammetry::selfcal::wand::{self, WandOptions};
use crate::photogrammetry::{Camera, Cancel, Target};

/// The wand calibration's flags of `ptv calibrate`.
#[derive(Debug, Args)]
pub struct WandFlags {
    /// Calibrate with a wand (two marks a known distance apart, moved
    /// through the volume) instead of control points: needs
    /// --wand-length, --frames and --wand-targets or --wand-images.
    #[arg(long, requires_all = ["wand_length", "frames"])]
    pub wand: bool,
    /// The distance between the wand's two marks (mm).
    #[arg(long, value_name = "MM", requires = "wand")]
    pub wand_length: Option<f64>,
    /// The wand's frames, FIRST..LAST (inclusive); a frame whose file is
    /// missing for some camera is skipped.
    #[arg(long, value_name = "FIRST..LAST", value_parser = FrameRange::parse, requires = "wand")]
    pub frames: Option<FrameRange>,
    /// One camera's target files of the wand frames, with a printf-style
    /// frame number (`cam1_targets.%05d.csv`); once per camera, in camera
    /// order. Per frame the two brightest targets are the wand's marks.
    #[arg(
        long,
        value_name = "PATTERN",
        requires = "wand",
        conflicts_with = "wand_images"
    )]
    pub wand_targets: Vec<String>,
    /// One camera's images of the wand frames, with a printf-style frame
    /// number; once per camera, in camera order; detected with the
    /// detection flags.
    #[arg(long, value_name = "PATTERN", requires = "wand")]
    pub wand_images: Vec<String>,
}

fn flag(flag: &'static str, reason: impl Into<String>) -> CliError {
    CliError::Flag {
        flag,
        reason: reason.into(),
    }
}

/// Runs the wand calibration of `args`.
pub(super) fn run(
    args: &super::CalibrateArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let w = &args.wand;
    let length = w
        .wand_length
        .ok_or_else(|| flag("--wand-length", "give the wand's length in mm"))?;
    let range = w
        .frames
        .ok_or_else(|| flag("--frames", "give the wand's frames, FIRST..LAST"))?;
    let Some(setup) = &args.calibration else {
        return Err(CliError::Flag {
            flag: "--calibration",
            reason: "--wand starts from a setup calibration; give --calibration".into(),
        });
    };
    let start =
        formats::calibration::from_json(&formats::read_text(setup)?, &setup.display().to_string())?;
    let (patterns, images, which) = match (w.wand_targets.is_empty(), w.wand_images.is_empty()) {
        (false, true) => (&w.wand_targets, false, "--wand-targets"),
        (true, false) => (&w.wand_images, true, "--wand-images"),
        _ => {
            return Err(flag(
                "--wand-targets",
                "give the wand's frames as --wand-targets or --wand-images, once per camera",
            ))
        }
    };
    super::check_camera_count(setup, start.len(), patterns.len(), (which, "pattern"))?;
    let patterns = patterns
        .iter()
        .map(|p| FramePattern::parse(p, WithoutNumber::Refuse).map_err(|e| flag(which, e)))
        .collect::<Result<Vec<_>, _>>()?;
    let fixed = control::fixed_parameters(&args.fix).map_err(|e| flag("--fix", e.reason))?;
    let options = WandOptions {
        fixed,
        max_correlation: args.max_correlation,
        ..WandOptions::new(length)
    };
    let parameters = args.detection.parameters();
    let mut frames: Vec<Vec<Vec<Target>>> = Vec::new();
    let mut numbers = Vec::new();
    let mut missing = 0u64;
    for frame in range.first..=range.last {
        if patterns.iter().any(|p| !p.path(frame).is_file()) {
            missing += 1;
            continue;
        }
        let targets = patterns
            .iter()
            .zip(&start)
            .map(|(p, camera)| read_frame(&p.path(frame), images, camera, &parameters))
            .collect::<Result<Vec<_>, _>>()?;
        frames.push(targets);
        numbers.push(frame);
    }
    if missing > 0 {
        write_stderr_line(
            stderr,
            &format!("{missing} frames skipped: a camera's file is missing"),
        )?;
    }
    let cameras: Vec<_> = start.iter().map(|c| c.parameters().clone()).collect();
    let result = wand::wand_calibrate(&cameras, &frames, &options, &Cancel::new())?;
    let r = &result.report;
    write_stderr_line(
        stderr,
        &format!(
            "{} wand positions used of {} frames ({} incomplete, {} ambiguous pairings, {} \
             removed as gross errors); reprojection RMS {:.4} px, sigma0 {:.4} px; wand length \
             {:.4} mm +- {:.4} mm (min {:.4}, max {:.4}); the start's scale multiplied by {:.6}",
            r.positions,
            r.frames,
            r.incomplete,
            r.ambiguous,
            r.rejected,
            r.rms_px,
            r.sigma0_px,
            r.length_after.mean_mm,
            r.length_after.std_mm,
            r.length_after.min_mm,
            r.length_after.max_mm,
            r.scale_factor
        ),
    )?;
    let models = result
        .cameras
        .iter()
        .map(|p| Camera::new(p.clone()))
        .collect::<Result<Vec<_>, _>>()?;
    formats::write_text(&args.output, &formats::calibration::to_json(&models))?;
    // Frame numbers in the report are the files' numbers.
    let mut report = serde_json::to_value(r).map_err(|e| flag("--output", e.to_string()))?;
    report["frame_numbers"] = serde_json::json!({
        "first": range.first,
        "last": range.last,
        "read": numbers.len(),
    });
    let text =
        serde_json::to_string_pretty(&report).map_err(|e| flag("--output", e.to_string()))?;
    write_stdout(stdout, &(text + "\n"))
}

fn read_frame(
    path: &Path,
    image: bool,
    camera: &Camera,
    parameters: &crate::photogrammetry::DetectionParameters,
) -> Result<Vec<Target>, CliError> {
    if image {
        let grey = formats::image::read_image(path, None)?;
        let sensor = camera.sensor();
        if (grey.width(), grey.height()) != (sensor.width, sensor.height) {
            return Err(flag(
                "--wand-images",
                format!(
                    "{} is {}x{} px, the camera's sensor {}x{}",
                    path.display(),
                    grey.width(),
                    grey.height(),
                    sensor.width,
                    sensor.height
                ),
            ));
        }
        Ok(crate::photogrammetry::detect(&grey, parameters))
    } else {
        Ok(formats::parse_targets(
            &formats::read_text(path)?,
            &path.display().to_string(),
        )?)
    }
}
