//! `ptv calibrate`: the rig's calibration by resection on control points
//! ([`crate::photogrammetry::calibrate`]), from measured image coordinates
//! or from calibration images (detection, then identification of the marks).

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;

use super::{write_stderr_line, write_stdout, CliError, DetectionFlags};
use crate::formats::{self, control};
use crate::photogrammetry::calibrate::{self, CalibrationOptions, MarkObservation};

/// Arguments of `ptv calibrate`.
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// The setup: a calibration JSON with sensor (image_size, pixel_size)
    /// and media of every camera; its orientation (position, angles,
    /// principal_distance) is optional, used only for fixed parameters and,
    /// with --image and no --reference, as starting values to identify marks.
    #[arg(
        long,
        value_name = "SETUP_JSON",
        required_unless_present = "experiment"
    )]
    pub calibration: Option<PathBuf>,
    /// The control points (OpenPTV calibration block: `id X Y Z` per line,
    /// mm); not with --wand.
    #[arg(
        long,
        value_name = "CALBLOCK",
        required_unless_present_any = ["wand", "experiment", "calib_points", "plane"],
        conflicts_with = "wand"
    )]
    pub control: Option<PathBuf>,
    /// The LPT challenge's calibration points instead of --control and
    /// --observations: `X Y Z x1 y1 ... xN yN` per line, a control point
    /// (mm) and its image in each of the setup's N cameras (pixels).
    #[arg(
        long,
        value_name = "FILE",
        conflicts_with_all = ["control", "observations", "image", "reference", "wand", "experiment"]
    )]
    pub calib_points: Option<PathBuf>,
    /// Calibrate an OpenPTV experiment (a directory with parameters/*.par,
    /// or a pyptv YAML) from its own calibration images as OpenPTV would:
    /// the setup from ptv.par and the .ori/.addpar files, the target and
    /// images from cal_ori, the detection from detect_plate, the fixed
    /// parameters from orient, and man_ori's manual points as the start.
    /// Writes calibration.json, camN.ori/.addpar and report.json into
    /// --output (a directory).
    #[arg(
        long,
        value_name = "DIR",
        conflicts_with_all = ["calibration", "control", "observations", "image", "reference", "fix", "wand"]
    )]
    pub experiment: Option<PathBuf>,
    /// Measured image coordinates of control points, `id x y` per line
    /// (pixels); once per camera, in camera order.
    #[arg(long, value_name = "FILE")]
    pub observations: Vec<PathBuf>,
    /// A calibration image per camera, in camera order, instead of
    /// --observations: marks are detected (allow their size with
    /// --max-pixels) and identified with the control points.
    #[arg(long, value_name = "IMAGE", conflicts_with = "observations")]
    pub image: Vec<PathBuf>,
    /// Multi-plane calibration: the plate at one known position, its
    /// control points in the common frame (`id X Y Z`) and one image per
    /// camera in camera order, as CONTROL:IMAGE1,IMAGE2,...; repeat for
    /// each position (the plate moved along its normal). All positions go
    /// into one adjustment; the setup's orientation identifies the marks.
    /// In the report, plane k's point id is k * 1000000 + id.
    #[arg(
        long,
        value_name = "CONTROL:IMAGES",
        conflicts_with_all = ["control", "calib_points", "image", "observations", "reference", "experiment", "wand"]
    )]
    pub plane: Vec<String>,
    /// With --image: per camera, at least 6 identified marks (`id x y`; 4 if
    /// they lie in one plane and c, xh, yh are fixed) to start from; without
    /// it, the setup's orientation is the start.
    #[arg(long, value_name = "FILE", requires = "image")]
    pub reference: Vec<PathBuf>,
    /// Parameters held at the setup's values, comma separated, OpenPTV's
    /// names: x0,y0,z0,omega,phi,kappa,xh,yh,c,k1,k2,k3,p1,p2,scx,she.
    #[arg(long, value_name = "LIST", value_delimiter = ',')]
    pub fix: Vec<String>,
    /// Every K-th control point (file order) is a check point: left out of
    /// the resections, then intersected from all cameras.
    #[arg(long, value_name = "K", conflicts_with = "check_ids")]
    pub check_every: Option<usize>,
    /// A file of check point ids (whitespace separated).
    #[arg(long, value_name = "FILE")]
    pub check_ids: Option<PathBuf>,
    /// Parameters correlated above this are held (one of each pair).
    #[arg(long, value_name = "R", default_value_t = 0.99)]
    pub max_correlation: f64,
    /// Where to write the calibrated calibration JSON (with --experiment:
    /// the directory for its files).
    #[arg(short, long, value_name = "CALIBRATION_JSON")]
    pub output: PathBuf,
    /// Detection of the marks, with --image.
    #[command(flatten)]
    pub detection: DetectionFlags,
    /// With --image: an image of a camera's view without the target (same
    /// size and bit depth), subtracted before detection; once per camera,
    /// in camera order, or not at all.
    #[arg(long = "background", value_name = "FILE", requires = "image")]
    pub backgrounds: Vec<PathBuf>,
    /// With --image: an image of the pixels of a camera to use (same size,
    /// non-zero = use); once per camera, in camera order, or not at all.
    #[arg(long = "mask", value_name = "FILE", requires = "image")]
    pub masks: Vec<PathBuf>,
    /// Wand calibration instead (`--wand`).
    #[command(flatten)]
    pub wand: super::wand::WandFlags,
}

