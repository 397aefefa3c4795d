//! The `ptv` command line: offline conversions and computations on files.
//!
//! - `ptv calibration import-openptv` and `export-openptv`
//!   (`cli/calibration.rs`): between OpenPTV's `ptv.par`/`.ori`/`.addpar` and the
//!   calibration JSON; `import-myptv`/`export-myptv` and
//!   `import-openlpt`/`export-openlpt`: MyPTV's and OpenLPT's camera files,
//!   with how exact the conversion is, by reprojection.
//! - `ptv calibrate` (`cli/calibrate.rs`): the rig's calibration by
//!   resection on control points (section 5), from image coordinates or
//!   calibration images; the report as JSON.
//! - `ptv project` (`cli/project.rs`): 3D points to their images in every camera,
//!   the collinearity equations with the multimedia module (Eq. 1-12).
//! - `ptv intersect` (`cli/intersect.rs`): images back to 3D points by
//!   least-squares spatial intersection (section 4.3).
//! - `ptv detect` (`cli/detect.rs`): the targets of one camera image
//!   (section 6.1).
//! - `ptv match` (`cli/match_targets.rs`): the particles of one frame from
//!   every camera's targets (correspondences, section 6.2, and intersection).
//! - `ptv process` (`cli/process.rs`): the particles of one frame from every
//!   camera's image, through the frame pipeline (detection, then `match`).
//! - `ptv reconstruct` (`cli/reconstruct.rs`): the particles of one dense
//!   frame set by iterative particle reconstruction.
//! - `ptv score` (`cli/score.rs`): particles scored against the truth by
//!   the LPT challenge's 1-voxel rule.
//! - `ptv experiment import` (`cli/experiment.rs`): an OpenPTV/pyptv
//!   experiment as the calibration JSON and the service's sequence body.
//! - `ptv process-sequence` (`cli/process_sequence.rs`): every frame of an
//!   OpenPTV experiment, in parallel, to particles and OpenPTV's `rt_is`.
//! - `ptv background` (`cli/background.rs`): a camera's background image,
//!   the per-pixel median or minimum over its frames, streamed.
//! - `ptv plot` (`cli/plot.rs`): pictures of results as PNG or SVG, the
//!   same the service serves: residuals, disparity maps, a frame overlay,
//!   particles and trajectories in three views.
//! - `ptv upload` (`cli/upload.rs`): a recording's frames pushed to a
//!   running `ptv serve`, several at once, retried, resumable.
//! - `ptv simulate` (`cli/simulate.rs`): a synthetic experiment for the
//!   commands above: calibration, targets, images and the truth, one frame
//!   or a sequence of particles moving through an analytic flow.
//!
//! Results go to standard output or a file; warnings about points left out
//! go to standard error, one line each. Reading and parsing files is
//! [`crate::formats`]'s job and the numbers are [`crate::photogrammetry`]'s:
//! this module only wires the two together. `main.rs` parses the arguments
//! and prints a [`CliError`].

mod background;
mod calibrate;
mod calibration;
mod detect;
mod experiment;
mod export;
mod intersect;
mod match_targets;
mod plot;
mod process;
mod process_sequence;
mod project;
mod reconstruct;
mod score;
mod selfcalibrate;
mod simulate;
mod simulate_wand;
mod track;
mod upload;
mod wand;

use std::io::{self, Write};
use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand};

pub use self::background::{BackgroundArgs, ModeArg};
pub use self::calibrate::CalibrateArgs;
pub use self::detect::{DetectArgs, DetectionFlags, RawImageFlags, TargetFormat};
pub use self::experiment::{ExperimentCommand, ImportExperimentArgs};
pub use self::export::ExportFormat;
pub use self::match_targets::{MatchArgs, MatchingFlags};
pub use self::plot::PlotCommand;
pub use self::process::ProcessArgs;
pub use self::process_sequence::{BackgroundChoice, ProcessSequenceArgs};
pub use self::reconstruct::ReconstructArgs;
pub use self::score::ScoreArgs;
pub use self::selfcalibrate::SelfCalibrateArgs;
pub use self::simulate::{FlowArg, SimulateArgs};
pub use self::track::TrackArgs;
pub use self::upload::UploadArgs;
use crate::formats::{self, FormatError};
use crate::photogrammetry::camera::InvalidCamera;
use crate::photogrammetry::correspond::MatchError;
use crate::photogrammetry::{Camera, InvalidDetectionParameters, PipelineError, SensorMismatch};

