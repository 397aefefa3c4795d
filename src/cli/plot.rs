//! `ptv plot`: the service's pictures ([`crate::plot`]) from files, offline.
//! The format comes from the output file's extension, `.png` or `.svg`.
//!
//! - `residuals`: a calibration's residuals in one camera, from the
//!   calibration JSON (the sensor) and `ptv calibrate`'s report.
//! - `disparity`: a self-calibration's disparity maps, from `ptv
//!   selfcalibrate`'s report.
//! - `overlay`: one camera's image (or a black sensor without `--image`)
//!   with its targets (`ptv detect`'s CSV or an OpenPTV `_targets` file)
//!   and, with `--particles` (`ptv match`'s CSV, whose `tC` columns say
//!   which targets are used), the particles' reprojections.
//! - `particles`: a particles CSV in three views.
//! - `trajectories`: `ptv track`'s CSV in three views, coloured by speed.

use std::path::{Path, PathBuf};

use clap::{Args, Subcommand};

use super::{read_calibration_with_splitter, CliError};
use crate::formats;
use crate::plot::disparity::{disparity_plot, DisparityMaps};
use crate::plot::overlay::{overlay_plot, Overlay};
use crate::plot::residuals::{residual_plot, ResidualReport};
use crate::plot::views::{particles_plot, trajectories_plot, ParticlePoint, TrajectoryPoint};
use crate::plot::{PlotError, PlotFormat};

/// The `plot` subcommands.
#[derive(Debug, Subcommand)]
pub enum PlotCommand {
    /// A calibration's residual vectors over one camera's sensor, a
    /// histogram of their lengths, and the check points' errors.
    Residuals(ResidualsArgs),
    /// A self-calibration's disparity maps, before and after.
    Disparity(DisparityArgs),
    /// One camera's image with its targets (unmatched ones in magenta) and
    /// the particles' reprojections, coloured by how many cameras saw them.
    Overlay(OverlayArgs),
    /// A frame's particles in three orthographic views (XY, XZ, YZ).
    Particles(ParticlesArgs),
    /// Trajectories in three orthographic views, coloured by speed.
    Trajectories(TrajectoriesArgs),
}

/// Where to write the picture.
#[derive(Debug, Args)]
pub struct Output {
    /// The picture: PNG or SVG by its extension (.png, .svg).
    #[arg(short, long, value_name = "PICTURE")]
    pub output: PathBuf,
}

/// Arguments of `ptv plot residuals`.
#[derive(Debug, Args)]
pub struct ResidualsArgs {
    /// The calibration JSON (the cameras' sensors).
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// `ptv calibrate`'s report (JSON).
    #[arg(long, value_name = "REPORT_JSON")]
    pub report: PathBuf,
    /// The camera, from 0.
    #[arg(long, default_value_t = 0)]
    pub camera: usize,
    /// Where to write it.
    #[command(flatten)]
    pub output: Output,
}

/// Arguments of `ptv plot disparity`.
#[derive(Debug, Args)]
pub struct DisparityArgs {
    /// `ptv selfcalibrate`'s report (JSON).
    #[arg(long, value_name = "REPORT_JSON")]
    pub report: PathBuf,
    /// Where to write it.
    #[command(flatten)]
    pub output: Output,
}

/// Arguments of `ptv plot overlay`.
#[derive(Debug, Args)]
pub struct OverlayArgs {
    /// The calibration JSON.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// The camera, from 0.
    #[arg(long, default_value_t = 0)]
    pub camera: usize,
    /// The camera's targets: CSV (`ptv detect`) or an OpenPTV _targets file.
    #[arg(long, value_name = "TARGETS")]
    pub targets: PathBuf,
    /// The camera's image (PNG or TIFF, grey; with a splitter, the whole
    /// sensor's image) [default: a black sensor]
    #[arg(long, value_name = "IMAGE")]
    pub image: Option<PathBuf>,
    /// The frame's particles (`ptv match`'s CSV): reprojected, and their
    /// `tC` columns mark the targets used.
    #[arg(long, value_name = "PARTICLES_CSV")]
    pub particles: Option<PathBuf>,
    /// Where to write it.
    #[command(flatten)]
    pub output: Output,
}

/// Arguments of `ptv plot particles`.
#[derive(Debug, Args)]
pub struct ParticlesArgs {
    /// A particles CSV (`ptv match`, `ptv process`): x,y,z and t0,t1,...
    #[arg(long, value_name = "PARTICLES_CSV")]
    pub particles: PathBuf,
    /// Where to write it.
    #[command(flatten)]
    pub output: Output,
}

/// Arguments of `ptv plot trajectories`.
#[derive(Debug, Args)]
pub struct TrajectoriesArgs {
    /// `ptv track`'s CSV (trajectory,frame,x,y,z,u,v,w,...).
    #[arg(long, value_name = "TRAJECTORIES_CSV")]
    pub trajectories: PathBuf,
    /// Where to write it.
    #[command(flatten)]
    pub output: Output,
}

fn name(path: &Path) -> String {
    path.display().to_string()
}

/// A camera of the calibration, or an error naming `--camera`.
fn camera_flag(camera: usize, cameras: usize, calibration: &Path) -> Result<(), CliError> {
    if camera < cameras {
        Ok(())
    } else {
        Err(CliError::Flag {
            flag: "--camera",
            reason: format!(
                "{} has cameras 0 to {}, not {camera}",
                calibration.display(),
                cameras.saturating_sub(1)
            ),
        })
    }
}