fn flag(flag: &'static str, reason: impl Into<String>) -> CliError {
    CliError::Flag {
        flag,
        reason: reason.into(),
    }
}

fn options(args: &CalibrateArgs) -> Result<CalibrationOptions, CliError> {
    options_with(args, &args.fix)
}

fn options_with(args: &CalibrateArgs, fix: &[String]) -> Result<CalibrationOptions, CliError> {
    let check_ids = match &args.check_ids {
        Some(path) => Some(control::parse_check_ids(
            &formats::read_text(path)?,
            &path.display().to_string(),
        )?),
        None => None,
    };
    control::fixed_parameters(fix)
        .and_then(|fixed| {
            control::calibration_options(fixed, args.check_every, check_ids, args.max_correlation)
        })
        .map_err(|e| {
            flag(
                match e.option {
                    "fix" => "--fix",
                    "check_every" => "--check-every",
                    "check_ids" => "--check-ids",
                    _ => "--max-correlation",
                },
                e.reason,
            )
        })
}

fn read_marks(path: &Path) -> Result<Vec<MarkObservation>, CliError> {
    let text = formats::read_text(path)?;
    Ok(control::parse_mark_observations(
        &text,
        &path.display().to_string(),
    )?)
}

/// Calibrates, writes the calibration JSON to `--output` and the report to
/// standard output.
pub(super) fn run(
    args: &CalibrateArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    if let Some(dir) = &args.experiment {
        return run_experiment(args, dir, stdout, stderr);
    }
    if args.wand.wand {
        return super::wand::run(args, stdout, stderr);
    }
    if !args.plane.is_empty() {
        return run_planes(args, stdout, stderr);
    }
    let Some(calibration) = &args.calibration else {
        return Err(flag(
            "--calibration",
            "give --calibration with --control, --calib-points or --plane, or --wand, or \
             --experiment",
        ));
    };
    let formats::calibration::Setup {
        cameras: setup,
        unknown,
    } = formats::calibration::setup_from_json(
        &formats::read_text(calibration)?,
        &calibration.display().to_string(),
    )?;
    let (control_points, calib_points) =
        match (&args.calib_points, &args.control) {
            (Some(path), _) => {
                let (points, observations) = control::parse_calib_points(
                    &formats::read_text(path)?,
                    &path.display().to_string(),
                    setup.len(),
                )?;
                (points, Some(observations))
            }
            (None, Some(control_path)) => (
                control::parse_control_points(
                    &formats::read_text(control_path)?,
                    &control_path.display().to_string(),
                )?,
                None,
            ),
            (None, None) => return Err(flag(
                "--control",
                "give --calibration with --control or --calib-points, or --wand, or --experiment",
            )),
        };
    let options = CalibrationOptions {
        unknown,
        ..options(args)?
    };
    let result = if let Some(observations) = calib_points {
        calibrate::calibrate(&setup, &control_points, &observations, &options)?
    } else if args.image.is_empty() {
        super::check_camera_count(
            calibration,
            setup.len(),
            args.observations.len(),
            ("--observations", "observation file"),
        )?;
        let observations = args
            .observations
            .iter()
            .map(|p| read_marks(p))
            .collect::<Result<Vec<_>, _>>()?;
        calibrate::calibrate(&setup, &control_points, &observations, &options)?
    } else {
        super::check_camera_count(
            calibration,
            setup.len(),
            args.image.len(),
            ("--image", "image"),
        )?;
        if !args.reference.is_empty() {
            super::check_camera_count(
                calibration,
                setup.len(),
                args.reference.len(),
                ("--reference", "reference file"),
            )?;
        }
        let references = if args.reference.is_empty() {
            vec![Vec::new(); setup.len()]
        } else {
            args.reference
                .iter()
                .map(|p| read_marks(p))
                .collect::<Result<Vec<_>, _>>()?
        };
        // Before reading any image: can every camera's marks be identified?
        let counts: Vec<usize> = references.iter().map(Vec::len).collect();
        calibrate::check_mark_inputs(&setup, &control_points, &counts, &options)?;
        let (parameters, preprocessing) = mark_detection(args, calibration, setup.len())?;
        let mut marks = Vec::with_capacity(args.image.len());
        for (k, path) in args.image.iter().enumerate() {
            marks.push(detect_in_image(
                args,
                k,
                path,
                &preprocessing[k],
                &parameters,
                stderr,
            )?);
        }
        calibrate::calibrate_from_marks(&setup, &control_points, &marks, &references, &options)?
    };
    let cameras = result.camera_models()?;
    formats::write_text(&args.output, &formats::calibration::to_json(&cameras))?;
    write_stdout(stdout, &control::report_to_json(&result.report))
}

