//! `ptv match`: the particles of one frame from the targets of every camera,
//! by [`Matcher`]: correspondences by epipolar geometry through the walls
//! (design paper, section 6.2) and least-squares intersection (section 4.3).
//!
//! Target files come in camera order, each a CSV table or an OpenPTV
//! `_targets` file ([`formats::parse_targets`] tells them apart). The
//! particles go to standard output as the CSV
//! `x,y,z,sx,sy,sz,rms_px,cameras,t0,t1,...`, where `tC` is the index of the
//! particle's target in camera C's file (its `pnr` in a `_targets` file),
//! -1 where that camera has none.

use std::io::Write;
use std::path::PathBuf;

use clap::Args;
use nalgebra::Point3;

use super::{check_camera_count, read_calibration, write_stdout, CliError};
use crate::formats::{self, FormatError};
use crate::photogrammetry::correspond::{Matcher, MatchingParameters, DEFAULT_TOLERANCE_PX};
use crate::photogrammetry::Volume;

/// Arguments of `ptv match`.
#[derive(Debug, Args)]
pub struct MatchArgs {
    /// The calibration JSON.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// The targets of one camera, pixels: a CSV with a header naming at
    /// least x,y (as `ptv detect` writes), or an OpenPTV _targets file.
    /// Give the flag once per camera, in camera order.
    #[arg(long = "targets", value_name = "TARGETS", required = true)]
    pub targets: Vec<PathBuf>,
    /// How to match.
    #[command(flatten)]
    pub matching: MatchingFlags,
}

/// The matching flags, shared by `ptv match` and `ptv process`; they mirror
/// [`MatchingParameters`]' fields.
#[derive(Debug, Args)]
pub struct MatchingFlags {
    /// Half-width (px) of the epipolar band, and the largest reprojection
    /// residual (px) of an accepted particle.
    #[arg(
        long,
        value_name = "PX",
        default_value_t = DEFAULT_TOLERANCE_PX,
        allow_negative_numbers = true
    )]
    pub tolerance: f64,
    /// The observation volume (mm) where particles are sought, as
    /// xmin,xmax,ymin,ymax,zmin,zmax; inf and -inf leave an axis unbounded
    /// (OpenPTV bounds only the depth) [default: a cube around the point
    /// all cameras look at, as large as the narrowest field of view there]
    #[arg(
        long,
        value_name = "XMIN,XMAX,YMIN,YMAX,ZMIN,ZMAX",
        allow_hyphen_values = true
    )]
    pub volume: Option<String>,
    /// The fewest cameras that must see a particle (2 up to the number of
    /// cameras).
    #[arg(long, value_name = "K", default_value_t = 2)]
    pub min_cameras: usize,
}

impl MatchingFlags {
    /// The parameters the flags give; the volume is parsed here, the rest is
    /// validated by [`Matcher::new`].
    pub(super) fn parameters(&self) -> Result<MatchingParameters, CliError> {
        Ok(MatchingParameters {
            tolerance: self.tolerance,
            volume: self.volume.as_deref().map(parse_volume).transpose()?,
            min_cameras: self.min_cameras,
            ..MatchingParameters::default()
        })
    }
}

/// The bounds in the order `--volume` takes them.
const VOLUME_BOUNDS: [&str; 6] = ["xmin", "xmax", "ymin", "ymax", "zmin", "zmax"];

/// Parses `xmin,xmax,ymin,ymax,zmin,zmax`: six numbers (`inf`, `-inf`
/// allowed), each minimum below its maximum.
pub(super) fn parse_volume(text: &str) -> Result<Volume, CliError> {
    let error = |reason: String| CliError::Flag {
        flag: "--volume",
        reason,
    };
    let fields: Vec<&str> = text.split(',').map(str::trim).collect();
    if fields.len() != VOLUME_BOUNDS.len() {
        return Err(error(format!(
            "expected 6 numbers xmin,xmax,ymin,ymax,zmin,zmax (mm), got {} in `{text}`",
            fields.len()
        )));
    }
    let mut bounds = [0.0; 6];
    for ((bound, field), name) in bounds.iter_mut().zip(&fields).zip(VOLUME_BOUNDS) {
        *bound = field
            .parse::<f64>()
            .ok()
            .filter(|v| !v.is_nan())
            .ok_or_else(|| {
                error(format!(
                    "{name} is `{field}`, not a number; give mm, or inf / -inf for no bound"
                ))
            })?;
    }
    for axis in 0..3 {
        let (min, max) = (bounds[2 * axis], bounds[2 * axis + 1]);
        if min >= max {
            return Err(error(format!(
                "{} ({min}) must be below {} ({max})",
                VOLUME_BOUNDS[2 * axis],
                VOLUME_BOUNDS[2 * axis + 1]
            )));
        }
    }
    Ok(Volume {
        min: Point3::new(bounds[0], bounds[2], bounds[4]),
        max: Point3::new(bounds[1], bounds[3], bounds[5]),
    })
}

/// Matches the target files and writes the particles to standard output.
pub(super) fn run(args: &MatchArgs, stdout: &mut dyn Write) -> Result<(), CliError> {
    let cameras = read_calibration(&args.calibration)?;
    check_camera_count(
        &args.calibration,
        cameras.len(),
        args.targets.len(),
        ("--targets", "target file"),
    )?;
    let matcher = Matcher::new(&cameras, &args.matching.parameters()?)?;
    let targets = args
        .targets
        .iter()
        .map(|path| formats::parse_targets(&formats::read_text(path)?, &path.display().to_string()))
        .collect::<Result<Vec<_>, FormatError>>()?;
    let particles = matcher.match_frame(&targets)?;
    write_stdout(
        stdout,
        &formats::csv::format_particles(&particles, cameras.len()),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn volume_error(text: &str) -> String {
        parse_volume(text).unwrap_err().to_string()
    }

    #[test]
    fn volumes_with_and_without_bounds() {
        assert_eq!(
            parse_volume("-40,40, -40 ,40,-20,20.5").unwrap(),
            Volume {
                min: Point3::new(-40.0, -40.0, -20.0),
                max: Point3::new(40.0, 40.0, 20.5),
            }
        );
        let open = parse_volume("-inf,inf,-inf,inf,-20,20").unwrap();
        assert_eq!(open.min.x, f64::NEG_INFINITY);
        assert_eq!(open.max.y, f64::INFINITY);
    }

    #[test]
    fn malformed_volumes_are_named() {
        for (text, expected) in [
            (
                "1,2,3",
                "--volume: expected 6 numbers xmin,xmax,ymin,ymax,zmin,zmax (mm), got 3",
            ),
            ("1,2,3,4,5,6,7", "got 7"),
            ("0,1,a,4,5,6", "--volume: ymin is `a`, not a number"),
            ("0,1,2,3,NaN,6", "zmin is `NaN`"),
            ("0,1,2,3,4,", "zmax is ``"),
            ("5,1,2,3,4,6", "--volume: xmin (5) must be below xmax (1)"),
            ("0,1,2,3,4,4", "zmin (4) must be below zmax (4)"),
            ("0,1,inf,inf,4,5", "ymin (inf) must be below ymax (inf)"),
        ] {
            let message = volume_error(text);
            assert!(message.contains(expected), "{text}: {message}");
        }
    }
}
