//! `ptv calibration import-openptv` and `export-openptv`: OpenPTV's files
//! to and from the calibration JSON, through [`crate::formats::openptv`].

use std::io::Write;

use super::{
    read_calibration, write_stderr_line, write_stdout, CliError, ExportOpenptvArgs,
    ImportOpenptvArgs,
};
use crate::formats::{self, openptv};

/// Imports OpenPTV's files and writes the calibration JSON to the output
/// file, or to standard output.
pub(super) fn import_openptv(
    args: &ImportOpenptvArgs,
    stdout: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = openptv::import(&args.ptv_par, &args.ori)?;
    let json = formats::calibration::to_json(&cameras);
    match &args.output {
        Some(path) => Ok(formats::write_text(path, &json)?),
        None => write_stdout(stdout, &json),
    }
}

/// Exports a calibration JSON as OpenPTV's files and lists them on standard error.
pub(super) fn export_openptv(
    args: &ExportOpenptvArgs,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let cameras = read_calibration(&args.calibration)?;
    let written = openptv::export(&cameras, &args.out_dir).map_err(|source| CliError::Export {
        calibration: args.calibration.clone(),
        source,
    })?;
    for path in written {
        write_stderr_line(stderr, &path.display().to_string())?;
    }
    Ok(())
}
