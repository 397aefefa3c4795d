//! `ptv process-sequence`: a whole OpenPTV experiment processed locally,
//! frame by frame through [`FramePipeline`] (detection, section 6.1;
//! correspondences and intersection, sections 6.2 and 4.3), with the
//! experiment's own settings as [`crate::formats::experiment`] maps them.
//!
//! It reads the OpenPTV experiment directly (the directory or pyptv YAML
//! that `ptv experiment import` takes). Frames run in parallel (rayon); a
//! progress bar with frames per second is drawn on standard error when it
//! is a terminal. Per frame it writes, into the output directory:
//! `particles.<frame>.csv` (as `ptv process` writes), `rt_is.<frame>`
//! (OpenPTV's) and `<camera>.<frame>_targets` (OpenPTV's targets, the
//! indices `rt_is` and the CSV refer to). At the end a JSON summary goes to
//! standard output: frames, targets per camera (total and per frame),
//! particles by the number of cameras that see them, and the median
//! residual.
//!
//! Before detection, per camera (per sensor image with a splitter), pyptv's
//! masking images are subtracted, as pyptv's sequence loop does
//! (`masking.mask_base_name`; clipped at 0), and, with `--background
//! median|min`, the camera's background over the processed frames
//! ([`BackgroundBuilder`], one streaming pass over the frames first). Both
//! go to the pipeline as one background per camera
//! ([`FramePipeline::with_preprocessing`]): their saturating sum, since
//! `max(max(g - m, 0) - b, 0) = max(g - (m + b), 0)`; with a splitter it is
//! built at the sensor's size and cut into the views.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use clap::{Args, ValueEnum};
use rayon::prelude::*;
use serde::Serialize;

use super::{write_stdout, CliError};
use crate::formats::experiment::{read_experiment, Experiment};
use crate::formats::frames::FrameRange;
use crate::formats::{self, FormatError};
use crate::photogrammetry::{
    BackgroundBuilder, BackgroundMode, FrameDetection, FramePipeline, GreyImage, GreyPixels,
    PipelineError, Preprocessing, SplitterError,
};

/// The background subtracted before detection.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum BackgroundChoice {
    /// The per-pixel median of the processed frames (an evenly spaced
    /// sample of at most 32).
    Median,
    /// The per-pixel minimum of the processed frames.
    Min,
    /// None.
    None,
}

/// Arguments of `ptv process-sequence`.
#[derive(Debug, Args)]
pub struct ProcessSequenceArgs {
    /// The OpenPTV experiment: a directory with parameters/ptv.par (or one
    /// parameters_*.yaml), or a pyptv YAML file.
    #[arg(long, value_name = "DIR")]
    pub experiment: PathBuf,
    /// Where to write the per-frame files (created if missing) [default:
    /// res/ in the experiment's directory, where OpenPTV writes them].
    #[arg(short, long, value_name = "OUTDIR")]
    pub output: Option<PathBuf>,
    /// The frames to process, FIRST..LAST inclusive [default: the
    /// experiment's sequence].
    #[arg(long, value_name = "FIRST..LAST", value_parser = FrameRange::parse)]
    pub frames: Option<FrameRange>,
    /// A background per camera, computed from the processed frames and
    /// subtracted before detection.
    #[arg(long, value_enum, default_value_t = BackgroundChoice::None)]
    pub background: BackgroundChoice,
    /// Then track the processed frames with the experiment's tracking
    /// settings (track.par, or the YAML's `track:`), writing
    /// `trajectories.csv` (as `ptv track` writes it) into the output
    /// directory.
    #[arg(long)]
    pub track: bool,
    /// With --track, also write OpenPTV's linkage files `ptv_is.<frame>`
    /// into the output directory, as OpenPTV's tracker does.
    #[arg(long, requires = "track")]
    pub ptv_is: bool,
    /// With --track, also export the particles and trajectories for
    /// ParaView (`vtk`: `particles.<frame>.vtp`, `trajectories.vtp` and
    /// `particles.pvd`) or as one HDF5 file (`hdf5`: `sequence.h5`), into
    /// the output directory (docs/exports.md).
    #[arg(long, value_enum, requires = "track")]
    pub export: Vec<super::export::ExportFormat>,
    /// With --track, do not extend the trajectories backwards in time
    /// after the forward pass (on by default: docs/tracking.md; backward
    /// tracking holds the sequence's particles until its end).
    #[arg(long, requires = "track", conflicts_with = "backward")]
    pub no_backward: bool,
    /// Backward tracking, the default with --track (kept for scripts that
    /// ask for it).
    #[arg(long, requires = "track", hide = true)]
    pub backward: bool,
}