/// The marks of camera `k`'s calibration image `path`, with `--background`
/// and `--mask` (`preprocessing`) if given; the count goes to stderr.
fn detect_in_image(
    args: &CalibrateArgs,
    k: usize,
    path: &Path,
    preprocessing: &crate::photogrammetry::Preprocessing,
    parameters: &crate::photogrammetry::DetectionParameters,
    stderr: &mut dyn Write,
) -> Result<Vec<crate::photogrammetry::Target>, CliError> {
    let image = formats::image::read_image(path, None)?;
    args.detection
        .warn_if_threshold_unsuited(&image, path, stderr)?;
    let found = if preprocessing.is_empty() {
        calibrate::detect_marks(&image, parameters).map_err(|error| CliError::Flag {
            flag: "--image",
            reason: format!("{}: {error}", path.display()),
        })?
    } else {
        let files = super::detect::PreprocessingFiles {
            background: args.backgrounds.get(k).map(PathBuf::as_path),
            mask: args.masks.get(k).map(PathBuf::as_path),
        };
        crate::photogrammetry::detect_preprocessed(&image, preprocessing, parameters)
            .map_err(|error| super::detect::preprocess_error(error, path, &files))?
    };
    write_stderr_line(
        stderr,
        &format!(
            "{}: {} marks detected (camera {k})",
            path.display(),
            found.len()
        ),
    )?;
    Ok(found)
}

/// One `--plane CONTROL:IMAGE1,IMAGE2,...`: the control file and the images.
fn parse_plane(value: &str) -> Result<(PathBuf, Vec<PathBuf>), CliError> {
    let bad = |reason: &str| {
        flag(
            "--plane",
            format!("{value:?}: {reason}; give CONTROL_FILE:IMAGE_CAM1,IMAGE_CAM2,... (one image per camera, in camera order)"),
        )
    };
    let Some((control, images)) = value.rsplit_once(':') else {
        return Err(bad("no ':' between the control file and the images"));
    };
    let images: Vec<PathBuf> = images
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(PathBuf::from)
        .collect();
    if control.trim().is_empty() || images.is_empty() {
        return Err(bad("a control file and at least one image are needed"));
    }
    Ok((PathBuf::from(control), images))
}

