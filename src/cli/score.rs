//! `ptv score`: a particle table scored against the simulator's truth by
//! the LPT challenge's rule ([`crate::photogrammetry::score`]): the 1-voxel
//! test, recall, ghost fraction, position RMS in voxels, mm and
//! reprojected px; and the seeding density the images show: the true
//! particles per pixel of the volume's footprint in each camera (`ppp`,
//! the mean over the cameras, and `ppp_per_camera`), which is the density
//! to quote (over the sensor's whole area it understates the density
//! wherever the volume does not fill the view). Any table with `x,y,z`
//! columns can be scored (`ptv reconstruct`'s, `ptv match`'s, `ptv
//! process`'s), against any table with `x,y,z` (`ptv simulate`'s
//! `truth.csv` or a sequence's `truth.FFFFF.csv`). The scores go to standard output as JSON.

use std::io::Write;
use std::path::PathBuf;

use clap::Args;
use nalgebra::{Point3, Vector3};
use serde_json::json;

use super::match_targets::parse_volume;
use super::{read_calibration, write_stdout, CliError};
use crate::formats;
use crate::photogrammetry::score::{particles_per_pixel, score_particles, voxel};
use crate::photogrammetry::Volume;

/// Arguments of `ptv score`.
#[derive(Debug, Args)]
pub struct ScoreArgs {
    /// The calibration JSON: its first camera's sensor sets the voxel, and
    /// every camera reprojects the position errors.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// The true particles: a CSV with columns x,y,z (mm), e.g. `ptv
    /// simulate`'s truth.csv.
    #[arg(long, value_name = "CSV")]
    pub truth: PathBuf,
    /// The particles to score: a CSV with columns x,y,z (mm).
    #[arg(long, value_name = "CSV")]
    pub particles: PathBuf,
    /// The observation volume (mm) as xmin,xmax,ymin,ymax,zmin,zmax (the
    /// one `ptv simulate` reports) [default: the true particles' bounding
    /// box]
    #[arg(
        long,
        value_name = "XMIN,XMAX,YMIN,YMAX,ZMIN,ZMAX",
        allow_hyphen_values = true
    )]
    pub volume: Option<String>,
}

/// Scores the particles and writes the scores to standard output.
pub(super) fn run(args: &ScoreArgs, stdout: &mut dyn Write) -> Result<(), CliError> {
    let cameras = read_calibration(&args.calibration)?;
    let read = |path: &PathBuf| {
        formats::csv::parse_points(&formats::read_text(path)?, &path.display().to_string())
    };
    let truth = read(&args.truth)?;
    let particles = read(&args.particles)?;
    let volume = match &args.volume {
        Some(text) => parse_volume(text)?,
        None => bounding_box(&truth).ok_or_else(|| CliError::Flag {
            flag: "--volume",
            reason: format!(
                "{} holds fewer than two distinct finite particles to take the volume from; \
                 give the volume (xmin,xmax,ymin,ymax,zmin,zmax, mm)",
                args.truth.display()
            ),
        })?,
    };
    let sensor = cameras[0].sensor();
    let voxel = voxel(&volume, sensor.width, sensor.height).ok_or_else(|| CliError::Flag {
        flag: "--volume",
        reason: "the voxel is the volume's size over the sensor's: give a bounded volume \
                 (no inf)"
            .to_owned(),
    })?;
    let s = score_particles(&truth, &particles, voxel, &cameras);
    let ppp = particles_per_pixel(truth.len(), &volume, &cameras);
    let known: Vec<f64> = ppp.iter().flatten().copied().collect();
    let mean_ppp = (!known.is_empty()).then(|| known.iter().sum::<f64>() / known.len() as f64);
    let report = json!({
        "ppp": mean_ppp,
        "ppp_per_camera": ppp,
        "voxel_mm": [s.voxel.x, s.voxel.y, s.voxel.z],
        "truth": s.truth,
        "reconstructed": s.reconstructed,
        "found": s.found,
        "ghosts": s.ghosts,
        "duplicates": s.duplicates,
        "recall": s.recall,
        "ghost_fraction": s.ghost_fraction,
        "rms_voxels": s.rms_voxels,
        "rms_mm": s.rms_mm,
        "rms_px": s.rms_px,
    });
    write_stdout(
        stdout,
        &(serde_json::to_string_pretty(&report).expect("plain data serialises") + "\n"),
    )
}

/// The bounding box of the finite points; `None` if it is empty along an
/// axis.
fn bounding_box(points: &[Point3<f64>]) -> Option<Volume> {
    let finite = points.iter().filter(|p| p.iter().all(|v| v.is_finite()));
    let (mut min, mut max) = (
        Vector3::repeat(f64::INFINITY),
        Vector3::repeat(f64::NEG_INFINITY),
    );
    for p in finite {
        min = min.inf(&p.coords);
        max = max.sup(&p.coords);
    }
    (0..3).all(|i| min[i] < max[i]).then(|| Volume {
        min: Point3::from(min),
        max: Point3::from(max),
    })
}
