//! Files people already have, parsed into validated core values.
//!
//! - [`calibration`]: the project's calibration JSON.
//! - [`openptv`]: OpenPTV's `.ori`, `.addpar` and `ptv.par`.
//! - [`csv`]: point and observation tables of the command line.
//!
//! Every parser takes the text and a `source` (a file name, or a label like
//! `request body`) and returns a [`FormatError`] that names the source, the
//! line or field, and what was expected.

pub mod calibration;
pub mod csv;
pub mod openptv;

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

/// Reads a whole text file, naming it in the error.
pub fn read_text(path: &Path) -> Result<String, FormatError> {
    std::fs::read_to_string(path).map_err(|reason| FormatError::Io {
        path: path.to_owned(),
        reason,
    })
}

/// Writes a whole text file, naming it in the error.
pub fn write_text(path: &Path, text: &str) -> Result<(), FormatError> {
    std::fs::write(path, text).map_err(|reason| FormatError::Io {
        path: path.to_owned(),
        reason,
    })
}
