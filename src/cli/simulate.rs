//! `ptv simulate`: a synthetic experiment for `ptv match` and `ptv process`,
//! with its ground truth, from [`crate::photogrammetry::simulate`].
//!
//! Into the output directory (created if missing):
//!
//! - `calibration.json`: the rig of [`RigSpec::convergent`], 2..8 cameras on
//!   one side of a glass-walled water tank, 1280x1024 sensors.
//! - per camera `camN_targets.csv` (N from 1, the cameras' names): the exact
//!   image of every particle plus Gaussian noise of `--noise` px per
//!   coordinate, a fraction `--drop` of them lost, in random order
//!   ([`simulate::target_frame`]).
//! - per camera `camN.png`: the 8-bit image of every particle, rendered at
//!   its exact position as a spot of `--diameter` px on a sloping background
//!   with photon and read noise ([`simulate::render_frame`]); `--noise` and
//!   `--drop` do not apply to it.
//! - `truth.csv`: `particle,x,y,z,t0,t1,...`, every particle (mm) and per
//!   camera C the index of its target in the C-th targets file (the data
//!   row, from 0), -1 where it was lost.
//!
//! With `--frames N --flow burgers|taylor-green|shear`, a sequence instead
//! (frames 0 to N-1): the particles move through the analytic flow
//! ([`simulate::flow`]; `--displacement` its speed scale in mm per frame),
//! particles that leave the volume are replaced by new ones (new ids)
//! entering with the flow, and per frame F (five digits, `%05d`):
//!
//! - `camN_targets.FFFFF.csv`: the targets as above, drawn anew each frame
//!   (`ptv track --targets DIR/cam1_targets.%05d.csv ...` reads them);
//! - `camN.FFFFF.png`: the rendered images, unless `--no-images`;
//! - `truth.FFFFF.csv`: `id,x,y,z,u,v,w,ax,ay,az,t0,t1,...`, every particle
//!   in the volume at that frame: its id (the same particle keeps it over
//!   the frames), position (mm), true velocity (mm per frame) and material
//!   acceleration (mm per frame²), and per camera its target's row as in
//!   `truth.csv`.
//!
//! A progress bar shows on standard error when it is a terminal.
//!
//! The files written and the volume the particles fill (to pass as
//! `--volume`) are listed on standard error, for a sequence with the
//! flow's largest speed (to pass as `--max-velocity`), its RMS and the
//! mean particle spacing. The same arguments always give the same files.

use std::fmt::Write as _;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

use clap::{Args, ValueEnum};
use nalgebra::Point3;

use super::{write_stderr_line, CliError};
use crate::formats::{self, FormatError};
use crate::photogrammetry::simulate::{
    self, Flow, FlowKind, RenderSpec, RigSpec, Seeding, TracerState,
};
use crate::photogrammetry::{Camera, GreyImage};

/// The most particles `ptv simulate` draws: about 0.15 particles per pixel
/// of a 1280x1024 sensor, far denser than any matcher resolves.
const MAX_PARTICLES: usize = 200_000;

/// The largest particle image diameter (px).
const MAX_DIAMETER_PX: f64 = 50.0;

/// The most frames of a sequence: their numbers fit the file names' five
/// digits.
const MAX_FRAMES: u64 = 100_000;

/// The flow of a simulated sequence.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FlowArg {
    /// A Burgers vortex along z through the volume's centre (particles
    /// enter at the sides, leave through the z faces).
    Burgers,
    /// The 3D Taylor-Green vortex, decaying over 33 turnover times (no
    /// particle leaves).
    TaylorGreen,
    /// Uniform shear along x, u = gamma (y - centre) (particles enter and
    /// leave through the x faces).
    Shear,
}

impl From<FlowArg> for FlowKind {
    fn from(flow: FlowArg) -> FlowKind {
        match flow {
            FlowArg::Burgers => FlowKind::Burgers,
            FlowArg::TaylorGreen => FlowKind::TaylorGreen,
            FlowArg::Shear => FlowKind::Shear,
        }
    }
}

