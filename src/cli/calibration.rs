//! `ptv calibration import-openptv` and `export-openptv`: OpenPTV's files
//! to and from the calibration JSON, through [`crate::formats::openptv`].
//! `import-myptv`/`export-myptv` and `import-openlpt`/`export-openlpt`:
//! MyPTV's and OpenLPT's camera files ([`crate::formats::myptv`],
//! [`crate::formats::openlpt`]), exactly where their models carry ptv's,
//! else through the best fit ([`crate::formats::between`]), each camera's
//! conversion measured by reprojection over a grid through `--volume`.

use std::io::Write;

use nalgebra::{Point2, Point3};

use super::{
    read_calibration, write_stderr_line, write_stdout, CliError, ExportCamerasArgs,
    ExportOpenptvArgs, ImportCamerasArgs, ImportOpenptvArgs,
};
use crate::formats::{self, between, myptv, openlpt, openptv, FormatError};
use crate::photogrammetry::calibrate::Parameter;
use crate::photogrammetry::camera::PIXEL_SIZE_RANGE;
use crate::photogrammetry::{
    check_camera_name, Camera, CameraParameters, Distortion, Media, Volume,
};

/// Imports OpenPTV's files and writes the calibration JSON to the output
/// file, or to standard output.
pub(super) fn import_openptv(
    args: &ImportOpenptvArgs,
    stdout: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = openptv::import(&args.ptv_par, &args.ori)?;
    let json = formats::calibration::to_json(&cameras);
    match &args.output {
        Some(path) => Ok(formats::write_text(path, &json)?),
        None => write_stdout(stdout, &json),
    }
}

/// Exports a calibration JSON as OpenPTV's files and lists them on standard error.
pub(super) fn export_openptv(
    args: &ExportOpenptvArgs,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = read_calibration(&args.calibration)?;
    let written = openptv::export(&cameras, &args.out_dir).map_err(|source| CliError::Export {
        calibration: args.calibration.clone(),
        source,
    })?;
    for path in written {
        write_stderr_line(stderr, &path.display().to_string())?;
    }
    Ok(())
}

/// The other tools whose camera files `ptv calibration` reads and writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Tool {
    /// MyPTV's Tsai model.
    Myptv,
    /// OpenLPT's PINHOLE model.
    Openlpt,
}

impl Tool {
    fn label(self) -> &'static str {
        match self {
            Tool::Myptv => "MyPTV",
            Tool::Openlpt => "OpenLPT",
        }
    }
}

/// A camera of the other tool, as read or about to be written.
enum Theirs {
    Myptv(myptv::MyptvCamera),
    Openlpt(openlpt::OpenlptCamera),
}

impl Theirs {
    fn project(&self, point: &Point3<f64>) -> Option<Point2<f64>> {
        match self {
            Theirs::Myptv(camera) => camera.project(point),
            Theirs::Openlpt(camera) => camera.project(point),
        }
    }
}

/// The volume flag, with finite bounds (the grid fills it).
fn volume(text: &str) -> Result<Volume, CliError> {
    let volume = super::match_targets::parse_volume(text)?;
    if !(0..3).all(|i| volume.min[i].is_finite() && volume.max[i].is_finite()) {
        return Err(CliError::Flag {
            flag: "--volume",
            reason: format!("the conversion is measured over a grid through the volume, so its bounds must be finite, got `{text}`"),
        });
    }
    Ok(volume)
}

/// One line of the report: how the camera was converted and how exact.
fn report_line(name: &str, tool: Tool, how: &str, difference: &between::Difference) -> String {
    format!(
        "{name}: {how}; {}'s images and ptv's differ by at most {:.3e} px (RMS {:.3e} px) over \
         {} grid points of the volume",
        tool.label(),
        difference.max_px,
        difference.rms_px,
        difference.points
    )
}

/// Reads MyPTV's or OpenLPT's camera files, converts them (exactly, or by
/// the best fit), reports how exact on standard error, and writes the
/// calibration JSON.
pub(super) fn import_cameras(
    tool: Tool,
    args: &ImportCamerasArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let volume = volume(&args.volume)?;
    let pixel_size = args.pixel_size;
    let (low, high) = PIXEL_SIZE_RANGE;
    if !(pixel_size >= low && pixel_size <= high) {
        return Err(CliError::Flag {
            flag: "--pixel-size",
            reason: format!(
                "the pixel pitch must be in {low}..{high} mm, got {pixel_size}; give the \
                 sensor's pixel size in mm (e.g. 0.01 for 10 µm)"
            ),
        });
    }
    let mut parameters = Vec::with_capacity(args.cameras.len());
    let mut lines = Vec::new();
    for (index, path) in args.cameras.iter().enumerate() {
        let source = path.display().to_string();
        let text = formats::read_text(path)?;
        let invalid = |reason: String| FormatError::invalid(&source, "camera", reason);
        let (theirs, direct, exact) = match tool {
            Tool::Myptv => {
                let camera = myptv::parse(&text, &source)?;
                let direct = myptv::to_parameters(&camera, pixel_size);
                let exact = camera.is_pinhole();
                (Theirs::Myptv(camera), direct, exact)
            }
            Tool::Openlpt => {
                let camera = openlpt::parse(&text, &source)?;
                let name = path
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .filter(|s| check_camera_name(s).is_ok())
                    .map_or_else(|| format!("cam{}", index + 1), str::to_owned);
                let (direct, exact) =
                    openlpt::to_parameters(&camera, pixel_size, &name).map_err(invalid)?;
                (Theirs::Openlpt(camera), direct, exact)
            }
        };
        let project = |point: &Point3<f64>| theirs.project(point);
        let (camera, how) = if exact {
            (direct, "exact".to_owned())
        } else {
            let reason = match &theirs {
                Theirs::Myptv(_) => "its correction polynomial E has no counterpart in ptv's model",
                Theirs::Openlpt(_) => {
                    "its distortion (rational, or about a principal point off the sensor's centre) \
                     has no exact counterpart in ptv's model"
                }
            };
            // scx is interchangeable with c, xh, yh and the distortion.
            let fitted = between::best_fit(&direct, &project, &[Parameter::Scx], &volume)
                .map_err(invalid)?;
            (
                fitted,
                format!("best fit ({reason}; all parameters but scx adjusted)"),
            )
        };
        let model = Camera::new(camera.clone()).map_err(|e| invalid(e.to_string()))?;
        let difference = between::reprojection_difference(&model, &project, &volume);
        lines.push(report_line(&camera.name, tool, &how, &difference));
        parameters.push(camera);
    }
    let source = args
        .cameras
        .first()
        .map(|p| p.display().to_string())
        .unwrap_or_default();
    let cameras = formats::calibration::from_parameters(parameters, &source)?;
    for line in lines {
        write_stderr_line(stderr, &line)?;
    }
    let json = formats::calibration::to_json(&cameras);
    match &args.output {
        Some(path) => Ok(formats::write_text(path, &json)?),
        None => write_stdout(stdout, &json),
    }
}

