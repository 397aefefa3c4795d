//! Files people already have, parsed into validated core values.
//!
//! - [`calibration`]: the project's calibration JSON.
//! - [`control`]: calibration inputs (control points `id X Y Z`, image
//!   coordinates `id x y`, the LPT challenge's `CalibPoints.txt`) and the
//!   calibration report.
//! - [`openptv`]: OpenPTV's `.ori`, `.addpar` and `ptv.par`.
//! - [`myptv`] and [`openlpt`]: MyPTV's and OpenLPT's camera files, and
//!   [`between`]: what conversions to them share (the axes, the best fit,
//!   how exact a conversion is by reprojection).
//! - [`experiment`]: a whole OpenPTV/pyptv experiment (the `parameters/`
//!   folder or pyptv's YAML) in `ptv`'s settings.
//! - [`csv`]: point, observation and target tables of the command line.
//! - [`image`]: camera images (greyscale PNG, TIFF, raw buffers).
//! - [`vtk`] and [`hdf5`]: exports of particles and trajectories for
//!   ParaView and for HDF5 readers (h5py, pandas).
//!
//! [`parse_targets`] reads targets in either format;
//! [`targets::TargetsReader`] reads them as their bytes arrive, with a
//! limit on their count.
//!
//! Every parser takes the text and a `source` (a file name, or a label like
//! `request body`) and returns a [`FormatError`] that names the source, the
//! line or field, and what was expected.

pub mod between;
pub mod calibration;
pub mod control;
pub mod csv;
pub mod experiment;
pub mod frames;
pub mod hdf5;
pub mod image;
mod lzw;
pub mod myptv;
pub mod openlpt;
pub mod openptv;
pub mod targets;
#[cfg(test)]
mod untrusted;
pub mod vtk;

use std::path::{Path, PathBuf};

/// What is wrong with an input file.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The file could not be read or written.
    #[error("{path}: {reason}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's reason (part of the message, not a
        /// separate cause, so that it is printed once).
        reason: std::io::Error,
    },
    /// A file that is not an image this program opens: empty, neither PNG
    /// nor TIFF, or a header that does not read (the service answers 415).
    #[error("{input}: {location}: {reason}")]
    UnsupportedImage {
        /// The file or other source.
        input: String,
        /// `file`, `format`, `PNG` or `TIFF`.
        location: String,
        /// What is wrong and what is expected.
        reason: String,
    },
    /// A value is missing, malformed or out of range.
    #[error("{input}: {location}: {reason}")]
    Invalid {
        /// The file or other source of the text.
        input: String,
        /// Where in it: `line 3`, `cameras[1].pixel_size[0]`, ...
        location: String,
        /// What is wrong and what is expected.
        reason: String,
    },
}

impl FormatError {
    pub(crate) fn invalid(
        source: &str,
        location: impl Into<String>,
        reason: impl Into<String>,
    ) -> Self {
        FormatError::Invalid {
            input: source.to_owned(),
            location: location.into(),
            reason: reason.into(),
        }
    }
}

/// Reads a targets file in either format: OpenPTV `_targets` when the first
/// non-blank line is a single integer (the count), else a CSV table with a
/// header naming at least `x,y`.
pub fn parse_targets(
    text: &str,
    source: &str,
) -> Result<Vec<crate::photogrammetry::Target>, FormatError> {
    let first = text
        .lines()
        .find(|line| !line.trim().is_empty())
        .unwrap_or("");
    if first.trim().parse::<u64>().is_ok() {
        openptv::parse_targets(text, source)
    } else {
        csv::parse_targets(text, source)
    }
}

/// Reads a whole text file, naming it in the error.
pub fn read_text(path: &Path) -> Result<String, FormatError> {
    std::fs::read_to_string(path).map_err(|reason| FormatError::Io {
        path: path.to_owned(),
        reason,
    })
}

/// Writes a whole text file, naming it in the error.
pub fn write_text(path: &Path, text: &str) -> Result<(), FormatError> {
    write_file(path, text.as_bytes())
}

/// Writes a whole file, naming it in the error.
pub fn write_file(path: &Path, bytes: &[u8]) -> Result<(), FormatError> {
    std::fs::write(path, bytes).map_err(|reason| FormatError::Io {
        path: path.to_owned(),
        reason,
    })
}
