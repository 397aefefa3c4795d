//! `ptv calibrate`: the rig's calibration by resection on control points
//! ([`crate::photogrammetry::calibrate`]), from measured image coordinates
//! or from calibration images (detection, then identification of the marks).

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;
use nalgebra::Point2;

use super::{write_stderr_line, write_stdout, CliError, DetectionFlags};
use crate::formats::{self, control};
use crate::photogrammetry::calibrate::{
    self, CalibrationError, CalibrationOptions, CheckPoints, MarkObservation, Parameter,
};
use crate::photogrammetry::{detect, Camera};

/// Arguments of `ptv calibrate`.
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// The setup: a calibration JSON with sensor and media of every camera;
    /// its orientation values are only used for fixed parameters and, with
    /// --image and no --reference, as starting values to identify marks.
    #[arg(long, value_name = "SETUP_JSON")]
    pub calibration: PathBuf,
    /// The control points (OpenPTV calibration block: `id X Y Z` per line, mm).
    #[arg(long, value_name = "CALBLOCK")]
    pub control: PathBuf,
    /// Measured image coordinates of control points, `id x y` per line
    /// (pixels); once per camera, in camera order.
    #[arg(long, value_name = "FILE")]
    pub observations: Vec<PathBuf>,
    /// A calibration image per camera, in camera order, instead of
    /// --observations: marks are detected (allow their size with
    /// --max-pixels) and identified with the control points.
    #[arg(long, value_name = "IMAGE", conflicts_with = "observations")]
    pub image: Vec<PathBuf>,
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
    /// Where to write the calibrated calibration JSON.
    #[arg(short, long, value_name = "CALIBRATION_JSON")]
    pub output: PathBuf,
    /// Detection of the marks, with --image.
    #[command(flatten)]
    pub detection: DetectionFlags,
}

fn flag(flag: &'static str, reason: impl Into<String>) -> CliError {
    CliError::Flag {
        flag,
        reason: reason.into(),
    }
}

fn options(args: &CalibrateArgs) -> Result<CalibrationOptions, CliError> {
    let fixed = args
        .fix
        .iter()
        .filter(|name| !name.trim().is_empty())
        .map(|name| {
            Parameter::from_name(name).ok_or_else(|| {
                flag(
                    "--fix",
                    format!(
                        "unknown parameter `{name}`; the names are {}",
                        Parameter::ALL.map(Parameter::name).join(",")
                    ),
                )
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let check_points = match (&args.check_every, &args.check_ids) {
        (Some(k), _) if *k < 2 => {
            return Err(flag(
                "--check-every",
                format!("K must be at least 2, got {k}"),
            ))
        }
        (Some(k), _) => CheckPoints::Every(*k),
        (None, Some(path)) => {
            let text = formats::read_text(path)?;
            let ids = text
                .split_whitespace()
                .map(|t| {
                    t.parse::<u64>().map_err(|_| {
                        flag(
                            "--check-ids",
                            format!("{}: `{t}` is not a point id", path.display()),
                        )
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            CheckPoints::Ids(ids)
        }
        (None, None) => CheckPoints::None,
    };
    Ok(CalibrationOptions {
        fixed,
        check_points,
        max_correlation: args.max_correlation,
        ..CalibrationOptions::default()
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
    let setup = formats::calibration::parameters_from_json(
        &formats::read_text(&args.calibration)?,
        &args.calibration.display().to_string(),
    )?;
    let control_points = control::parse_control_points(
        &formats::read_text(&args.control)?,
        &args.control.display().to_string(),
    )?;
    let options = options(args)?;
    let result = if args.image.is_empty() {
        super::check_camera_count(
            &args.calibration,
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
            &args.calibration,
            setup.len(),
            args.image.len(),
            ("--image", "image"),
        )?;
        if !args.reference.is_empty() {
            super::check_camera_count(
                &args.calibration,
                setup.len(),
                args.reference.len(),
                ("--reference", "reference file"),
            )?;
        }
        let mut parameters = args.detection.parameters();
        // Marks are larger than particles: their extent is bounded only by
        // the pixel count.
        parameters.max_nx = parameters.max_nx.max(parameters.max_pixels);
        parameters.max_ny = parameters.max_ny.max(parameters.max_pixels);
        parameters.validate()?;
        let mut marks = Vec::with_capacity(args.image.len());
        for (k, path) in args.image.iter().enumerate() {
            let image = formats::image::read_image(path, None)?;
            args.detection
                .warn_if_threshold_unsuited(&image, path, stderr)?;
            let found: Vec<Point2<f64>> = detect(&image, &parameters)
                .iter()
                .map(|t| Point2::new(t.x, t.y))
                .collect();
            write_stderr_line(
                stderr,
                &format!(
                    "{}: {} marks detected (camera {k})",
                    path.display(),
                    found.len()
                ),
            )?;
            marks.push(found);
        }
        let references = if args.reference.is_empty() {
            vec![Vec::new(); setup.len()]
        } else {
            args.reference
                .iter()
                .map(|p| read_marks(p))
                .collect::<Result<Vec<_>, _>>()?
        };
        calibrate::calibrate_from_marks(&setup, &control_points, &marks, &references, &options)?
    };
    let cameras = result
        .cameras
        .iter()
        .enumerate()
        .map(|(camera, p)| {
            Camera::new(p.clone()).map_err(|source| {
                CliError::Calibrate(CalibrationError::InvalidSetup { camera, source })
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    formats::write_text(&args.output, &formats::calibration::to_json(&cameras))?;
    write_stdout(stdout, &control::report_to_json(&result.report))
}