/// `a + b`, saturating, pixel by pixel; `None` if the sizes or depths
/// differ.
fn saturating_sum(a: &GreyImage, b: &GreyImage) -> Option<GreyImage> {
    if (a.width(), a.height()) != (b.width(), b.height()) {
        return None;
    }
    let (w, h) = (a.width(), a.height());
    match (a.pixels(), b.pixels()) {
        (GreyPixels::Eight(a), GreyPixels::Eight(b)) => GreyImage::from_u8(
            w,
            h,
            a.iter().zip(b).map(|(a, b)| a.saturating_add(*b)).collect(),
        )
        .ok(),
        (GreyPixels::Sixteen(a), GreyPixels::Sixteen(b)) => GreyImage::from_u16(
            w,
            h,
            a.iter().zip(b).map(|(a, b)| a.saturating_add(*b)).collect(),
        )
        .ok(),
        _ => None,
    }
}

/// The sensor images' count: one with a splitter, else one per camera.
fn sensor_images(experiment: &Experiment) -> usize {
    if experiment.splitter.is_some() {
        1
    } else {
        experiment.cameras.len()
    }
}

/// What to subtract from each sensor image, if anything: the saturating sum
/// of pyptv's masking image (read and checked against the first frame) and
/// the background of `frames`.
fn subtrahends(
    experiment: &Experiment,
    frames: &[u64],
    background: BackgroundChoice,
) -> Result<Vec<Option<GreyImage>>, CliError> {
    let mode = match background {
        BackgroundChoice::Median => Some(BackgroundMode::Median),
        BackgroundChoice::Min => Some(BackgroundMode::Min),
        BackgroundChoice::None => None,
    };
    (0..sensor_images(experiment))
        .into_par_iter()
        .map(|camera| {
            let mut subtrahend = None;
            let first = experiment
                .sequence
                .image_path(&experiment.root, camera, frames[0]);
            let reference = formats::image::read_image(&first, None)?;
            if let Some(masks) = &experiment.masks {
                let path = &masks[camera.min(masks.len() - 1)];
                let mask = formats::image::read_image(path, None)?;
                if saturating_sum(&reference, &mask).is_none() {
                    return Err(CliError::Flag {
                        flag: "masking.mask_base_name",
                        reason: format!(
                            "{} is {}x{} at {} bits but the frames ({}) are {}x{} at {} bits; \
                             give masks of the images' size and depth",
                            path.display(),
                            mask.width(),
                            mask.height(),
                            mask.bit_depth().bits(),
                            first.display(),
                            reference.width(),
                            reference.height(),
                            reference.bit_depth().bits()
                        ),
                    });
                }
                subtrahend = Some(mask);
            }
            if let Some(mode) = mode {
                let mut builder = BackgroundBuilder::new(
                    mode,
                    reference.width(),
                    reference.height(),
                    reference.bit_depth(),
                );
                for &frame in frames {
                    let path = experiment
                        .sequence
                        .image_path(&experiment.root, camera, frame);
                    let image = formats::image::read_image(&path, None)?;
                    builder.add(&image).map_err(|source| CliError::Background {
                        image: path.clone(),
                        source,
                    })?;
                }
                let background = builder.finish().map_err(|source| CliError::Background {
                    image: first.clone(),
                    source,
                })?;
                subtrahend = Some(match subtrahend {
                    // Both were checked against the first frame.
                    Some(mask) => saturating_sum(&mask, &background).expect(
                        "the mask and the background have the first frame's size and depth",
                    ),
                    None => background,
                });
            }
            Ok(subtrahend)
        })
        .collect()
}

