//! `ptv detect`: the targets of one camera image, by
//! [`crate::photogrammetry::detect()`] (section 6.1: high-pass filter,
//! threshold, splitting of overlapping particles, grey value weighted
//! centroids).
//!
//! The flags mirror [`DetectionParameters`]' fields (`--min-pixels` is
//! `min_pixels`), and their defaults are its defaults. Targets go to
//! standard output as CSV `x,y,n,nx,ny,sumg` or as an OpenPTV `_targets`
//! file, in pixels with the top-left pixel's centre at (0.5, 0.5).

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::builder::TypedValueParser as _;
use clap::{Args, ValueEnum};

use super::{write_stderr_line, write_stdout, CliError};
use crate::formats::{self, image::RawLayout};
use crate::photogrammetry::{
    detect_preprocessed, detect_within, BitDepth, Centroid, DetectError, DetectionParameters,
    GreyImage, Mask, PreprocessError, Preprocessing, Target,
};

/// How `ptv detect` writes its targets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum TargetFormat {
    /// CSV with the header `x,y,n,nx,ny,sumg`.
    Csv,
    /// OpenPTV's `_targets`: the count, then `pnr x y n nx ny sumg tnr` per line.
    Openptv,
}

/// Arguments of `ptv detect`.
#[derive(Debug, Args)]
pub struct DetectArgs {
    /// The camera image: greyscale PNG or TIFF (8 or 16 bits, TIFF also
    /// LZW-compressed), or raw samples with --width, --height and --bits.
    #[arg(long, value_name = "FILE")]
    pub image: PathBuf,
    /// How to find the targets.
    #[command(flatten)]
    pub detection: DetectionFlags,
    /// An image of the view without particles (same size and bit depth),
    /// subtracted from the image before the high-pass filter.
    #[arg(long, value_name = "FILE")]
    pub background: Option<PathBuf>,
    /// An image of the pixels to use (same size): non-zero = use, zero =
    /// never part of a target.
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// Output format.
    #[arg(long, value_enum, default_value_t = TargetFormat::Csv)]
    pub format: TargetFormat,
    /// Stop with an error once more than N targets are found, as the frame
    /// pipeline does at its camera's bound (a hostile image then costs the
    /// detection's scratch and N targets, not a target per two pixels); by
    /// default no limit.
    #[arg(long, value_name = "N")]
    pub max_targets: Option<usize>,
    /// The layout of raw images.
    #[command(flatten)]
    pub raw: RawImageFlags,
}

/// The detection flags, shared by `ptv detect` and `ptv process`; they
/// mirror [`DetectionParameters`]' fields.
#[derive(Debug, Args)]
pub struct DetectionFlags {
    /// Grey threshold, in the image's own grey levels: a pixel belongs to a
    /// particle if its high-pass filtered value is larger [default: 10, meant
    /// for 8-bit images]
    #[arg(long, value_name = "T")]
    pub threshold: Option<u16>,
    /// Radius (px) of the window whose mean the high-pass filter subtracts;
    /// 0 turns the filter off.
    #[arg(long, value_name = "R", default_value_t = DetectionParameters::default().highpass_radius)]
    pub highpass_radius: u32,
    /// Fewest pixels of a target.
    #[arg(long, value_name = "N", default_value_t = DetectionParameters::default().min_pixels)]
    pub min_pixels: u32,
    /// Most pixels of a target.
    #[arg(long, value_name = "N", default_value_t = DetectionParameters::default().max_pixels)]
    pub max_pixels: u32,
    /// Smallest sum of grey values of a target.
    #[arg(long, value_name = "S", default_value_t = DetectionParameters::default().min_sumg)]
    pub min_sumg: u64,
    /// How far (grey levels) the fainter of two touching particles' maxima
    /// must rise above the saddle between them to be split off (OpenPTV's
    /// `discont`). Without it, the automatic rule: the rise must exceed a
    /// fifth of the maximum's height above the threshold and 3 times the
    /// image's noise level (25 times in a frame whose particle images have
    /// structure of their own, rings or streaks: one whose splits are far
    /// more than chance overlaps explain), and the maximum's pixels above
    /// the saddle must hold a volume above it of more than 4 times the
    /// noise of their sum. Either way, as in OpenPTV, pixels that touch
    /// only at a corner are not joined.
    #[arg(long, value_name = "D")]
    pub split_depth: Option<u16>,
    /// Smallest signal-to-noise ratio of a target: its sum of grey over its
    /// n pixels must be at least K times the image's noise level (after the
    /// high-pass filter, estimated on each image) times sqrt(n); 0 turns
    /// the test off (OpenPTV has none: use --min-sumg).
    #[arg(long, value_name = "K", default_value_t = DetectionParameters::default().min_snr)]
    pub min_snr: u16,
    /// Do not split blobs of overlapping particles: one target per blob.
    #[arg(long)]
    pub no_split: bool,
    /// How a target's position is estimated: `weighted`, the grey value
    /// weighted centroid (OpenPTV's), or `gaussian`, a 3-point Gaussian fit
    /// per axis around the brightest pixel (the weighted centroid on an
    /// axis where it does not apply).
    #[arg(long, value_name = "METHOD", value_enum, default_value_t = CentroidFlag::Weighted)]
    pub centroid: CentroidFlag,
}

