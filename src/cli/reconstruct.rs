//! `ptv reconstruct`: the particles of one dense frame set by iterative
//! particle reconstruction ([`crate::photogrammetry::ipr`]): the particle
//! image model estimated per camera, residual peaks matched by the
//! correspondence search, candidates shaken into the images, ghosts
//! removed, outer loops repeated.
//!
//! The particles go to standard output as the CSV
//! `x,y,z,sx,sy,sz,intensity,rms_px` (mm, grey levels above the
//! background, px); standard error gets the particle image model per camera,
//! then one progress line per outer loop.

use std::fmt::Write as _;
use std::io::Write;
use std::path::PathBuf;

use clap::Args;

use super::detect::{
    preprocess_error, read_camera_preprocessing, PreprocessingFiles, RawImageFlags,
};
use super::match_targets::parse_volume;
use super::{check_camera_count, read_calibration, write_stderr_line, write_stdout, CliError};
use crate::formats;
use crate::photogrammetry::ipr::{self, IprError, IprParameters, LoopReport, Reconstruction};
use crate::photogrammetry::GreyImage;

/// Arguments of `ptv reconstruct`.
#[derive(Debug, Args)]
pub struct ReconstructArgs {
    /// The calibration JSON.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// The image of one camera: greyscale PNG or TIFF (8 or 16 bits), or
    /// raw samples with --width, --height and --bits. Give the flag once per
    /// camera, in camera order.
    #[arg(long = "image", value_name = "FILE", required = true)]
    pub images: Vec<PathBuf>,
    /// The observation volume (mm) as xmin,xmax,ymin,ymax,zmin,zmax
    /// [default: a cube around the point all cameras look at, as large as
    /// the narrowest field of view there]
    #[arg(
        long,
        value_name = "XMIN,XMAX,YMIN,YMAX,ZMIN,ZMAX",
        allow_hyphen_values = true
    )]
    pub volume: Option<String>,
    /// An image of a camera's view without particles (its images' size and
    /// bit depth), subtracted first. Once per camera, in camera order, or
    /// not at all.
    #[arg(long = "background", value_name = "FILE")]
    pub backgrounds: Vec<PathBuf>,
    /// An image of the pixels of a camera to use (its images' size):
    /// non-zero = use. Once per camera, in camera order, or not at all.
    #[arg(long = "mask", value_name = "FILE")]
    pub masks: Vec<PathBuf>,
    /// Half-width (px) of the correspondence search's epipolar band for
    /// the candidates (an upper bound; the search narrows it to the
    /// frame's noise).
    #[arg(long, value_name = "PX", default_value_t = IprParameters::default().tolerance)]
    pub tolerance: f64,
    /// Outer loops with candidates seen in every camera.
    #[arg(long, value_name = "N", default_value_t = IprParameters::default().loops)]
    pub loops: usize,
    /// Further outer loops with candidates seen in one camera less.
    #[arg(long, value_name = "N", default_value_t = IprParameters::default().reduced_loops)]
    pub reduced_loops: usize,
    /// The layout of raw images.
    #[command(flatten)]
    pub raw: RawImageFlags,
}