/// Per camera, its [`Preprocessing`]: the sensor image's subtrahend
/// ([`subtrahends`]) as the background, cut into the views with a splitter.
fn preprocessing(
    experiment: &Experiment,
    frames: &[u64],
    background: BackgroundChoice,
) -> Result<Vec<Preprocessing>, CliError> {
    let subtrahends = subtrahends(experiment, frames, background)?;
    let backgrounds: Vec<Option<GreyImage>> = match (experiment.splitter, subtrahends.as_slice()) {
        (Some(splitter), [Some(subtrahend)]) => {
            let first = experiment
                .sequence
                .image_path(&experiment.root, 0, frames[0]);
            splitter
                .split(subtrahend)
                .map_err(|source| CliError::Splitter {
                    image: first,
                    source,
                })?
                .into_iter()
                .map(Some)
                .collect()
        }
        (Some(_), _) => vec![None; experiment.cameras.len()],
        (None, _) => subtrahends,
    };
    Ok(backgrounds
        .into_iter()
        .map(|background| Preprocessing {
            background,
            mask: None,
        })
        .collect())
}

/// Why one frame failed (sent back from the worker threads).
#[derive(Debug)]
enum FrameFailure {
    Format(FormatError),
    Split(PathBuf, SplitterError),
    Pipeline(PipelineError, Vec<PathBuf>),
}

/// One frame's counts.
struct FrameCounts {
    targets: Vec<usize>,
    by_cameras: Vec<usize>,
    residuals: Vec<f64>,
}

/// The summary printed at the end.
#[derive(Serialize)]
struct Summary {
    frames: u64,
    first: u64,
    last: u64,
    output: String,
    cameras: Vec<String>,
    targets_per_camera: Vec<usize>,
    targets_per_camera_per_frame: Vec<f64>,
    particles: usize,
    /// Index k: particles seen by k cameras.
    particles_by_cameras: Vec<usize>,
    median_residual_px: Option<f64>,
    /// With --track: what tracking found.
    #[serde(skip_serializing_if = "Option::is_none")]
    tracking: Option<TrackingSummary>,
}

/// What backward tracking added: points before the trajectories'
/// starts, trajectories lengthened, trajectories joined to the one ending
/// before them.
#[derive(Serialize)]
struct BackwardAdded {
    points: usize,
    lengthened: usize,
    joined: usize,
}

/// The tracking part of the summary.
#[derive(Serialize)]
struct TrackingSummary {
    /// The limits used (mm per frame, mm per frame²) and where from.
    max_velocity: f64,
    max_acceleration: f64,
    max_gap: usize,
    min_length: usize,
    recovery: bool,
    trajectories: u64,
    points: usize,
    recovered_particles: usize,
    /// What backward tracking added (absent with --no-backward).
    #[serde(skip_serializing_if = "Option::is_none")]
    backward: Option<BackwardAdded>,
    output: String,
    ptv_is: bool,
    exports: Vec<String>,
}

fn process_frame(
    experiment: &Experiment,
    pipeline: &FramePipeline,
    frame: u64,
    output: &Path,
) -> Result<FrameCounts, FrameFailure> {
    let root = &experiment.root;
    let cameras = experiment.cameras.len();
    let (paths, images) = match experiment.splitter {
        Some(splitter) => {
            let path = experiment.sequence.image_path(root, 0, frame);
            let image = formats::image::read_image(&path, None).map_err(FrameFailure::Format)?;
            let views = splitter
                .split(&image)
                .map_err(|e| FrameFailure::Split(path.clone(), e))?;
            (vec![path; cameras], views)
        }
        None => {
            let paths: Vec<PathBuf> = (0..cameras)
                .map(|camera| experiment.sequence.image_path(root, camera, frame))
                .collect();
            let images = paths
                .iter()
                .map(|path| formats::image::read_image(path, None).map_err(FrameFailure::Format))
                .collect::<Result<Vec<GreyImage>, _>>()?;
            (paths, images)
        }
    };
    let result = pipeline
        .process(&images)
        .map_err(|e| FrameFailure::Pipeline(e, paths))?;
    let write = |name: String, text: &str| {
        formats::write_text(&output.join(name), text).map_err(FrameFailure::Format)
    };
    write(
        format!("particles.{frame}.csv"),
        &formats::csv::format_particles(&result.particles, cameras),
    )?;
    write(
        format!("rt_is.{frame}"),
        &formats::openptv::format_rt_is(&result.particles, cameras),
    )?;
    for (camera, targets) in experiment.cameras.iter().zip(&result.targets) {
        write(
            format!("{}.{frame}_targets", camera.name()),
            &formats::openptv::format_targets(targets),
        )?;
    }
    let mut by_cameras = vec![0; cameras + 1];
    for particle in &result.particles {
        by_cameras[particle.camera_count()] += 1;
    }
    Ok(FrameCounts {
        targets: result.targets.iter().map(Vec::len).collect(),
        by_cameras,
        residuals: result.particles.iter().map(|p| p.rms_px).collect(),
    })
}