/// `--centroid`'s values, as [`Centroid`]'s.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum CentroidFlag {
    /// The grey value weighted centroid.
    Weighted,
    /// The 3-point Gaussian fit per axis.
    Gaussian,
}

impl From<CentroidFlag> for Centroid {
    fn from(flag: CentroidFlag) -> Centroid {
        match flag {
            CentroidFlag::Weighted => Centroid::Weighted,
            CentroidFlag::Gaussian => Centroid::Gaussian,
        }
    }
}

/// The layout of raw images, which have no header to say it; shared by
/// `ptv detect` and `ptv process`.
#[derive(Debug, Args)]
pub struct RawImageFlags {
    /// Width (px) of a raw image.
    #[arg(long, value_name = "W", requires_all = ["height", "bits"])]
    pub width: Option<u32>,
    /// Height (px) of a raw image.
    #[arg(long, value_name = "H", requires_all = ["width", "bits"])]
    pub height: Option<u32>,
    /// Bits per sample of a raw image: 8, or 16 (little-endian).
    #[arg(
        long,
        value_name = "B",
        requires_all = ["width", "height"],
        value_parser = clap::builder::PossibleValuesParser::new(["8", "16"])
            .map(|bits| if bits == "8" { BitDepth::Eight } else { BitDepth::Sixteen }),
    )]
    pub bits: Option<BitDepth>,
}

impl DetectionFlags {
    /// The parameters the flags give (not yet validated).
    pub(super) fn parameters(&self) -> DetectionParameters {
        let defaults = DetectionParameters::default();
        DetectionParameters {
            threshold: self.threshold.unwrap_or(defaults.threshold),
            highpass_radius: self.highpass_radius,
            min_pixels: self.min_pixels,
            max_pixels: self.max_pixels,
            min_sumg: self.min_sumg,
            split: !self.no_split,
            split_depth: self.split_depth,
            centroid: self.centroid.into(),
            min_snr: self.min_snr,
            ..defaults
        }
    }

    /// Warns when a 16-bit image is searched with the default threshold,
    /// which is meant for 8-bit images.
    pub(super) fn warn_if_threshold_unsuited(
        &self,
        image: &GreyImage,
        path: &Path,
        stderr: &mut dyn Write,
    ) -> Result<(), CliError> {
        if image.bit_depth() == BitDepth::Sixteen && self.threshold.is_none() {
            write_stderr_line(
                stderr,
                &format!(
                    "warning: {} is a 16-bit image but no --threshold was given; the default ({}) \
                     is meant for 8-bit images, give one in this image's grey levels",
                    path.display(),
                    DetectionParameters::default().threshold
                ),
            )?;
        }
        Ok(())
    }
}

impl RawImageFlags {
    /// The raw layout, if the flags give one.
    pub(super) fn layout(&self) -> Option<RawLayout> {
        Some(RawLayout {
            width: self.width?,
            height: self.height?,
            bit_depth: self.bits?,
        })
    }
}

/// Detects the targets of the image and writes them to standard output.
pub(super) fn run(
    args: &DetectArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let parameters = args.detection.parameters();
    parameters.validate()?;
    let image = formats::image::read_image(&args.image, args.raw.layout().as_ref())?;
    args.detection
        .warn_if_threshold_unsuited(&image, &args.image, stderr)?;
    let preprocessing = read_preprocessing(
        args.background.as_deref(),
        args.mask.as_deref(),
        args.raw.layout().as_ref(),
    )?;
    let preprocess_error = |error| preprocess_error(error, &args.image, &preprocessing_files(args));
    let targets = match args.max_targets {
        None => {
            detect_preprocessed(&image, &preprocessing, &parameters).map_err(preprocess_error)?
        }
        Some(limit) => detect_within(&image, &preprocessing, &parameters, limit).map_err(
            |error| match error {
                DetectError::Preprocess(error) => preprocess_error(error),
                DetectError::TooManyTargets(error) => CliError::Flag {
                    flag: "--max-targets",
                    reason: format!("{}: {error}", args.image.display()),
                },
            },
        )?,
    };
    match args.format {
        TargetFormat::Csv => write_csv(stdout, &targets),
        TargetFormat::Openptv => write_stdout(stdout, &formats::openptv::format_targets(&targets)),
    }
}