/// Writes a calibration as MyPTV's or OpenLPT's camera files: exactly
/// where the model carries ptv's, else the best fit of a camera it
/// carries; reports how exact on standard error.
pub(super) fn export_cameras(
    tool: Tool,
    args: &ExportCamerasArgs,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let volume = volume(&args.volume)?;
    let cameras = read_calibration(&args.calibration)?;
    let export_error = |reason: String| CliError::Export {
        calibration: args.calibration.clone(),
        source: FormatError::invalid("calibration", "cameras", reason),
    };
    let mut files = Vec::with_capacity(cameras.len());
    let mut lines = Vec::new();
    for camera in &cameras {
        let p = camera.parameters();
        let not_carried = match tool {
            Tool::Myptv => myptv::not_carried(p),
            Tool::Openlpt => openlpt::not_carried(p),
        };
        let (carried, how) = match not_carried {
            None => (p.clone(), "exact".to_owned()),
            Some(reason) => {
                let (start, fixed) = carried_form(tool, p);
                let source = |point: &Point3<f64>| camera.project(point).ok();
                let fitted = between::best_fit(&start, &source, &fixed, &volume)
                    .map_err(|e| export_error(format!("camera {}: {e}", p.name)))?;
                let held: Vec<&str> = fixed.iter().map(|q| q.name()).collect();
                (
                    fitted,
                    format!(
                        "best fit ({} cannot carry {reason}; {} held)",
                        tool.label(),
                        held.join(",")
                    ),
                )
            }
        };
        let (theirs, name, text) = match tool {
            Tool::Myptv => {
                let theirs = myptv::from_parameters(&carried).map_err(export_error)?;
                let text = myptv::format(&theirs);
                (Theirs::Myptv(theirs), p.name.clone(), text)
            }
            Tool::Openlpt => {
                let theirs = openlpt::from_parameters(&carried).map_err(export_error)?;
                let text = openlpt::format(&theirs);
                if !theirs.is_distorted() && theirs.distortion.iter().any(|&k| k != 0.0) {
                    lines.push(format!(
                        "{}: warning: OpenLPT applies a lens's distortion only if a coefficient is \
                         above 1e-8, and none of these is; OpenLPT will project without it",
                        p.name
                    ));
                }
                (Theirs::Openlpt(theirs), format!("{}.txt", p.name), text)
            }
        };
        let difference =
            between::reprojection_difference(camera, &|point| theirs.project(point), &volume);
        lines.push(report_line(&p.name, tool, &how, &difference));
        files.push((name, text));
    }
    std::fs::create_dir_all(&args.out_dir).map_err(|reason| FormatError::Io {
        path: args.out_dir.clone(),
        reason,
    })?;
    for (name, text) in files {
        let path = args.out_dir.join(name);
        formats::write_text(&path, &text)?;
        write_stderr_line(stderr, &path.display().to_string())?;
    }
    for line in lines {
        write_stderr_line(stderr, &line)?;
    }
    Ok(())
}

/// The start of the best fit of a camera the tool's model cannot carry:
/// the camera in air, without what the model lacks, and the parameters
/// held there.
fn carried_form(tool: Tool, p: &CameraParameters) -> (CameraParameters, Vec<Parameter>) {
    let mut start = p.clone();
    start.media = Media::air();
    start.distortion.shear = 0.0;
    match tool {
        Tool::Myptv => {
            start.distortion = Distortion {
                scx: p.distortion.scx,
                ..Distortion::default()
            };
            start.sensor.pixel_size_y = start.sensor.pixel_size_x;
            let fixed = vec![
                Parameter::K1,
                Parameter::K2,
                Parameter::K3,
                Parameter::P1,
                Parameter::P2,
                Parameter::Scx,
                Parameter::She,
            ];
            (start, fixed)
        }
        Tool::Openlpt => {
            let distorted = !start.distortion.is_identity()
                && [
                    p.distortion.k1,
                    p.distortion.k2,
                    p.distortion.k3,
                    p.distortion.p1,
                    p.distortion.p2,
                ]
                .iter()
                .any(|&k| k != 0.0);
            let mut fixed = vec![Parameter::Scx, Parameter::She];
            if distorted || !p.media.is_homogeneous() {
                // The distortion about the principal point at the centre.
                start.interior.xh = 0.0;
                start.interior.yh = 0.0;
                fixed.extend([Parameter::Xh, Parameter::Yh]);
            }
            (start, fixed)
        }
    }
}