/// 3D particle tracking velocimetry photogrammetry.
#[derive(Debug, Parser)]
#[command(name = "ptv", version)]
pub struct Cli {
    /// What to do; without one, `ptv` runs `ptv serve` with its defaults.
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Convert calibrations between OpenPTV's files and the calibration JSON.
    #[command(subcommand)]
    Calibration(CalibrationCommand),
    /// Calibrate every camera by resection on control points (all 16
    /// parameters through the media, no starting values needed); writes the
    /// calibration JSON to --output and the report (JSON) to standard output.
    Calibrate(CalibrateArgs),
    /// Refine a calibration from the particles of many frames (volume
    /// self-calibration): the targets of every camera per frame; writes the
    /// refined calibration JSON to --output and the report (JSON:
    /// disparities before and after, maps over sub-volumes, parameter
    /// changes, rounds, gauge) to standard output.
    Selfcalibrate(SelfCalibrateArgs),
    /// Project 3D points (CSV x,y,z in mm) into every camera; writes the
    /// observations CSV point,camera,x,y (pixels) to standard output.
    Project(ProjectArgs),
    /// Intersect observations (CSV point,camera,x,y in pixels) into 3D points;
    /// writes the CSV point,x,y,z,sx,sy,sz,rms_px (mm, px) to standard output.
    Intersect(IntersectArgs),
    /// Find the particle images (targets) in one camera image; writes CSV
    /// x,y,n,nx,ny,sumg (pixels) or an OpenPTV _targets file to standard output.
    Detect(DetectArgs),
    /// Find the particles of one frame from the targets of every camera
    /// (correspondences by epipolar geometry, then intersection); writes the
    /// CSV x,y,z,sx,sy,sz,rms_px,cameras,t0,t1,... (mm, px, target indices)
    /// to standard output.
    Match(MatchArgs),
    /// Find the particles of one frame from the image of every camera
    /// (detection, then as `ptv match`); writes the same CSV as `ptv match`.
    Process(ProcessArgs),
    /// Find the particles of one dense frame set (0.01..0.15 particles per
    /// pixel) by iterative particle reconstruction (IPR) from the image of
    /// every camera; writes the CSV x,y,z,sx,sy,sz,intensity,rms_px (mm,
    /// grey levels, px) to standard output, a line per outer loop to
    /// standard error.
    Reconstruct(ReconstructArgs),
    /// Score a particle table against the true particles (`ptv simulate`'s
    /// truth.csv) by the LPT challenge's 1-voxel rule; writes JSON (found,
    /// ghosts, recall, ghost fraction, position RMS in voxels, mm and px)
    /// to standard output.
    Score(ScoreArgs),
    /// Import an OpenPTV/pyptv experiment.
    #[command(subcommand)]
    Experiment(ExperimentCommand),
    /// Process every frame of an OpenPTV experiment (frames in parallel)
    /// with its own parameters; writes per frame particles.<frame>.csv,
    /// rt_is.<frame> and the targets, and a JSON summary to standard output.
    ProcessSequence(ProcessSequenceArgs),
    /// Link the particles of a sequence into trajectories (Malik et al.
    /// 1993), from `ptv match`'s particle files or from every camera's
    /// targets; writes the CSV
    /// trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras,t0,t1,... (mm,
    /// mm per frame, mm per frame²) to standard output.
    Track(TrackArgs),
    /// Write a synthetic experiment into a directory: calibration.json,
    /// per camera camN_targets.csv and camN.png, and truth.csv; with
    /// --frames and --flow, a sequence of particles moving through an
    /// analytic flow, per frame camN_targets.%05d.csv, camN.%05d.png and
    /// truth.%05d.csv (ids, true velocities and accelerations).
    Simulate(SimulateArgs),
    /// Draw a picture of a result as PNG or SVG (by the output's
    /// extension): a calibration's residuals, a self-calibration's
    /// disparity maps, a camera image with its targets and reprojections,
    /// particles or trajectories in three views. The service serves the
    /// same pictures.
    #[command(subcommand)]
    Plot(PlotCommand),
    /// Compute a camera's background image from its frames (the per-pixel
    /// median or minimum), streaming them one at a time; writes PNG or TIFF
    /// at the frames' bit depth.
    Background(BackgroundArgs),
    /// Push a recording's frames to a running `ptv serve`: several at once,
    /// retried on connection errors and 5xx, frames already there skipped;
    /// prints a summary and fails if any frame failed.
    Upload(UploadArgs),
    /// Run the HTTP service (the default without a subcommand); prints the
    /// address it listens on and where its API docs are.
    Serve(crate::service::ServeArgs),
    /// Run jobs from a data directory's queue without serving HTTP: any
    /// number of these next to one `ptv serve` (which may run with
    /// `--workers 0`); jobs are held by leases, so a killed worker's job
    /// goes to another within `--lease-secs`.
    Worker(crate::service::WorkerArgs),
}

