//! `ptv selfcalibrate`: a calibration refined from the particles of many
//! frames ([`crate::photogrammetry::selfcal`]): the targets of every camera
//! per frame (one printf-style pattern per camera, CSV or OpenPTV
//! `_targets`), the refined calibration JSON to `-o`, the report (JSON) to
//! standard output, a progress bar on standard error when it is a terminal.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;

use clap::Args;

use super::{write_stderr_line, write_stdout, CliError};
use crate::formats;
use crate::formats::frames::{FramePattern, FrameRange, WithoutNumber};
use crate::photogrammetry::calibrate::Parameter;
use crate::photogrammetry::selfcal::{self, Outcome, SelfCalibrationOptions};
use crate::photogrammetry::{Cancel, Target};

/// Arguments of `ptv selfcalibrate`.
#[derive(Debug, Args)]
pub struct SelfCalibrateArgs {
    /// The calibration to refine (JSON).
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// One camera's target files, with a printf-style frame number
    /// (`cam1.%05d_targets`, `cam1.%d.csv`); once per camera, in camera
    /// order.
    #[arg(long = "targets", value_name = "PATTERN", required = true)]
    pub targets: Vec<String>,
    /// The frames, FIRST..LAST (inclusive).
    #[arg(long, value_name = "FIRST..LAST", value_parser = FrameRange::parse)]
    pub frames: FrameRange,
    /// The first round's band (px): wide enough for the calibration's
    /// disparities.
    #[arg(long, value_name = "PX", default_value_t = 4.0)]
    pub tolerance: f64,
    /// The narrowest band (px), about 3-5 times the image noise.
    #[arg(long, value_name = "PX", default_value_t = 0.5)]
    pub final_tolerance: f64,
    /// The observation volume (mm), xmin,xmax,ymin,ymax,zmin,zmax
    /// [default: the region all cameras look at].
    #[arg(
        long,
        value_name = "XMIN,XMAX,YMIN,YMAX,ZMIN,ZMAX",
        allow_hyphen_values = true
    )]
    pub volume: Option<String>,
    /// Parameters to adjust besides the exterior orientation (interior and
    /// distortion are fixed by default), comma separated, OpenPTV's names:
    /// xh,yh,c,k1,k2,k3,p1,p2,scx,she.
    #[arg(long, value_name = "LIST", value_delimiter = ',')]
    pub free: Vec<String>,
    /// The fewest cameras a confident particle must be seen by.
    #[arg(long, value_name = "K", default_value_t = 3)]
    pub min_cameras: usize,
    /// Where to write the refined calibration JSON.
    #[arg(short, long, value_name = "CALIBRATION_JSON")]
    pub output: PathBuf,
    /// Also draw the report's disparity maps (per camera and sub-volume,
    /// before and after) as a PNG picture to this file.
    #[arg(long, value_name = "FILE")]
    pub disparity_png: Option<PathBuf>,
}

fn flag(flag: &'static str, reason: impl Into<String>) -> CliError {
    CliError::Flag {
        flag,
        reason: reason.into(),
    }
}

fn options(args: &SelfCalibrateArgs) -> Result<SelfCalibrationOptions, CliError> {
    let mut fixed = selfcal::default_fixed();
    for name in &args.free {
        let p = Parameter::from_name(name).ok_or_else(|| {
            flag(
                "--free",
                format!(
                    "`{name}` is not a parameter; give names among xh,yh,c,k1,k2,k3,p1,p2,scx,she"
                ),
            )
        })?;
        fixed.retain(|q| *q != p);
    }
    Ok(SelfCalibrationOptions {
        start_tolerance_px: args.tolerance,
        final_tolerance_px: args.final_tolerance,
        volume: args
            .volume
            .as_deref()
            .map(super::match_targets::parse_volume)
            .transpose()?,
        min_cameras: args.min_cameras,
        fixed,
        ..SelfCalibrationOptions::default()
    })
}