/// Runs `ptv process-sequence`.
pub(super) fn run(args: &ProcessSequenceArgs, stdout: &mut dyn Write) -> Result<(), CliError> {
    let experiment = read_experiment(&args.experiment)?;
    if args.track && experiment.tracking.is_none() {
        return Err(CliError::Flag {
            flag: "--track",
            reason: format!(
                "the experiment {} has no tracking settings (parameters/track.par or the YAML's \
                 `track:`); add them, or track the particles with `ptv track --particles`",
                args.experiment.display()
            ),
        });
    }
    let sequence = FrameRange {
        first: experiment.sequence.first,
        last: experiment.sequence.last,
    };
    let range = args.frames.unwrap_or(sequence);
    range
        .check_within(sequence)
        .map_err(|reason| CliError::Flag {
            flag: "--frames",
            reason,
        })?;
    let FrameRange { first, last } = range;
    let output = args
        .output
        .clone()
        .unwrap_or_else(|| experiment.root.join("res"));
    std::fs::create_dir_all(&output).map_err(|reason| FormatError::Io {
        path: output.clone(),
        reason,
    })?;
    let frames: Vec<u64> = (first..=last).collect();
    let preprocessing = preprocessing(&experiment, &frames, args.background)?;
    let pipeline = FramePipeline::new(
        &experiment.cameras,
        &FrameDetection::PerCamera(experiment.detection.clone()),
        &experiment.matching,
    )
    .and_then(|pipeline| pipeline.with_preprocessing(preprocessing))
    .map_err(CliError::Pipeline)?;
    let done = AtomicU64::new(0);
    let bar = indicatif::ProgressBar::with_draw_target(
        Some(frames.len() as u64),
        indicatif::ProgressDrawTarget::stderr(),
    );
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:40} {pos}/{len} frames, {per_sec}, {elapsed} (eta {eta})",
        )
        .expect("a valid template"),
    );
    // The bar is drawn from this thread only: the frames run on another,
    // so that standard error (locked by this thread in `main`) is never
    // waited for by a worker.
    let results = std::thread::scope(|scope| {
        let worker = scope.spawn(|| {
            frames
                .par_iter()
                .map(|&frame| {
                    let result = process_frame(&experiment, &pipeline, frame, &output);
                    done.fetch_add(1, Ordering::Relaxed);
                    (frame, result)
                })
                .collect::<Vec<_>>()
        });
        while !worker.is_finished() {
            bar.set_position(done.load(Ordering::Relaxed));
            std::thread::sleep(Duration::from_millis(100));
        }
        bar.set_position(done.load(Ordering::Relaxed));
        worker.join().expect("the frames' worker does not panic")
    });
    bar.finish_and_clear();

    let cameras = experiment.cameras.len();
    let mut targets = vec![0; cameras];
    let mut by_cameras = vec![0; cameras + 1];
    let mut residuals = Vec::new();
    for (frame, result) in results {
        let counts = result.map_err(|failure| frame_error(&args.experiment, frame, failure))?;
        for (total, n) in targets.iter_mut().zip(&counts.targets) {
            *total += n;
        }
        for (total, n) in by_cameras.iter_mut().zip(&counts.by_cameras) {
            *total += n;
        }
        residuals.extend(counts.residuals);
    }
    residuals.sort_by(f64::total_cmp);
    let median = match residuals.len() {
        0 => None,
        n if n % 2 == 1 => Some(residuals[n / 2]),
        n => Some((residuals[n / 2 - 1] + residuals[n / 2]) / 2.0),
    };
    let count = frames.len() as u64;
    let summary = Summary {
        frames: count,
        first,
        last,
        output: output.display().to_string(),
        cameras: experiment
            .cameras
            .iter()
            .map(|c| c.name().to_owned())
            .collect(),
        targets_per_camera_per_frame: targets.iter().map(|&t| t as f64 / count as f64).collect(),
        targets_per_camera: targets,
        particles: by_cameras.iter().sum(),
        particles_by_cameras: by_cameras,
        median_residual_px: median,
        tracking: None,
    };
    let summary = Summary {
        tracking: if args.track {
            Some(track(args, &experiment, &output, range)?)
        } else {
            None
        },
        ..summary
    };
    write_stdout(
        stdout,
        &(serde_json::to_string_pretty(&summary).expect("plain data serialises") + "\n"),
    )
}

