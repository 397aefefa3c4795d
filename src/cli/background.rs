//! `ptv background`: a camera's background image (the per-pixel median or
//! minimum over its frames) for subtraction before detection.
//!
//! The frames are read one at a time and handed to a
//! [`BackgroundBuilder`](crate::photogrammetry::BackgroundBuilder), which
//! keeps at most `--sample-frames` of them (median) or one image (min):
//! memory does not grow with the number of frames given. The result is
//! written as PNG, or TIFF when the output's name ends in `.tif`/`.tiff`,
//! at the frames' own bit depth.

use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};

use clap::{Args, ValueEnum};
use image::{ExtendedColorType, ImageEncoder};

use super::{write_stderr_line, CliError};
use crate::formats::{self, FormatError};
use crate::photogrammetry::background::DEFAULT_MEDIAN_SAMPLE;
use crate::photogrammetry::{BackgroundBuilder, BackgroundMode, GreyImage, GreyPixels};

/// Arguments of `ptv background`.
#[derive(Debug, Args)]
pub struct BackgroundArgs {
    /// One frame of the camera (PNG or TIFF, 8 or 16 bit); give it once per
    /// frame, all of one size and depth.
    #[arg(long = "image", value_name = "IMAGE", required = true)]
    pub images: Vec<PathBuf>,
    /// `median`: the per-pixel median of an evenly spaced sample of the
    /// frames (at most --sample-frames of them); `min`: the per-pixel
    /// minimum of every frame.
    #[arg(long, value_enum, default_value_t = ModeArg::Median)]
    pub mode: ModeArg,
    /// The most frames a median keeps in memory (an even number >= 2):
    /// with more frames given, an evenly spaced sample of them.
    #[arg(long, value_name = "K", default_value_t = DEFAULT_MEDIAN_SAMPLE)]
    pub sample_frames: usize,
    /// Where to write the background: PNG, or TIFF if the name ends in
    /// .tif or .tiff.
    #[arg(short, long, value_name = "FILE")]
    pub output: PathBuf,
}

/// `--mode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ModeArg {
    /// The per-pixel median.
    Median,
    /// The per-pixel minimum.
    Min,
}

impl From<ModeArg> for BackgroundMode {
    fn from(mode: ModeArg) -> Self {
        match mode {
            ModeArg::Median => BackgroundMode::Median,
            ModeArg::Min => BackgroundMode::Min,
        }
    }
}

/// Output formats by extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum OutputFormat {
    Png,
    Tiff,
}

fn output_format(path: &Path) -> Result<OutputFormat, CliError> {
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match extension.as_deref() {
        Some("png") => Ok(OutputFormat::Png),
        Some("tif" | "tiff") => Ok(OutputFormat::Tiff),
        _ => Err(CliError::Flag {
            flag: "--output",
            reason: format!(
                "{}: name the output .png or .tif/.tiff (the extension picks the format)",
                path.display()
            ),
        }),
    }
}

/// Runs `ptv background`: the background to `--output`, its name and the
/// frames used on standard error.
pub fn run(args: &BackgroundArgs, stderr: &mut dyn Write) -> Result<(), CliError> {
    let format = output_format(&args.output)?;
    let mode = BackgroundMode::from(args.mode);
    let progress = indicatif::ProgressBar::with_draw_target(
        Some(args.images.len() as u64),
        indicatif::ProgressDrawTarget::stderr(),
    );
    progress.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames ({per_sec}, {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut builder: Option<BackgroundBuilder> = None;
    for path in &args.images {
        let frame = formats::image::read_image(path, None)?;
        let builder = match &mut builder {
            Some(builder) => builder,
            None => builder.insert(
                BackgroundBuilder::new(mode, frame.width(), frame.height(), frame.bit_depth())
                    .with_sample_limit(args.sample_frames)
                    .map_err(|e| CliError::Flag {
                        flag: "--sample-frames",
                        reason: e.to_string(),
                    })?,
            ),
        };
        builder.add(&frame).map_err(|source| CliError::Background {
            image: path.clone(),
            source,
        })?;
        progress.inc(1);
    }
    progress.finish_and_clear();
    let Some(builder) = builder else {
        // clap requires one --image at least.
        return Err(CliError::Flag {
            flag: "--image",
            reason: "give at least one frame".into(),
        });
    };
    let (frames, kept) = (builder.frames(), builder.frames_kept());
    let background = builder.finish().map_err(|source| CliError::Background {
        image: args.images[0].clone(),
        source,
    })?;
    write_image(&args.output, &background, format)?;
    let what = match mode {
        BackgroundMode::Median => format!("median of {kept} of {frames} frames"),
        BackgroundMode::Min => format!("minimum of {frames} frames"),
    };
    write_stderr_line(stderr, &format!("{} ({what})", args.output.display()))
}

/// Writes a grey image as PNG or TIFF at its bit depth.
fn write_image(path: &Path, image: &GreyImage, format: OutputFormat) -> Result<(), CliError> {
    let (width, height) = (image.width(), image.height());
    let (samples, color): (Vec<u8>, ExtendedColorType) = match image.pixels() {
        GreyPixels::Eight(s) => (s.clone(), ExtendedColorType::L8),
        GreyPixels::Sixteen(s) => (
            s.iter().flat_map(|v| v.to_ne_bytes()).collect(),
            ExtendedColorType::L16,
        ),
    };
    let mut bytes = Cursor::new(Vec::new());
    let encoded = match format {
        OutputFormat::Png => image::codecs::png::PngEncoder::new(&mut bytes)
            .write_image(&samples, width, height, color),
        OutputFormat::Tiff => image::codecs::tiff::TiffEncoder::new(&mut bytes)
            .write_image(&samples, width, height, color),
    };
    encoded.map_err(|error| {
        FormatError::invalid(
            &path.display().to_string(),
            "image",
            format!("cannot encode the background: {error}"),
        )
    })?;
    std::fs::write(path, bytes.into_inner()).map_err(|reason| {
        CliError::Format(FormatError::Io {
            path: path.to_owned(),
            reason,
        })
    })
}