/// The `calibration` subcommands.
#[derive(Debug, Subcommand)]
pub enum CalibrationCommand {
    /// Read OpenPTV's ptv.par and one .ori per camera (with the .addpar beside
    /// it, if any) and write the calibration JSON.
    ImportOpenptv(ImportOpenptvArgs),
    /// Write a calibration JSON as OpenPTV's ptv.par, NAME.ori and NAME.addpar.
    ExportOpenptv(ExportOpenptvArgs),
    /// Read MyPTV's Tsai model camera files (one per camera) and write the
    /// calibration JSON; how exact the conversion is goes to standard error.
    ImportMyptv(ImportCamerasArgs),
    /// Write a calibration JSON as MyPTV's Tsai model camera files (NAME),
    /// exactly where its model carries ptv's, else by the best fit.
    ExportMyptv(ExportCamerasArgs),
    /// Read OpenLPT's PINHOLE camera files (one per camera) and write the
    /// calibration JSON; how exact the conversion is goes to standard error.
    ImportOpenlpt(ImportCamerasArgs),
    /// Write a calibration JSON as OpenLPT's PINHOLE camera files
    /// (NAME.txt), exactly where its model carries ptv's, else by the best
    /// fit.
    ExportOpenlpt(ExportCamerasArgs),
}

/// Arguments of `ptv calibration import-myptv` and `import-openlpt`.
#[derive(Debug, Args)]
pub struct ImportCamerasArgs {
    /// The camera files, one per camera, in camera order.
    #[arg(value_name = "CAMERA_FILE", required = true)]
    pub cameras: Vec<PathBuf>,
    /// The sensor's pixel pitch (mm), which the files do not hold: ptv's
    /// principal distance c (mm) is the file's (px) times it. The images
    /// computed do not depend on it.
    #[arg(long, value_name = "MM")]
    pub pixel_size: f64,
    /// The observation volume `xmin,xmax,ymin,ymax,zmin,zmax` (mm): the
    /// conversion is measured by reprojection over a grid of 11x11x11
    /// points through it, and fitted on it where it is not exact.
    #[arg(long, value_name = "BOUNDS", allow_hyphen_values = true)]
    pub volume: String,
    /// Where to write the calibration JSON; standard output if not given.
    #[arg(short, long, value_name = "CALIBRATION_JSON")]
    pub output: Option<PathBuf>,
}