/// Tracks the processed frames with the experiment's settings: from the
/// particle files, or, with `flagNewParticles` (the image-space recovery),
/// from every camera's target files matched again as the pipeline matched
/// them (the recovery needs the targets the correspondences left).
fn track(
    args: &ProcessSequenceArgs,
    experiment: &Experiment,
    output: &Path,
    range: FrameRange,
) -> Result<TrackingSummary, CliError> {
    use crate::formats::frames::{FramePattern, WithoutNumber};
    use crate::photogrammetry::correspond::Matcher;
    use crate::photogrammetry::track::{ImageSpaceRecovery, Tracker};
    let settings = experiment
        .tracking
        .as_ref()
        .expect("checked before processing");
    let parameters = &settings.parameters;
    let pattern = |name: &str| {
        // `%` in the directory's own name is written `%%` for the pattern.
        let path = output.join(name).display().to_string();
        let escaped = path[..path.len() - name.len()].replace('%', "%%") + name;
        FramePattern::parse(&escaped, WithoutNumber::Refuse).map_err(|reason| CliError::Flag {
            flag: "--output",
            reason,
        })
    };
    let matcher = Matcher::new(&experiment.cameras, &experiment.matching)?;
    parameters.check_volume(matcher.volume())?;
    let (tracker, source) = if settings.recovery {
        let recovery =
            ImageSpaceRecovery::new(experiment.cameras.clone(), experiment.matching.tolerance)
                .map_err(|e| CliError::Flag {
                    flag: "criteria.eps0",
                    reason: e.to_string(),
                })?;
        let patterns = experiment
            .cameras
            .iter()
            .map(|c| pattern(&format!("{}.%d_targets", c.name())))
            .collect::<Result<Vec<_>, _>>()?;
        (
            Tracker::with_recovery(parameters.clone(), recovery)?,
            super::track::Source::targets(matcher, patterns),
        )
    } else {
        (
            Tracker::new(parameters.clone())?,
            super::track::Source::particles(pattern("particles.%d.csv")?),
        )
    };
    let tracker = if !args.no_backward {
        tracker.extending_backward()
    } else {
        tracker
    };
    let csv_path = output.join("trajectories.csv");
    let mut csv = Vec::new();
    let counts = super::track::track_source(
        parameters,
        tracker,
        &source,
        range,
        false,
        None,
        args.ptv_is.then_some(output),
        !args.export.is_empty(),
        &mut csv,
    )?;
    std::fs::write(&csv_path, &csv).map_err(|reason| FormatError::Io {
        path: csv_path.clone(),
        reason,
    })?;
    let mut exports = Vec::new();
    if let Some(collector) = &counts.export {
        for format in &args.export {
            exports.extend(collector.write(*format, output)?);
        }
    }
    Ok(TrackingSummary {
        max_velocity: parameters.max_velocity,
        max_acceleration: parameters.max_acceleration,
        max_gap: parameters.max_gap,
        min_length: parameters.min_length,
        recovery: settings.recovery,
        trajectories: counts.trajectories,
        points: counts.points,
        recovered_particles: counts.recovered,
        backward: counts.backward.map(|b| BackwardAdded {
            points: b.points,
            lengthened: b.lengthened,
            joined: b.joined,
        }),
        output: csv_path.display().to_string(),
        ptv_is: args.ptv_is,
        exports: exports.iter().map(|p| p.display().to_string()).collect(),
    })
}

fn frame_error(experiment: &Path, frame: u64, failure: FrameFailure) -> CliError {
    let source = match failure {
        FrameFailure::Format(error) => CliError::Format(error),
        FrameFailure::Split(image, source) => CliError::Splitter { image, source },
        FrameFailure::Pipeline(PipelineError::Sensor { camera, source }, paths) => {
            CliError::ImageSize {
                image: paths.get(camera).cloned().unwrap_or_default(),
                camera,
                calibration: experiment.to_owned(),
                source,
            }
        }
        FrameFailure::Pipeline(error, _) => CliError::Pipeline(error),
    };
    CliError::Frame {
        frame,
        source: Box::new(source),
    }
}