/// Runs a `plot` subcommand.
pub(super) fn run(command: &PlotCommand) -> Result<(), CliError> {
    let (output, bytes) = match command {
        PlotCommand::Residuals(args) => {
            let format = PlotFormat::from_path(&args.output.output)?;
            let (cameras, _) = read_calibration_with_splitter(&args.calibration)?;
            camera_flag(args.camera, cameras.len(), &args.calibration)?;
            let report =
                ResidualReport::from_json(&formats::read_text(&args.report)?, &name(&args.report))?;
            let sensor = cameras[args.camera].sensor();
            let bytes =
                match residual_plot(&report, args.camera, (sensor.width, sensor.height), format) {
                    Err(PlotError::Camera { camera, cameras }) => {
                        return Err(CliError::Flag {
                            flag: "--camera",
                            reason: format!(
                                "{} has cameras 0 to {}, not {camera}",
                                args.report.display(),
                                cameras.saturating_sub(1)
                            ),
                        })
                    }
                    other => other?,
                };
            (&args.output.output, bytes)
        }
        PlotCommand::Disparity(args) => {
            let format = PlotFormat::from_path(&args.output.output)?;
            let maps =
                DisparityMaps::from_json(&formats::read_text(&args.report)?, &name(&args.report))?;
            (&args.output.output, disparity_plot(&maps, format)?)
        }
        PlotCommand::Overlay(args) => (&args.output.output, overlay(args)?),
        PlotCommand::Particles(args) => {
            let format = PlotFormat::from_path(&args.output.output)?;
            let rows = formats::csv::parse_particles(
                &formats::read_text(&args.particles)?,
                &name(&args.particles),
            )?;
            let points: Vec<ParticlePoint> = rows
                .iter()
                .map(|p| ParticlePoint {
                    position: p.position,
                    cameras: p.targets.iter().flatten().count(),
                })
                .collect();
            let title = args
                .particles
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
            (
                &args.output.output,
                particles_plot(&title, &points, format)?,
            )
        }
        PlotCommand::Trajectories(args) => {
            let format = PlotFormat::from_path(&args.output.output)?;
            let rows = formats::csv::parse_trajectories(
                &formats::read_text(&args.trajectories)?,
                &name(&args.trajectories),
            )?;
            // Points by trajectory, in frame order.
            let mut rows = rows;
            rows.sort_by_key(|p| (p.trajectory, p.frame));
            let mut trajectories: Vec<Vec<TrajectoryPoint>> = Vec::new();
            let mut current = None;
            for p in rows {
                if current != Some(p.trajectory) {
                    current = Some(p.trajectory);
                    trajectories.push(Vec::new());
                }
                if let Some(t) = trajectories.last_mut() {
                    t.push(TrajectoryPoint {
                        frame: i64::try_from(p.frame).unwrap_or(i64::MAX),
                        position: p.position,
                        velocity: p.velocity,
                    });
                }
            }
            let title = args
                .trajectories
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
            (
                &args.output.output,
                trajectories_plot(&title, "", &trajectories, format)?,
            )
        }
    };
    Ok(formats::write_file(output, &bytes)?)
}

fn overlay(args: &OverlayArgs) -> Result<Vec<u8>, CliError> {
    let format = PlotFormat::from_path(&args.output.output)?;
    let (cameras, splitter) = read_calibration_with_splitter(&args.calibration)?;
    camera_flag(args.camera, cameras.len(), &args.calibration)?;
    let camera = &cameras[args.camera];
    let targets =
        formats::parse_targets(&formats::read_text(&args.targets)?, &name(&args.targets))?;
    let particles = match &args.particles {
        Some(path) => formats::csv::parse_particles(&formats::read_text(path)?, &name(path))?,
        None => Vec::new(),
    };
    let image = match &args.image {
        None => None,
        Some(path) => {
            let image = formats::image::read_image(path, None)?;
            let image = match splitter {
                None => image,
                Some(splitter) => splitter
                    .split(&image)
                    .map_err(|source| CliError::Splitter {
                        image: path.clone(),
                        source,
                    })?
                    .into_iter()
                    .nth(args.camera)
                    .ok_or_else(|| CliError::Flag {
                        flag: "--camera",
                        reason: format!(
                            "the splitter of {} has no view {}",
                            args.calibration.display(),
                            args.camera
                        ),
                    })?,
            };
            image
                .check_sensor(camera.sensor())
                .map_err(|source| CliError::ImageSize {
                    image: path.clone(),
                    camera: args.camera,
                    calibration: args.calibration.clone(),
                    source,
                })?;
            Some(image)
        }
    };
    let mut overlay = Overlay::new(
        camera,
        args.camera,
        &targets,
        particles.iter().map(|p| (p.position, p.targets.as_slice())),
        image.as_ref(),
    );
    overlay.title = format!(
        "Camera {} ({}): {}",
        args.camera,
        camera.name(),
        args.image
            .as_deref()
            .or(Some(args.targets.as_path()))
            .and_then(Path::file_name)
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
    );
    Ok(overlay_plot(&overlay, format)?)
}