/// Arguments of `ptv calibration export-myptv` and `export-openlpt`.
#[derive(Debug, Args)]
pub struct ExportCamerasArgs {
    /// The calibration JSON to export.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// The observation volume `xmin,xmax,ymin,ymax,zmin,zmax` (mm): the
    /// conversion is measured by reprojection over a grid of 11x11x11
    /// points through it, and fitted on it where it is not exact.
    #[arg(long, value_name = "BOUNDS", allow_hyphen_values = true)]
    pub volume: String,
    /// The directory to write into (created if missing); the files written
    /// are listed on standard error.
    #[arg(long, value_name = "DIR")]
    pub out_dir: PathBuf,
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
    /// The files given are not one per camera.
    #[error(
        "{} has {cameras} cameras but {given} {what}{} given; give {flag} once per camera, \
         in camera order",
        calibration.display(),
        if *given == 1 { " was" } else { "s were" }
    )]
    CameraCount {
        /// The calibration JSON given.
        calibration: PathBuf,
        /// Its cameras.
        cameras: usize,
        /// Files given.
        given: usize,
        /// What the files are: `target file`, `image`.
        what: &'static str,
        /// The flag that names one: `--targets`, `--image`.
        flag: &'static str,
    },
    /// A flag's value is malformed or out of range.
    #[error("{flag}: {reason}")]
    Flag {
        /// The flag, `--volume`.
        flag: &'static str,
        /// What is wrong and what is expected.
        reason: String,
    },
    /// The tracking parameters are invalid, or a particle is not a
    /// position.
    #[error("cannot track")]
    Tracking(#[from] crate::photogrammetry::track::TrackError),
    /// The matching parameters are invalid, or matching failed.
    #[error("cannot match the targets")]
    Matching(#[from] MatchError),
    /// An image does not fit its camera's sensor.
    #[error("{} is not an image of camera {camera} of {}", image.display(), calibration.display())]
    ImageSize {
        /// The image file.
        image: PathBuf,
        /// The camera (0-based) it was given for.
        camera: usize,
        /// The calibration JSON given.
        calibration: PathBuf,
        /// The sizes that differ.
        #[source]
        source: SensorMismatch,
    },
    /// Iterative particle reconstruction refused the frame set.
    #[error("cannot reconstruct the particles")]
    Reconstruct(#[source] crate::photogrammetry::ipr::IprError),
    /// The frame pipeline refused the frame.
    #[error("cannot process the frame")]
    Pipeline(#[source] PipelineError),
    /// The calibration could not be done.
    #[error("cannot calibrate")]
    Calibrate(#[from] crate::photogrammetry::calibrate::CalibrationError),
    /// Self-calibration could not run.
    #[error("cannot self-calibrate")]
    SelfCalibrate(#[from] crate::photogrammetry::selfcal::SelfCalibrationError),
    /// The wand calibration could not be done.
    #[error("cannot calibrate with the wand")]
    Wand(#[from] crate::photogrammetry::selfcal::wand::WandError),
    /// The simulator built a camera that the camera model refuses.
    #[error("the simulated rig is invalid")]
    Simulation(#[from] InvalidCamera),
    /// An OpenPTV experiment that cannot be read.
    #[error(transparent)]
    Experiment(#[from] crate::formats::experiment::ExperimentError),
    /// An image the calibration's splitter does not fit.
    #[error("cannot split {} into the calibration's views", image.display())]
    Splitter {
        /// The image file.
        image: PathBuf,
        /// Why.
        #[source]
        source: crate::photogrammetry::SplitterError,
    },
    /// One frame of a sequence failed.
    #[error("frame {frame}")]
    Frame {
        /// The frame number.
        frame: u64,
        /// Why.
        #[source]
        source: Box<CliError>,
    },
    /// A frame does not fit the background being computed from the others.
    #[error("{}", image.display())]
    Background {
        /// The frame given.
        image: PathBuf,
        /// What does not fit.
        #[source]
        source: crate::photogrammetry::BackgroundError,
    },
    /// A picture that cannot be drawn (its message names the input).
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
    /// `ptv upload` could not reach the sequence, or frames failed.
    #[error("upload: {0}")]
    Upload(String),
    /// The service could not start, or stopped with an error.
    #[error("the service")]
    Service(#[from] crate::service::ServiceError),
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
        Command::Calibration(CalibrationCommand::ImportMyptv(args)) => {
            calibration::import_cameras(calibration::Tool::Myptv, &args, stdout, stderr)
        }
        Command::Calibration(CalibrationCommand::ExportMyptv(args)) => {
            calibration::export_cameras(calibration::Tool::Myptv, &args, stderr)
        }
        Command::Calibration(CalibrationCommand::ImportOpenlpt(args)) => {
            calibration::import_cameras(calibration::Tool::Openlpt, &args, stdout, stderr)
        }
        Command::Calibration(CalibrationCommand::ExportOpenlpt(args)) => {
            calibration::export_cameras(calibration::Tool::Openlpt, &args, stderr)
        }
        Command::Calibrate(args) => calibrate::run(&args, stdout, stderr),
        Command::Selfcalibrate(args) => selfcalibrate::run(&args, stdout, stderr),
        Command::Project(args) => project::run(&args, stdout, stderr),
        Command::Intersect(args) => intersect::run(&args, stdout, stderr),
        Command::Detect(args) => detect::run(&args, stdout, stderr),
        Command::Match(args) => match_targets::run(&args, stdout),
        Command::Process(args) => process::run(&args, stdout, stderr),
        Command::Reconstruct(args) => reconstruct::run(&args, stdout, stderr),
        Command::Score(args) => score::run(&args, stdout),
        Command::Experiment(ExperimentCommand::Import(args)) => experiment::import(&args, stderr),
        Command::ProcessSequence(args) => process_sequence::run(&args, stdout),
        Command::Simulate(args) => simulate::run(&args, stderr),
        Command::Track(args) => track::run(&args, stdout, stderr),
        Command::Background(args) => background::run(&args, stderr),
        Command::Plot(command) => plot::run(&command),
        Command::Upload(args) => upload::run(&args, stdout),
        Command::Serve(args) => Ok(crate::service::run(args, stdout)?),
        Command::Worker(args) => Ok(crate::service::run_worker(args)?),
    }
}

/// Reads and validates a calibration JSON file.
fn read_calibration(path: &Path) -> Result<Vec<Camera>, FormatError> {
    formats::calibration::from_json(&formats::read_text(path)?, &path.display().to_string())
}

/// Reads and validates a calibration JSON file and its splitter, if any.
fn read_calibration_with_splitter(
    path: &Path,
) -> Result<(Vec<Camera>, Option<crate::photogrammetry::Splitter>), FormatError> {
    formats::calibration::from_json_with_splitter(
        &formats::read_text(path)?,
        &path.display().to_string(),
    )
}

/// Checks that one file per camera of the calibration was given with
/// `flag`: `given` files (`what`).
fn check_camera_count(
    calibration: &Path,
    cameras: usize,
    given: usize,
    (flag, what): (&'static str, &'static str),
) -> Result<(), CliError> {
    if given == cameras {
        Ok(())
    } else {
        Err(CliError::CameraCount {
            calibration: calibration.to_owned(),
            cameras,
            given,
            what,
            flag,
        })
    }
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
