//! The kinds of job, by the name stored in the `jobs` table's `kind`
//! column.

/// The kind of the job that processes one uploaded frame.
pub const PROCESS_FRAME: &str = "process_frame";

/// The kind of the job that solves a calibration by resection.
pub const SOLVE_CALIBRATION: &str = "solve_calibration";

/// The kind of the job that self-calibrates a sequence's calibration.
pub const SELF_CALIBRATE: &str = "self_calibrate";

/// The kind of the job that re-matches a sequence's frames with a
/// calibration.
pub const REPROCESS_SEQUENCE: &str = "reprocess_sequence";
