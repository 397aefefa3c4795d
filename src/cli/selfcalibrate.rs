//! `ptv selfcalibrate`: a calibration refined from the particles of many
//! frames ([`crate::photogrammetry::selfcal`]): the targets of every camera
//! per frame (one printf-style pattern per camera, CSV or OpenPTV
//! `_targets`), or its images (`--images`, detected first as `ptv process`
//! detects them: `ptv detect`'s flags, `--background`, `--mask`, through
//! [`FramePipeline::detect_camera`]), the refined calibration JSON to
//! `-o`, the report (JSON) to standard output, a progress bar on standard
//! error when it is a terminal.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;

use clap::Args;

use super::detect::{
    preprocess_error, read_camera_preprocessing, DetectionFlags, PreprocessingFiles, RawImageFlags,
};
use super::{write_stderr_line, write_stdout, CliError};
use crate::formats;
use crate::formats::frames::{FramePattern, FrameRange, WithoutNumber};

use crate::photogrammetry::correspond::MatchingParameters;
use crate::photogrammetry::selfcal::{self, Outcome, SelfCalibrationOptions};
use crate::photogrammetry::{
    Camera, Cancel, FrameDetection, FramePipeline, PipelineError, Splitter, Target,
};

/// Arguments of `ptv selfcalibrate`.
#[derive(Debug, Args)]
pub struct SelfCalibrateArgs {
    /// The calibration to refine (JSON).
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// One camera's target files, with a printf-style frame number
    /// (`cam1.%05d_targets`, `cam1.%d.csv`); once per camera, in camera
    /// order.
    #[arg(
        long = "targets",
        value_name = "PATTERN",
        required_unless_present = "images",
        conflicts_with = "images"
    )]
    pub targets: Vec<String>,
    /// One camera's images instead of targets, with a printf-style frame
    /// number (`cam1.%05d.tif`); once per camera, in camera order (once
    /// with a splitter calibration: the whole sensor). Detected first with
    /// `ptv detect`'s flags.
    #[arg(long = "images", value_name = "PATTERN")]
    pub images: Vec<String>,
    /// How to find the targets in `--images`.
    #[command(flatten)]
    pub detection: DetectionFlags,
    /// With `--images`: an image of a camera's view without particles,
    /// subtracted before the high-pass filter; once per camera, in camera
    /// order, or not at all.
    #[arg(long = "background", value_name = "FILE", requires = "images")]
    pub backgrounds: Vec<PathBuf>,
    /// With `--images`: the pixels of a camera to use (non-zero = use);
    /// once per camera, in camera order, or not at all.
    #[arg(long = "mask", value_name = "FILE", requires = "images")]
    pub masks: Vec<PathBuf>,
    /// The layout of raw `--images`.
    #[command(flatten)]
    pub raw: RawImageFlags,
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
    /// xh,yh,c,k1,k2,k3,p1,p2,scx,she; and the media: glass (each wall's
    /// glass vector), n_wall, n_object, thickness.
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
    let mut options = SelfCalibrationOptions::default();
    for name in &args.free {
        options.free(name).map_err(|e| flag("--free", e))?;
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
        ..options
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
            let path = frame_file(pattern, frame, "--targets")?;
            let text = formats::read_text(&path)?;
            cameras.push(formats::parse_targets(&text, &path.display().to_string())?);
        }
        frames.push(cameras);
    }
    Ok(frames)
}

/// The patterns of `flag_name`, each matching a file for some frame of
/// `range`.
fn parse_patterns(
    given: &[String],
    flag_name: &'static str,
    range: FrameRange,
) -> Result<Vec<FramePattern>, CliError> {
    let patterns = given
        .iter()
        .map(|t| FramePattern::parse(t, WithoutNumber::Refuse).map_err(|e| flag(flag_name, e)))
        .collect::<Result<Vec<_>, _>>()?;
    for pattern in &patterns {
        if !(range.first..=range.last).any(|f| pattern.path(f).is_file()) {
            return Err(flag(
                flag_name,
                format!(
                    "the pattern `{}` matches no file for frames {}..{}; check the pattern and --frames",
                    pattern.as_str(),
                    range.first,
                    range.last
                ),
            ));
        }
    }
    Ok(patterns)
}

/// The path of `pattern` for `frame`, which must be a file.
fn frame_file(
    pattern: &FramePattern,
    frame: u64,
    flag_name: &'static str,
) -> Result<PathBuf, CliError> {
    let path = pattern.path(frame);
    if !path.is_file() {
        return Err(flag(
            flag_name,
            format!(
                "no file {} for frame {frame} (pattern `{}`); give --frames within the recorded frames",
                path.display(),
                pattern.as_str()
            ),
        ));
    }
    Ok(path)
}