/// Reads every frame's targets: per frame, per camera.
fn read_frames(
    patterns: &[FramePattern],
    range: FrameRange,
) -> Result<Vec<Vec<Vec<Target>>>, CliError> {
    let mut frames = Vec::new();
    for frame in range.first..=range.last {
        let mut cameras = Vec::with_capacity(patterns.len());
        for pattern in patterns {
            let path = pattern.path(frame);
            if !path.is_file() {
                return Err(flag(
                    "--targets",
                    format!(
                        "no file {} for frame {frame} (pattern `{}`); give --frames within the recorded frames",
                        path.display(),
                        pattern.as_str()
                    ),
                ));
            }
            let text = formats::read_text(&path)?;
            cameras.push(formats::parse_targets(&text, &path.display().to_string())?);
        }
        frames.push(cameras);
    }
    Ok(frames)
}

/// Self-calibrates, writes the refined calibration JSON to `--output` and
/// the report to standard output.
pub(super) fn run(
    args: &SelfCalibrateArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = super::read_calibration(&args.calibration)?;
    super::check_camera_count(
        &args.calibration,
        cameras.len(),
        args.targets.len(),
        ("--targets", "target pattern"),
    )?;
    let patterns = args
        .targets
        .iter()
        .map(|t| FramePattern::parse(t, WithoutNumber::Refuse).map_err(|e| flag("--targets", e)))
        .collect::<Result<Vec<_>, _>>()?;
    for pattern in &patterns {
        if !(args.frames.first..=args.frames.last).any(|f| pattern.path(f).is_file()) {
            return Err(flag(
                "--targets",
                format!(
                    "the pattern `{}` matches no file for frames {}..{}; check the pattern and --frames",
                    pattern.as_str(),
                    args.frames.first,
                    args.frames.last
                ),
            ));
        }
    }
    let options = options(args)?;
    let frames = read_frames(&patterns, args.frames)?;
    let parameters: Vec<_> = cameras.iter().map(|c| c.parameters().clone()).collect();
    selfcal::check_inputs(&parameters, &frames, &options)?;
    let bar = indicatif::ProgressBar::with_draw_target(
        Some((frames.len() * options.max_rounds) as u64),
        if std::io::stderr().is_terminal() {
            indicatif::ProgressDrawTarget::stderr()
        } else {
            indicatif::ProgressDrawTarget::hidden()
        },
    );
    let result =
        selfcal::self_calibrate(&parameters, &frames, &options, &Cancel::new(), &mut |p| {
            bar.set_position((p.round * p.frames + p.frames_matched) as u64);
            bar.set_message(format!("round {}, band {:.2} px", p.round + 1, p.band_px));
        })?;
    bar.finish_and_clear();
    if result.report.outcome == Outcome::Diverged {
        write_stderr_line(
            stderr,
            &format!(
                "warning: the self-calibration diverged ({}); {} is the input calibration unchanged",
                result.report.message.as_deref().unwrap_or("no reason given"),
                args.output.display()
            ),
        )?;
    }
    let refined = result
        .cameras
        .iter()
        .map(|p| crate::photogrammetry::Camera::new(p.clone()))
        .collect::<Result<Vec<_>, _>>()?;
    formats::write_text(&args.output, &formats::calibration::to_json(&refined))?;
    if let Some(path) = &args.disparity_png {
        let png = crate::plot::disparity_png(&result.report)
            .map_err(|e| flag("--disparity-png", e.to_string()))?;
        std::fs::write(path, png).map_err(|reason| formats::FormatError::Io {
            path: path.clone(),
            reason,
        })?;
    }
    // The report holds only numbers, strings and enums: serialising it
    // cannot fail; should it, the message says so in the JSON.
    let json = serde_json::to_string_pretty(&result.report)
        .unwrap_or_else(|e| format!("{{\"error\": \"the report did not serialise: {e}\"}}"));
    write_stdout(stdout, &(json + "\n"))
}