/// How the marks of `--image` and `--plane` images are detected: the
/// detection flags as marks need them, and each camera's background and
/// mask.
fn mark_detection(
    args: &CalibrateArgs,
    calibration: &Path,
    cameras: usize,
) -> Result<
    (
        crate::photogrammetry::DetectionParameters,
        Vec<crate::photogrammetry::Preprocessing>,
    ),
    CliError,
> {
    let parameters = calibrate::mark_detection_parameters(&args.detection.parameters())?;
    let preprocessing = super::detect::read_camera_preprocessing(
        calibration,
        cameras,
        &args.backgrounds,
        &args.masks,
        None,
    )?;
    Ok((parameters, preprocessing))
}

/// `ptv calibrate --plane ... --plane ...`: the plate at several known
/// positions in one adjustment
/// ([`crate::photogrammetry::calibrate::planes`]).
fn run_planes(
    args: &CalibrateArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let Some(calibration) = &args.calibration else {
        return Err(flag("--plane", "give --calibration with the setup"));
    };
    let formats::calibration::Setup {
        cameras: setup,
        unknown,
    } = formats::calibration::setup_from_json(
        &formats::read_text(calibration)?,
        &calibration.display().to_string(),
    )?;
    let options = CalibrationOptions {
        unknown,
        ..options(args)?
    };
    let planes = args
        .plane
        .iter()
        .map(|value| parse_plane(value))
        .collect::<Result<Vec<_>, _>>()?;
    // Before reading any image: the counts, and the targets.
    let mut controls = Vec::with_capacity(planes.len());
    for (k, (control_path, images)) in planes.iter().enumerate() {
        if images.len() != setup.len() {
            return Err(calibrate::CalibrationError::PlaneCameraCount {
                plane: k + 1,
                cameras: setup.len(),
                given: images.len(),
            }
            .into());
        }
        controls.push(control::parse_control_points(
            &formats::read_text(control_path)?,
            &control_path.display().to_string(),
        )?);
    }
    let (parameters, preprocessing) = mark_detection(args, calibration, setup.len())?;
    let mut plates = Vec::with_capacity(planes.len());
    for ((_, images), control) in planes.iter().zip(controls) {
        let mut marks = Vec::with_capacity(images.len());
        for (k, path) in images.iter().enumerate() {
            marks.push(detect_in_image(
                args,
                k,
                path,
                &preprocessing[k],
                &parameters,
                stderr,
            )?);
        }
        plates.push(calibrate::PlaneMarks { control, marks });
    }
    let result = calibrate::calibrate_planes_from_marks(&setup, &plates, &options)?;
    let cameras = result.camera_models()?;
    formats::write_text(&args.output, &formats::calibration::to_json(&cameras))?;
    write_stdout(stdout, &control::report_to_json(&result.report))
}

