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
//! The files written and the volume the particles fill (to pass as
//! `--volume`) are listed on standard error. The same arguments always give
//! the same files.

use std::fmt::Write as _;
use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;
use nalgebra::Point3;

use super::{write_stderr_line, CliError};
use crate::formats::{self, FormatError};
use crate::photogrammetry::simulate::{self, RenderSpec, RigSpec};
use crate::photogrammetry::GreyImage;

/// The most particles `ptv simulate` draws: about 0.15 particles per pixel
/// of a 1280x1024 sensor, far denser than any matcher resolves.
const MAX_PARTICLES: usize = 200_000;

/// The largest particle image diameter (px).
const MAX_DIAMETER_PX: f64 = 50.0;

/// Arguments of `ptv simulate`.
#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Number of cameras, 2 to 8.
    #[arg(long, value_name = "N")]
    pub cameras: usize,
    /// Number of particles, drawn uniformly in the volume (at most 200000).
    #[arg(long, value_name = "COUNT")]
    pub particles: usize,
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
                self.particles <= MAX_PARTICLES,
                format!("at most {MAX_PARTICLES}, got {}", self.particles),
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
    let spec = RigSpec::convergent(args.cameras);
    let cameras = spec.build()?;
    let mut rng = simulate::rng(args.seed);
    let points = simulate::particles(&spec.volume, args.particles, &mut rng);
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
        let path = args.out.join(format!("{}.png", camera.name()));
        write_png(&path, &rendered.image)?;
        written.push(path);
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

/// The truth table: `particle,x,y,z,t0,...`, from the particles and, per
/// camera and target, the particle it images.
fn format_truth(points: &[Point3<f64>], truth: &[Vec<usize>]) -> String {
    let mut target_of = vec![vec![None; points.len()]; truth.len()];
    for (targets, camera) in truth.iter().zip(&mut target_of) {
        for (target, &point) in targets.iter().enumerate() {
            if let Some(slot) = camera.get_mut(point) {
                *slot = Some(target);
            }
        }
    }
    let mut text = String::from("particle,x,y,z");
    for camera in 0..truth.len() {
        let _ = write!(text, ",t{camera}");
    }
    text.push('\n');
    for (index, p) in points.iter().enumerate() {
        let _ = write!(text, "{index},{:?},{:?},{:?}", p.x, p.y, p.z);
        for camera in &target_of {
            match camera[index] {
                Some(target) => {
                    let _ = write!(text, ",{target}");
                }
                None => text.push_str(",-1"),
            }
        }
        text.push('\n');
    }
    text
}

/// Writes a grey image as a PNG of its bit depth.
fn write_png(path: &Path, image: &GreyImage) -> Result<(), FormatError> {
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
}