/// Arguments of `ptv simulate`.
#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Number of cameras, 2 to 8.
    #[arg(long, value_name = "N")]
    pub cameras: usize,
    /// Number of particles, drawn uniformly in the volume (at most 200000).
    #[arg(long, value_name = "COUNT", required_unless_present = "wand")]
    pub particles: Option<usize>,
    /// The directory to write into (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Standard deviation (px) of the Gaussian noise added to each target
    /// coordinate in the targets files.
    #[arg(
        long,
        value_name = "PX",
        default_value_t = 0.1,
        allow_negative_numbers = true
    )]
    pub noise: f64,
    /// Seed of the random numbers: the same seed gives the same files.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// Fraction (0..1) of particle images lost from the targets files, as
    /// overlaps and faint particles lose them from a detector's.
    #[arg(
        long,
        value_name = "FRACTION",
        default_value_t = 0.0,
        allow_negative_numbers = true
    )]
    pub drop: f64,
    /// Particle image diameter (px) in the rendered images (e^-2 diameter of
    /// the Gaussian spot).
    #[arg(
        long,
        value_name = "PX",
        default_value_t = 2.5,
        allow_negative_numbers = true
    )]
    pub diameter: f64,
    /// Simulate a sequence of N frames (0 to N-1, at most 100000) of
    /// particles moving with --flow, instead of one frame.
    #[arg(long, value_name = "N", requires = "flow")]
    pub frames: Option<u64>,
    /// The flow that moves the particles of a sequence.
    #[arg(long, value_enum, requires = "frames")]
    pub flow: Option<FlowArg>,
    /// The flow's speed scale (mm per frame): the largest swirl of the
    /// Burgers vortex, the largest speed of the Taylor-Green vortex, the
    /// shear's speed at the y faces; at most a quarter of the volume's
    /// shortest side [default: half the mean particle spacing].
    #[arg(
        long,
        value_name = "MM_PER_FRAME",
        requires = "frames",
        allow_negative_numbers = true
    )]
    pub displacement: Option<f64>,
    /// Write no rendered images (targets, truth and calibration only).
    #[arg(long)]
    pub no_images: bool,
    /// Simulate a wand calibration instead: a wand with two marks MM apart
    /// at --wand-positions positions, one per frame, on a rig with lens
    /// distortion, and a plate calibration's marks (see `ptv simulate`'s
    /// module documentation).
    #[arg(long, value_name = "MM", conflicts_with_all = ["particles", "frames", "flow"])]
    pub wand: Option<f64>,
    /// The wand's positions (frames), with --wand.
    #[arg(long, value_name = "N", default_value_t = 1000, requires = "wand")]
    pub wand_positions: usize,
    /// The fraction of wand frames with one mark of one camera displaced by
    /// 5-20 px (a gross error), with --wand.
    #[arg(
        long,
        value_name = "FRACTION",
        default_value_t = 0.0,
        requires = "wand"
    )]
    pub wand_gross: f64,
}

