//! The `ptv` command line: offline conversions and computations on files.
//!
//! - `ptv calibration import-openptv` and `export-openptv`
//!   (`cli/calibration.rs`): between OpenPTV's `ptv.par`/`.ori`/`.addpar` and the
//!   calibration JSON.
//! - `ptv project` (`cli/project.rs`): 3D points to their images in every camera,
//!   the collinearity equations with the multimedia module (Eq. 1-12).
//! - `ptv intersect` (`cli/intersect.rs`): images back to 3D points by
//!   least-squares spatial intersection (section 4.3).
//! - `ptv detect` (`cli/detect.rs`): the targets of one camera image
//!   (section 6.1).
//!
//! Results go to standard output or a file; warnings about points left out
//! go to standard error, one line each. Reading and parsing files is
//! [`crate::formats`]'s job and the numbers are [`crate::photogrammetry`]'s:
//! this module only wires the two together. `main.rs` parses the arguments
//! and prints a [`CliError`].

mod calibration;
mod detect;
mod intersect;
mod project;

use std::io::{self, Write};
use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand};

pub use self::detect::{DetectArgs, TargetFormat};
use crate::formats::{self, FormatError};
use crate::photogrammetry::{Camera, InvalidDetectionParameters};

/// 3D particle tracking velocimetry photogrammetry.
#[derive(Debug, Parser)]
#[command(name = "ptv", version)]
pub struct Cli {
    /// What to do; without one, `ptv` prints this help.
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Convert calibrations between OpenPTV's files and the calibration JSON.
    #[command(subcommand)]
    Calibration(CalibrationCommand),
    /// Project 3D points (CSV x,y,z in mm) into every camera; writes the
    /// observations CSV point,camera,x,y (pixels) to standard output.
    Project(ProjectArgs),
    /// Intersect observations (CSV point,camera,x,y in pixels) into 3D points;
    /// writes the CSV point,x,y,z,sx,sy,sz,rms_px (mm, px) to standard output.
    Intersect(IntersectArgs),
    /// Find the particle images (targets) in one camera image; writes CSV
    /// x,y,n,nx,ny,sumg (pixels) or an OpenPTV _targets file to standard output.
    Detect(DetectArgs),
}

/// The `calibration` subcommands.
#[derive(Debug, Subcommand)]
pub enum CalibrationCommand {
    /// Read OpenPTV's ptv.par and one .ori per camera (with the .addpar beside
    /// it, if any) and write the calibration JSON.
    ImportOpenptv(ImportOpenptvArgs),
    /// Write a calibration JSON as OpenPTV's ptv.par, NAME.ori and NAME.addpar.
    ExportOpenptv(ExportOpenptvArgs),
}

/// Arguments of `ptv calibration import-openptv`.
#[derive(Debug, Args)]
pub struct ImportOpenptvArgs {
    /// OpenPTV's ptv.par: the sensor and the media shared by all cameras.
    #[arg(long, value_name = "PTV_PAR")]
    pub ptv_par: PathBuf,
    /// One .ori file per camera, in camera order.
    #[arg(value_name = "ORI", required = true)]
    pub ori: Vec<PathBuf>,
    /// Where to write the calibration JSON; standard output if not given.
    #[arg(short, long, value_name = "CALIBRATION_JSON")]
    pub output: Option<PathBuf>,
}

/// Arguments of `ptv calibration export-openptv`.
#[derive(Debug, Args)]
pub struct ExportOpenptvArgs {
    /// The calibration JSON to export.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// The directory to write into (created if missing); the files written
    /// are listed on standard error.
    #[arg(long, value_name = "DIR")]
    pub out_dir: PathBuf,
}

/// Arguments of `ptv project`.
#[derive(Debug, Args)]
pub struct ProjectArgs {
    /// The calibration JSON.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// CSV with a header containing the columns x,y,z (mm); other columns are
    /// ignored. Points are numbered by data row from 0.
    #[arg(long, value_name = "POINTS_CSV")]
    pub points: PathBuf,
}

/// Arguments of `ptv intersect`.
#[derive(Debug, Args)]
pub struct IntersectArgs {
    /// The calibration JSON.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// CSV with a header containing the columns point,camera,x,y: a point id,
    /// the 0-based camera index and the image position (pixels).
    #[arg(long, value_name = "OBSERVATIONS_CSV")]
    pub observations: PathBuf,
}

/// Why a command failed.
///
/// The `Display` of each variant says what failed; the reason is its
/// [`std::error::Error::source`], for the caller to print after a `: `.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// An input or output file is missing, unreadable or malformed.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The calibration does not fit OpenPTV's files, or they could not be written.
    #[error("cannot export {} as OpenPTV files", calibration.display())]
    Export {
        /// The calibration JSON given.
        calibration: PathBuf,
        /// What went wrong.
        #[source]
        source: FormatError,
    },
    /// The detection parameters contradict each other.
    #[error("invalid detection parameters")]
    Detection(#[from] InvalidDetectionParameters),
    /// Standard output or standard error could not be written.
    #[error("cannot write to {stream}")]
    Output {
        /// `standard output` or `standard error`.
        stream: &'static str,
        /// The operating system's reason.
        #[source]
        source: io::Error,
    },
}

/// Runs one command: results to `stdout`, warnings and lists of files
/// written to `stderr`.
pub fn run(
    command: Command,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    match command {
        Command::Calibration(CalibrationCommand::ImportOpenptv(args)) => {
            calibration::import_openptv(&args, stdout)
        }
        Command::Calibration(CalibrationCommand::ExportOpenptv(args)) => {
            calibration::export_openptv(&args, stderr)
        }
        Command::Project(args) => project::run(&args, stdout, stderr),
        Command::Intersect(args) => intersect::run(&args, stdout, stderr),
        Command::Detect(args) => detect::run(&args, stdout, stderr),
    }
}

/// Reads and validates a calibration JSON file.
fn read_calibration(path: &Path) -> Result<Vec<Camera>, FormatError> {
    formats::calibration::from_json(&formats::read_text(path)?, &path.display().to_string())
}

/// Writes text to standard output.
///
/// A reader that stops early (`ptv project ... | head`) closes the pipe;
/// that ends the output quietly rather than as an error.
fn write_stdout(stdout: &mut dyn Write, text: &str) -> Result<(), CliError> {
    match stdout
        .write_all(text.as_bytes())
        .and_then(|()| stdout.flush())
    {
        Err(e) if e.kind() != io::ErrorKind::BrokenPipe => Err(CliError::Output {
            stream: "standard output",
            source: e,
        }),
        _ => Ok(()),
    }
}

/// Writes one line to standard error.
fn write_stderr_line(stderr: &mut dyn Write, line: &str) -> Result<(), CliError> {
    writeln!(stderr, "{line}").map_err(|source| CliError::Output {
        stream: "standard error",
        source,
    })
}
