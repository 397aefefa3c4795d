//! `ptv project`: the images of 3D points in every camera.
//!
//! Each point goes through [`Camera::project`], the collinearity equations
//! (Eq. 1-2) with the multimedia module (Eq. 6-12), distortion and affine
//! terms (Eq. 3, 5). The result is an observations table that `ptv
//! intersect` reads back.

use std::io::Write;

use nalgebra::Point3;

use super::{read_calibration, write_stderr_line, write_stdout, CliError, ProjectArgs};
use crate::formats::{self, csv::ObservedPoint};
use crate::photogrammetry::{Camera, Observation};

/// Projects the points file through the calibration: the observations table
/// to standard output, one warning line if some images do not exist.
pub(super) fn run(
    args: &ProjectArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = read_calibration(&args.calibration)?;
    let source = args.points.display().to_string();
    let points = formats::csv::parse_points(&formats::read_text(&args.points)?, &source)?;
    let (observed, missing) = project_points(&cameras, &points);
    if missing > 0 {
        write_stderr_line(
            stderr,
            &format!(
                "warning: {missing} of {} point images do not exist (the point lies behind the \
                 camera or its ray cannot pass the wall) and have no row in the output",
                points.len() * cameras.len()
            ),
        )?;
    }
    write_stdout(stdout, &formats::csv::format_observations(&observed))
}

/// The images of every point in every camera, the points numbered by their
/// index; and how many (point, camera) pairs have no image.
fn project_points(cameras: &[Camera], points: &[Point3<f64>]) -> (Vec<ObservedPoint>, usize) {
    let mut missing = 0;
    let observed = points
        .iter()
        .zip(0u64..)
        .map(|(point, id)| {
            let observations = cameras
                .iter()
                .enumerate()
                .filter_map(|(camera, model)| match model.project(point) {
                    Ok(pixel) => Some(Observation { camera, pixel }),
                    Err(_) => {
                        missing += 1;
                        None
                    }
                })
                .collect();
            ObservedPoint {
                point: id,
                observations,
            }
        })
        .collect();
    (observed, missing)
}