impl SimulateArgs {
    /// Checks the ranges clap does not.
    fn validate(&self) -> Result<(), CliError> {
        let checks = [
            (
                "--cameras",
                (2..=8).contains(&self.cameras),
                format!("the simulated rig has 2 to 8 cameras, got {}", self.cameras),
            ),
            (
                "--particles",
                self.particles.unwrap_or(0) <= MAX_PARTICLES,
                format!(
                    "at most {MAX_PARTICLES}, got {}",
                    self.particles.unwrap_or(0)
                ),
            ),
            (
                "--noise",
                self.noise.is_finite() && self.noise >= 0.0,
                format!(
                    "expected a standard deviation of 0 or more pixels, got {}",
                    self.noise
                ),
            ),
            (
                "--drop",
                (0.0..=1.0).contains(&self.drop),
                format!("expected a fraction from 0 to 1, got {}", self.drop),
            ),
            (
                "--diameter",
                self.diameter > 0.0 && self.diameter <= MAX_DIAMETER_PX,
                format!(
                    "expected more than 0 and at most {MAX_DIAMETER_PX} pixels, got {}",
                    self.diameter
                ),
            ),
            (
                "--frames",
                !matches!(self.frames, Some(n) if !(1..=MAX_FRAMES).contains(&n)),
                format!(
                    "expected 1 to {MAX_FRAMES} frames, got {}",
                    self.frames.unwrap_or(0)
                ),
            ),
        ];
        match checks.into_iter().find(|(_, ok, _)| !ok) {
            Some((flag, _, reason)) => Err(CliError::Flag { flag, reason }),
            None => Ok(()),
        }
    }
}

/// Simulates the experiment and writes its files, listing them and the
/// volume on standard error.
pub(super) fn run(args: &SimulateArgs, stderr: &mut dyn Write) -> Result<(), CliError> {
    args.validate()?;
    if let Some(length) = args.wand {
        return super::simulate_wand::run(args, length, stderr);
    }
    let spec = RigSpec::convergent(args.cameras);
    let cameras = spec.build()?;
    if let (Some(frames), Some(flow)) = (args.frames, args.flow) {
        return run_sequence(args, frames, flow.into(), &spec, &cameras, stderr);
    }
    let mut rng = simulate::rng(args.seed);
    let points = simulate::particles(&spec.volume, args.particles.unwrap_or(0), &mut rng);
    let frame = simulate::target_frame(&cameras, &points, args.noise, args.drop, &mut rng);
    let rendered = simulate::render_frame(
        &cameras,
        &points,
        &RenderSpec::eight_bit(args.diameter),
        &mut rng,
    );

    std::fs::create_dir_all(&args.out).map_err(|reason| FormatError::Io {
        path: args.out.clone(),
        reason,
    })?;
    let mut written = Vec::new();
    let path = args.out.join("calibration.json");
    formats::write_text(&path, &formats::calibration::to_json(&cameras))?;
    written.push(path);
    for ((camera, targets), rendered) in cameras.iter().zip(&frame.targets).zip(&rendered) {
        let path = args.out.join(format!("{}_targets.csv", camera.name()));
        formats::write_text(&path, &formats::csv::format_targets(targets))?;
        written.push(path);
        if !args.no_images {
            let path = args.out.join(format!("{}.png", camera.name()));
            write_png(&path, &rendered.image)?;
            written.push(path);
        }
    }
    let path = args.out.join("truth.csv");
    formats::write_text(&path, &format_truth(&points, &frame.truth))?;
    written.push(path);

    for path in written {
        write_stderr_line(stderr, &path.display().to_string())?;
    }
    let (min, max) = (spec.volume.min, spec.volume.max);
    write_stderr_line(
        stderr,
        &format!(
            "volume: {},{},{},{},{},{} (mm; pass it as --volume to ptv match and ptv process)",
            min.x, max.x, min.y, max.y, min.z, max.z
        ),
    )
}