/// Reconstructs the frame set and writes the particles to standard output.
pub(super) fn run(
    args: &ReconstructArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = read_calibration(&args.calibration)?;
    check_camera_count(
        &args.calibration,
        cameras.len(),
        args.images.len(),
        ("--image", "image"),
    )?;
    let layout = args.raw.layout();
    let preprocessing = read_camera_preprocessing(
        &args.calibration,
        cameras.len(),
        &args.backgrounds,
        &args.masks,
        layout.as_ref(),
    )?;
    let parameters = IprParameters {
        volume: args.volume.as_deref().map(parse_volume).transpose()?,
        tolerance: args.tolerance,
        loops: args.loops,
        reduced_loops: args.reduced_loops,
        ..IprParameters::default()
    };
    let images = args
        .images
        .iter()
        .map(|path| formats::image::read_image(path, layout.as_ref()))
        .collect::<Result<Vec<GreyImage>, _>>()?;
    let mut progress_error = None;
    let mut progress = |report: &LoopReport| {
        if progress_error.is_none() {
            progress_error = write_stderr_line(stderr, &loop_line(report)).err();
        }
    };
    let result = ipr::reconstruct(
        &cameras,
        &images,
        &preprocessing,
        &parameters,
        &mut progress,
    )
    .map_err(|error| cli_error(args, error))?;
    if let Some(error) = progress_error {
        return Err(error);
    }
    for (camera, otf) in result.otf.iter().enumerate() {
        write_stderr_line(
            stderr,
            &format!(
                "camera {camera}: particle image sigma {:.3} x {:.3} px (+-{:.3}), rho {:.3}, \
                 peak {:.1} grey, from {} isolated images",
                otf.sigma_x, otf.sigma_y, otf.sigma_error, otf.rho, otf.peak, otf.samples
            ),
        )?;
    }
    write_stdout(stdout, &format_reconstruction(&result))
}

/// One outer loop as a line of text.
fn loop_line(report: &LoopReport) -> String {
    let peaks: Vec<String> = report.peaks.iter().map(usize::to_string).collect();
    format!(
        "loop {} (seen in >= {} cameras): residual peaks {}, candidates {}, removed {}, \
         particles {}, residual RMS {:.2} grey",
        report.index,
        report.min_cameras,
        peaks.join("/"),
        report.candidates,
        report.removed,
        report.particles,
        report.residual_rms
    )
}

/// The particles as `x,y,z,sx,sy,sz,intensity,rms_px`.
fn format_reconstruction(result: &Reconstruction) -> String {
    let mut text = String::from("x,y,z,sx,sy,sz,intensity,rms_px\n");
    for p in &result.particles {
        let _ = writeln!(
            text,
            "{:?},{:?},{:?},{:?},{:?},{:?},{:?},{:?}",
            p.position.x,
            p.position.y,
            p.position.z,
            p.sigma.x,
            p.sigma.y,
            p.sigma.z,
            p.intensity,
            p.rms_px
        );
    }
    text
}

/// The reconstruction's errors in the terms of the command line: a misfit
/// image by its file, a misfit background or mask by its flag, matching
/// errors as `ptv match` reports them.
fn cli_error(args: &ReconstructArgs, error: IprError) -> CliError {
    match error {
        IprError::Sensor { camera, source } => CliError::ImageSize {
            image: args.images[camera.min(args.images.len() - 1)].clone(),
            camera,
            calibration: args.calibration.clone(),
            source,
        },
        IprError::Preprocess { camera, source } => {
            let files = PreprocessingFiles {
                background: args.backgrounds.get(camera).map(PathBuf::as_path),
                mask: args.masks.get(camera).map(PathBuf::as_path),
            };
            match args.images.get(camera) {
                Some(image) => preprocess_error(source, image, &files),
                None => preprocess_error(source, &args.calibration, &files),
            }
        }
        IprError::Matching(source) => CliError::Matching(source),
        other => CliError::Reconstruct(other),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::ipr::{Otf, ReconstructedParticle};
    use nalgebra::{Point3, Vector3};

    #[test]
    fn particles_are_written_in_the_documented_columns() {
        let result = Reconstruction {
            particles: vec![ReconstructedParticle {
                position: Point3::new(1.0, -2.5, 0.125),
                sigma: Vector3::new(0.01, 0.02, 0.03),
                intensity: 120.5,
                rms_px: 0.05,
                cameras: 4,
            }],
            otf: vec![Otf::round(0.7, 100.0)],
            loops: vec![],
        };
        assert_eq!(
            format_reconstruction(&result),
            "x,y,z,sx,sy,sz,intensity,rms_px\n1.0,-2.5,0.125,0.01,0.02,0.03,120.5,0.05\n"
        );
    }
}
