//! `ptv process`: the particles of one frame from the image of every camera,
//! through [`FramePipeline`]: detection (design paper, section 6.1), then
//! correspondences and intersection as in `ptv match` (sections 6.2, 4.3).
//!
//! The detection flags are `ptv detect`'s and apply to every camera; the
//! matching flags are `ptv match`'s, and so is the output. With a
//! calibration that declares a splitter (its cameras are views of one
//! sensor), one `--image` is the frame: it is cut into the views.

use std::io::Write;
use std::path::PathBuf;

use clap::Args;

use super::detect::{
    preprocess_error, read_camera_preprocessing, DetectionFlags, PreprocessingFiles, RawImageFlags,
};
use super::match_targets::MatchingFlags;
use super::{check_camera_count, read_calibration_with_splitter, write_stdout, CliError};
use crate::formats;
use crate::photogrammetry::{FrameDetection, FramePipeline, GreyImage, PipelineError};

/// Arguments of `ptv process`.
#[derive(Debug, Args)]
pub struct ProcessArgs {
    /// The calibration JSON.
    #[arg(long, value_name = "CALIBRATION_JSON")]
    pub calibration: PathBuf,
    /// The image of one camera: greyscale PNG or TIFF (8 or 16 bits), or
    /// raw samples with --width, --height and --bits. Give the flag once per
    /// camera, in camera order; once with a splitter calibration (the whole
    /// sensor's image).
    #[arg(long = "image", value_name = "FILE", required = true)]
    pub images: Vec<PathBuf>,
    /// How to find the targets.
    #[command(flatten)]
    pub detection: DetectionFlags,
    /// An image of a camera's view without particles (its images' size and
    /// bit depth), subtracted before the high-pass filter. Give it once per
    /// camera, in camera order, or not at all.
    #[arg(long = "background", value_name = "FILE")]
    pub backgrounds: Vec<PathBuf>,
    /// An image of the pixels of a camera to use (its images' size):
    /// non-zero = use. Once per camera, in camera order, or not at all.
    #[arg(long = "mask", value_name = "FILE")]
    pub masks: Vec<PathBuf>,
    /// How to match.
    #[command(flatten)]
    pub matching: MatchingFlags,
    /// The layout of raw images.
    #[command(flatten)]
    pub raw: RawImageFlags,
}

/// Processes the frame and writes the particles to standard output; a
/// warning for each 16-bit image searched with the 8-bit default threshold.
pub(super) fn run(
    args: &ProcessArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let (cameras, splitter) = read_calibration_with_splitter(&args.calibration)?;
    if let Some(splitter) = splitter {
        if args.images.len() != 1 {
            return Err(CliError::Flag {
                flag: "--image",
                reason: format!(
                    "{} declares a {} splitter: its {} cameras are views of one sensor; give \
                     --image once, the whole sensor's image, not {} images",
                    args.calibration.display(),
                    splitter.name(),
                    cameras.len(),
                    args.images.len()
                ),
            });
        }
    } else {
        check_camera_count(
            &args.calibration,
            cameras.len(),
            args.images.len(),
            ("--image", "image"),
        )?;
    }
    let detection = FrameDetection::AllCameras(args.detection.parameters());
    let layout = args.raw.layout();
    let preprocessing = read_camera_preprocessing(
        &args.calibration,
        cameras.len(),
        &args.backgrounds,
        &args.masks,
        layout.as_ref(),
    )?;
    let pipeline = FramePipeline::new(&cameras, &detection, &args.matching.parameters()?)
        .and_then(|pipeline| pipeline.with_preprocessing(preprocessing))
        .map_err(|error| cli_error(args, error))?;
    let images = args
        .images
        .iter()
        .map(|path| {
            let image = formats::image::read_image(path, layout.as_ref())?;
            args.detection
                .warn_if_threshold_unsuited(&image, path, stderr)?;
            Ok(image)
        })
        .collect::<Result<Vec<GreyImage>, CliError>>()?;
    let images = match splitter {
        Some(splitter) => splitter
            .split(&images[0])
            .map_err(|source| CliError::Splitter {
                image: args.images[0].clone(),
                source,
            })?,
        None => images,
    };
    let frame = pipeline
        .process(&images)
        .map_err(|error| cli_error(args, error))?;
    write_stdout(
        stdout,
        &formats::csv::format_particles(&frame.particles, cameras.len()),
    )
}

/// The pipeline's errors in the terms of the command line: detection and
/// matching errors as `ptv detect` and `ptv match` report them, a misfit
/// image by its file name.
fn cli_error(args: &ProcessArgs, error: PipelineError) -> CliError {
    match error {
        PipelineError::Detection { source, .. } => CliError::Detection(source),
        PipelineError::Matching(source) => CliError::Matching(source),
        PipelineError::Sensor { camera, source } => match args
            .images
            .get(camera)
            .or(args.images.first().filter(|_| args.images.len() == 1))
        {
            Some(image) => CliError::ImageSize {
                image: image.clone(),
                camera,
                calibration: args.calibration.clone(),
                source,
            },
            None => CliError::Pipeline(PipelineError::Sensor { camera, source }),
        },
        PipelineError::Preprocess { camera, source } => {
            let files = PreprocessingFiles {
                background: args.backgrounds.get(camera).map(PathBuf::as_path),
                mask: args.masks.get(camera).map(PathBuf::as_path),
            };
            match args.images.get(camera) {
                Some(image) => preprocess_error(source, image, &files),
                None => preprocess_error(source, &args.calibration, &files),
            }
        }
        other => CliError::Pipeline(other),
    }
}