/// Detects every frame's targets in its images, per frame and camera, as
/// `ptv process` does (the same [`FramePipeline`], its backgrounds and
/// masks); warnings for a threshold unsuited to an image's depth go to
/// `stderr` (for the first frame).
fn detect_frames(
    args: &SelfCalibrateArgs,
    cameras: &[Camera],
    splitter: Option<Splitter>,
    options: &SelfCalibrationOptions,
    stderr: &mut dyn Write,
) -> Result<Vec<Vec<Vec<Target>>>, CliError> {
    let layout = args.raw.layout();
    let preprocessing = read_camera_preprocessing(
        &args.calibration,
        cameras.len(),
        &args.backgrounds,
        &args.masks,
        layout.as_ref(),
    )?;
    let matching = MatchingParameters {
        tolerance: options.start_tolerance_px,
        volume: options.volume,
        ..MatchingParameters::default()
    };
    let detection = FrameDetection::AllCameras(args.detection.parameters());
    let pipeline = FramePipeline::new(cameras, &detection, &matching)
        .and_then(|pipeline| pipeline.with_preprocessing(preprocessing))
        .map_err(|e| pipeline_error(args, e, &args.calibration))?;
    let patterns = parse_patterns(&args.images, "--images", args.frames)?;
    let mut frames = Vec::new();
    for frame in args.frames.first..=args.frames.last {
        let mut images = Vec::with_capacity(patterns.len());
        for pattern in &patterns {
            let path = frame_file(pattern, frame, "--images")?;
            let image = formats::image::read_image(&path, layout.as_ref())?;
            if frame == args.frames.first {
                args.detection
                    .warn_if_threshold_unsuited(&image, &path, stderr)?;
            }
            images.push((path, image));
        }
        let views = match splitter {
            Some(splitter) => {
                let (path, image) = &images[0];
                let views = splitter.split(image).map_err(|source| CliError::Splitter {
                    image: path.clone(),
                    source,
                })?;
                views.into_iter().map(|v| (path.clone(), v)).collect()
            }
            None => images,
        };
        let targets = views
            .iter()
            .enumerate()
            .map(|(camera, (path, image))| {
                pipeline
                    .detect_camera(camera, image)
                    .map_err(|e| pipeline_error(args, e, path))
            })
            .collect::<Result<Vec<_>, _>>()?;
        frames.push(targets);
    }
    Ok(frames)
}

/// Detection's errors in the command line's terms (as `ptv process`
/// reports them): `file` is the image, or the calibration while preparing.
fn pipeline_error(
    args: &SelfCalibrateArgs,
    error: PipelineError,
    file: &std::path::Path,
) -> CliError {
    match error {
        PipelineError::Detection { source, .. } => CliError::Detection(source),
        PipelineError::Matching(source) => CliError::Matching(source),
        PipelineError::Sensor { camera, source } => CliError::ImageSize {
            image: file.to_path_buf(),
            camera,
            calibration: args.calibration.clone(),
            source,
        },
        PipelineError::Preprocess { camera, source } => {
            let files = PreprocessingFiles {
                background: args.backgrounds.get(camera).map(PathBuf::as_path),
                mask: args.masks.get(camera).map(PathBuf::as_path),
            };
            preprocess_error(source, file, &files)
        }
        other => CliError::Pipeline(other),
    }
}

/// Self-calibrates, writes the refined calibration JSON to `--output` and
/// the report to standard output.
pub(super) fn run(
    args: &SelfCalibrateArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let (cameras, splitter) = super::read_calibration_with_splitter(&args.calibration)?;
    let options = options(args)?;
    let frames = if args.images.is_empty() {
        super::check_camera_count(
            &args.calibration,
            cameras.len(),
            args.targets.len(),
            ("--targets", "target pattern"),
        )?;
        let patterns = parse_patterns(&args.targets, "--targets", args.frames)?;
        read_frames(&patterns, args.frames)?
    } else {
        let expected = if splitter.is_some() { 1 } else { cameras.len() };
        if args.images.len() != expected {
            return Err(flag(
                "--images",
                format!(
                    "{} has {} cameras{}: give --images {expected} times, in camera order, not {}",
                    args.calibration.display(),
                    cameras.len(),
                    if splitter.is_some() {
                        " (views of one sensor: one pattern of the whole sensor's images)"
                    } else {
                        ""
                    },
                    args.images.len()
                ),
            ));
        }
        detect_frames(args, &cameras, splitter, &options, stderr)?
    };
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
    formats::write_text(
        &args.output,
        &formats::calibration::to_json_with_splitter(&refined, splitter),
    )?;
    if let Some(path) = &args.disparity_png {
        let png = crate::plot::disparity_png(&result.report)
            .map_err(|e| flag("--disparity-png", e.to_string()))?;
        formats::write_file(path, &png)?;
    }
    // The report holds only numbers, strings and enums: serialising it
    // cannot fail; should it, the message says so in the JSON.
    let json = serde_json::to_string_pretty(&result.report)
        .unwrap_or_else(|e| format!("{{\"error\": \"the report did not serialise: {e}\"}}"));
    write_stdout(stdout, &(json + "\n"))
}