/// The most targets [`write_csv`] formats at once: 65,536 (a few MiB of
/// text).
const CSV_CHUNK: usize = 1 << 16;

/// Writes the targets as CSV (the header once), [`CSV_CHUNK`] targets at a
/// time: the text of a frame's targets never exists whole (that of a
/// hostile 8192x8192 frame's 33.5 million would take 12 bytes a pixel).
fn write_csv(stdout: &mut dyn Write, targets: &[Target]) -> Result<(), CliError> {
    let mut chunks = targets.chunks(CSV_CHUNK);
    write_stdout(
        stdout,
        &formats::csv::format_targets(chunks.next().unwrap_or_default()),
    )?;
    for chunk in chunks {
        let text = formats::csv::format_targets(chunk);
        // Past the header's line.
        let rows = text.find('\n').map_or("", |end| &text[end + 1..]);
        write_stdout(stdout, rows)?;
    }
    Ok(())
}

/// The background and mask files of one camera, if given.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct PreprocessingFiles<'a> {
    /// --background.
    pub background: Option<&'a Path>,
    /// --mask.
    pub mask: Option<&'a Path>,
}

fn preprocessing_files(args: &DetectArgs) -> PreprocessingFiles<'_> {
    PreprocessingFiles {
        background: args.background.as_deref(),
        mask: args.mask.as_deref(),
    }
}

/// Reads a camera's background and mask (raw files in `layout`, as its
/// images).
pub(super) fn read_preprocessing(
    background: Option<&Path>,
    mask: Option<&Path>,
    layout: Option<&RawLayout>,
) -> Result<Preprocessing, CliError> {
    let background = background
        .map(|path| formats::image::read_image(path, layout))
        .transpose()?;
    let mask = mask
        .map(|path| formats::image::read_image(path, layout).map(|image| Mask::from_image(&image)))
        .transpose()?;
    Ok(Preprocessing { background, mask })
}

/// Reads the backgrounds and masks of several cameras (`--background` and
/// `--mask` given once per camera, in camera order, or not at all).
pub(super) fn read_camera_preprocessing(
    calibration: &Path,
    cameras: usize,
    backgrounds: &[PathBuf],
    masks: &[PathBuf],
    layout: Option<&RawLayout>,
) -> Result<Vec<Preprocessing>, CliError> {
    for (files, flag, what) in [
        (backgrounds, "--background", "background"),
        (masks, "--mask", "mask"),
    ] {
        if !files.is_empty() {
            super::check_camera_count(calibration, cameras, files.len(), (flag, what))?;
        }
    }
    (0..cameras)
        .map(|camera| {
            read_preprocessing(
                backgrounds.get(camera).map(PathBuf::as_path),
                masks.get(camera).map(PathBuf::as_path),
                layout,
            )
        })
        .collect()
}

/// A background or mask that does not fit `image`, by its flag and file.
pub(super) fn preprocess_error(
    error: PreprocessError,
    image: &Path,
    files: &PreprocessingFiles<'_>,
) -> CliError {
    let (flag, file) = match error {
        PreprocessError::MaskSize { .. } => ("--mask", files.mask),
        _ => ("--background", files.background),
    };
    CliError::Flag {
        flag,
        reason: format!(
            "{} does not fit {}: {error}",
            file.map_or_else(|| "the file".to_owned(), |f| f.display().to_string()),
            image.display()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_written_in_chunks_is_the_whole_table() {
        // More targets than two chunks, and none at all.
        for count in [0, 2 * CSV_CHUNK + 3] {
            let targets: Vec<Target> = (0..count)
                .map(|i| Target {
                    x: i as f64 + 0.25,
                    y: (i / 7) as f64 + 0.5,
                    n: (i % 9) as u32 + 1,
                    nx: 2,
                    ny: 3,
                    sumg: i as u64,
                })
                .collect();
            let mut out = Vec::new();
            write_csv(&mut out, &targets).unwrap();
            assert_eq!(
                String::from_utf8(out).unwrap(),
                formats::csv::format_targets(&targets)
            );
        }
    }
}
