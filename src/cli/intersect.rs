//! `ptv intersect`: 3D points from their images, by the least-squares
//! spatial intersection of [`crate::photogrammetry::intersect()`] (section 4.3).

use std::io::Write;

use super::{read_calibration, write_stderr_line, write_stdout, CliError, IntersectArgs};
use crate::formats;
use crate::photogrammetry::intersect;

/// Intersects every point of the observations file: the intersections table
/// to standard output, one warning line per point left out.
pub(super) fn run(
    args: &IntersectArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = read_calibration(&args.calibration)?;
    let source = args.observations.display().to_string();
    let text = formats::read_text(&args.observations)?;
    let observed = formats::csv::parse_observations(&text, &source, cameras.len())?;
    let mut intersected = Vec::with_capacity(observed.len());
    for point in observed {
        match intersect(&cameras, &point.observations) {
            Ok(intersection) => intersected.push((point.point, intersection)),
            Err(reason) => write_stderr_line(
                stderr,
                &format!("warning: point {} skipped: {reason}", point.point),
            )?,
        }
    }
    write_stdout(stdout, &formats::csv::format_intersections(&intersected))
}