/// `ptv calibrate --experiment DIR`: the experiment's cameras calibrated
/// from its own calibration images with its own settings
/// ([`crate::formats::experiment::calibration_settings`]), written as
/// calibration.json, OpenPTV's camN.ori/camN.addpar and report.json in
/// `--output`; the report also goes to standard output.
fn run_experiment(
    args: &CalibrateArgs,
    dir: &Path,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    use crate::formats::experiment::{self, LocalFiles};
    let exp = experiment::read_experiment(dir)?;
    let settings = experiment::read_calibration_settings(&LocalFiles, dir, exp.cameras.len())?;
    let setup: Vec<_> = exp.cameras.iter().map(|c| c.parameters().clone()).collect();
    // examine.Combine_Flag 1: OpenPTV's multi-plane calibration from the
    // planes' identified points, read (and checked) before anything runs.
    let planes = if settings.planes.is_empty() {
        None
    } else {
        Some(settings.read_planes(&LocalFiles)?)
    };
    let result = if let Some(planes) = planes {
        print_unmapped(&settings, stderr)?;
        write_stderr_line(
            stderr,
            &format!(
                "multi-plane calibration (examine.Combine_Flag 1): {} planes from {}",
                planes.len(),
                settings.planes_source.display()
            ),
        )?;
        let fix: Vec<String> = settings.fixed.iter().map(|p| p.name().to_owned()).collect();
        calibrate::calibrate_planes(&setup, &planes, &options_with(args, &fix)?)?
    } else {
        calibrate_experiment_images(args, &settings, &setup, stderr)?
    };
    write_experiment_calibration(args, &result)?;
    write_stdout(stdout, &control::report_to_json(&result.report))
}

/// The experiment's cameras calibrated from `cal_ori`'s image per camera:
/// detect_plate's detection, man_ori's points as the start.
fn calibrate_experiment_images(
    args: &CalibrateArgs,
    settings: &crate::formats::experiment::CalibrationSettings,
    setup: &[crate::photogrammetry::CameraParameters],
    stderr: &mut dyn Write,
) -> Result<calibrate::RigCalibration, CliError> {
    let control_points = control::parse_control_points(
        &formats::read_text(&settings.control)?,
        &settings.control.display().to_string(),
    )?;
    let references = settings.references(&control_points)?;
    let fix: Vec<String> = settings.fixed.iter().map(|p| p.name().to_owned()).collect();
    let options = options_with(args, &fix)?;
    print_unmapped(settings, stderr)?;
    let counts: Vec<usize> = references.iter().map(Vec::len).collect();
    calibrate::check_mark_inputs(setup, &control_points, &counts, &options)?;
    let mut marks = Vec::with_capacity(setup.len());
    for (k, path) in settings.images.iter().enumerate() {
        let image = formats::image::read_image(path, None)?;
        let parameters = calibrate::mark_detection_parameters(&settings.detection[k])?;
        let found =
            calibrate::detect_marks(&image, &parameters).map_err(|error| CliError::Flag {
                flag: "--experiment",
                reason: format!("{}: {error}", path.display()),
            })?;
        write_stderr_line(
            stderr,
            &format!(
                "{}: {} marks detected (camera {k}, detect_plate threshold {})",
                path.display(),
                found.len(),
                parameters.threshold
            ),
        )?;
        marks.push(found);
    }
    Ok(calibrate::calibrate_from_marks(
        setup,
        &control_points,
        &marks,
        &references,
        &options,
    )?)
}

/// The experiment's settings not used, and why, on stderr.
fn print_unmapped(
    settings: &crate::formats::experiment::CalibrationSettings,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    for setting in &settings.unmapped {
        write_stderr_line(stderr, &format!("not used: {setting}"))?;
    }
    Ok(())
}

/// calibration.json, camN.ori/camN.addpar and report.json in `--output`.
fn write_experiment_calibration(
    args: &CalibrateArgs,
    result: &calibrate::RigCalibration,
) -> Result<(), CliError> {
    let cameras = result.camera_models()?;
    std::fs::create_dir_all(&args.output).map_err(|reason| formats::FormatError::Io {
        path: args.output.clone(),
        reason,
    })?;
    formats::write_text(
        &args.output.join("calibration.json"),
        &formats::calibration::to_json(&cameras),
    )?;
    for (k, camera) in cameras.iter().enumerate() {
        let name = format!("cam{}", k + 1);
        formats::write_text(
            &args.output.join(format!("{name}.ori")),
            &formats::openptv::format_ori(camera),
        )?;
        formats::write_text(
            &args.output.join(format!("{name}.addpar")),
            &formats::openptv::format_addpar(&camera.parameters().distortion),
        )?;
    }
    formats::write_text(
        &args.output.join("report.json"),
        &control::report_to_json(&result.report),
    )?;
    Ok(())
}