/// Simulates a sequence of `frames` frames in `kind` and writes its files
/// frame by frame.
fn run_sequence(
    args: &SimulateArgs,
    frames: u64,
    kind: FlowKind,
    spec: &RigSpec,
    cameras: &[Camera],
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let extent = spec.volume.max - spec.volume.min;
    let spacing =
        (extent.x * extent.y * extent.z / args.particles.unwrap_or(0).max(1) as f64).cbrt();
    let speed = match args.displacement {
        Some(speed) => speed,
        None => (0.5 * spacing).min(extent.min() / 4.0),
    };
    let flow = Flow::new(kind, &spec.volume, speed).map_err(|e| CliError::Flag {
        flag: "--displacement",
        reason: e.to_string(),
    })?;
    let max_speed = flow.speed_bound();
    let mut rng = simulate::rng(args.seed);
    let mut seeding = Seeding::new(flow, args.particles.unwrap_or(0), &mut rng);

    std::fs::create_dir_all(&args.out).map_err(|reason| FormatError::Io {
        path: args.out.clone(),
        reason,
    })?;
    let calibration = args.out.join("calibration.json");
    formats::write_text(&calibration, &formats::calibration::to_json(cameras))?;
    let bar = indicatif::ProgressBar::with_draw_target(
        Some(frames),
        if std::io::stderr().is_terminal() {
            indicatif::ProgressDrawTarget::stderr()
        } else {
            indicatif::ProgressDrawTarget::hidden()
        },
    );
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames ({per_sec}, {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let render = RenderSpec::eight_bit(args.diameter);
    let (mut speed_sq, mut samples, mut replaced) = (0.0, 0usize, 0usize);
    for frame in 0..frames {
        if frame > 0 {
            replaced += seeding.advance(&mut rng);
        }
        let states = seeding.states();
        let points = seeding.positions();
        let targets = simulate::target_frame(cameras, &points, args.noise, args.drop, &mut rng);
        for (camera, targets) in cameras.iter().zip(&targets.targets) {
            let path = args
                .out
                .join(format!("{}_targets.{frame:05}.csv", camera.name()));
            formats::write_text(&path, &formats::csv::format_targets(targets))?;
        }
        if !args.no_images {
            let rendered = simulate::render_frame(cameras, &points, &render, &mut rng);
            for (camera, rendered) in cameras.iter().zip(&rendered) {
                let path = args.out.join(format!("{}.{frame:05}.png", camera.name()));
                write_png(&path, &rendered.image)?;
            }
        }
        let path = args.out.join(format!("truth.{frame:05}.csv"));
        formats::write_text(&path, &format_sequence_truth(&states, &targets.truth))?;
        speed_sq += states
            .iter()
            .map(|s| s.velocity.norm_squared())
            .sum::<f64>();
        samples += states.len();
        bar.inc(1);
    }
    bar.finish_and_clear();

    let last = frames - 1;
    let out = args.out.display();
    let mut lines = vec![calibration.display().to_string()];
    for camera in cameras {
        let name = camera.name();
        lines.push(format!("{out}/{name}_targets.%05d.csv (frames 0..{last})"));
        if !args.no_images {
            lines.push(format!("{out}/{name}.%05d.png (frames 0..{last})"));
        }
    }
    lines.push(format!("{out}/truth.%05d.csv (frames 0..{last})"));
    let (min, max) = (spec.volume.min, spec.volume.max);
    lines.push(format!(
        "volume: {},{},{},{},{},{} (mm; pass it as --volume to ptv match and ptv track)",
        min.x, max.x, min.y, max.y, min.z, max.z
    ));
    let rms = (speed_sq / samples.max(1) as f64).sqrt();
    lines.push(format!(
        "flow: speed at most {max_speed:.4} mm per frame (pass it as --max-velocity to ptv \
         track), RMS {rms:.4} = {:.2} of the mean particle spacing {spacing:.3} mm; \
         {replaced} particles left the volume and were replaced by new ones",
        rms / spacing
    ));
    for line in lines {
        write_stderr_line(stderr, &line)?;
    }
    Ok(())
}

/// Per camera and particle, the row of its target in the camera's file,
/// from the targets' particles.
fn target_rows(particles: usize, truth: &[Vec<usize>]) -> Vec<Vec<Option<usize>>> {
    let mut target_of = vec![vec![None; particles]; truth.len()];
    for (targets, camera) in truth.iter().zip(&mut target_of) {
        for (target, &point) in targets.iter().enumerate() {
            if let Some(slot) = camera.get_mut(point) {
                *slot = Some(target);
            }
        }
    }
    target_of
}

/// Appends `,tC` for every camera C: the particle's target row, -1 for none.
fn write_target_columns(text: &mut String, target_of: &[Vec<Option<usize>>], index: usize) {
    for camera in target_of {
        match camera[index] {
            Some(target) => {
                let _ = write!(text, ",{target}");
            }
            None => text.push_str(",-1"),
        }
    }
}

/// The truth table: `particle,x,y,z,t0,...`, from the particles and, per
/// camera and target, the particle it images.
fn format_truth(points: &[Point3<f64>], truth: &[Vec<usize>]) -> String {
    let target_of = target_rows(points.len(), truth);
    let mut text = String::from("particle,x,y,z");
    for camera in 0..truth.len() {
        let _ = write!(text, ",t{camera}");
    }
    text.push('\n');
    for (index, p) in points.iter().enumerate() {
        let _ = write!(text, "{index},{:?},{:?},{:?}", p.x, p.y, p.z);
        write_target_columns(&mut text, &target_of, index);
        text.push('\n');
    }
    text
}

/// A sequence frame's truth table: `id,x,y,z,u,v,w,ax,ay,az,t0,...`.
fn format_sequence_truth(states: &[TracerState], truth: &[Vec<usize>]) -> String {
    let target_of = target_rows(states.len(), truth);
    let mut text = String::from("id,x,y,z,u,v,w,ax,ay,az");
    for camera in 0..truth.len() {
        let _ = write!(text, ",t{camera}");
    }
    text.push('\n');
    for (index, s) in states.iter().enumerate() {
        let _ = write!(text, "{}", s.id);
        for value in s
            .position
            .iter()
            .chain(s.velocity.iter())
            .chain(s.acceleration.iter())
        {
            let _ = write!(text, ",{value:?}");
        }
        write_target_columns(&mut text, &target_of, index);
        text.push('\n');
    }
    text
}

/// Writes a grey image as a PNG of its bit depth.
pub(super) fn write_png(path: &Path, image: &GreyImage) -> Result<(), FormatError> {
    let bytes = formats::image::encode_png(image, &path.display().to_string())?;
    std::fs::write(path, bytes).map_err(|reason| FormatError::Io {
        path: path.to_owned(),
        reason,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truth_lists_each_particles_targets() {
        let points = [Point3::new(1.0, 2.0, 3.0), Point3::new(-0.5, 0.0, 1e-9)];
        // Camera 0 has both, in swapped order; camera 1 lost particle 0.
        let truth = vec![vec![1, 0], vec![1]];
        assert_eq!(
            format_truth(&points, &truth),
            "particle,x,y,z,t0,t1\n0,1.0,2.0,3.0,1,-1\n1,-0.5,0.0,1e-9,0,0\n"
        );
    }

    #[test]
    fn sequence_truth_has_ids_velocities_and_accelerations() {
        use nalgebra::Vector3;
        let states = [
            TracerState {
                id: 7,
                position: Point3::new(1.0, 2.0, 3.0),
                velocity: Vector3::new(0.5, -0.25, 0.0),
                acceleration: Vector3::new(1e-3, 0.0, -2e-3),
            },
            TracerState {
                id: 12,
                position: Point3::new(-1.0, 0.0, 0.5),
                velocity: Vector3::zeros(),
                acceleration: Vector3::zeros(),
            },
        ];
        // Camera 0 sees both (swapped); camera 1 only the second.
        let truth = vec![vec![1, 0], vec![1]];
        assert_eq!(
            format_sequence_truth(&states, &truth),
            "id,x,y,z,u,v,w,ax,ay,az,t0,t1\n\
             7,1.0,2.0,3.0,0.5,-0.25,0.0,0.001,0.0,-0.002,1,-1\n\
             12,-1.0,0.0,0.5,0.0,0.0,0.0,0.0,0.0,0.0,0,0\n"
        );
    }
}
