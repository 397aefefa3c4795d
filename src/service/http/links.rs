//! The API's URLs, built in one place: `Location` headers, the links in
//! accepted uploads, a job's `result`. The store keeps ids, never URLs.

use crate::service::store::{CalibrationId, FrameNumber, JobId, SequenceId};

/// Where the API is mounted.
const API: &str = "/api/v1";

/// A calibration.
pub fn calibration(id: CalibrationId) -> String {
    format!("{API}/calibrations/{id}")
}

/// A sequence.
pub fn sequence(id: SequenceId) -> String {
    format!("{API}/sequences/{id}")
}

/// A frame's particles.
pub fn frame_particles(sequence_id: SequenceId, frame: FrameNumber) -> String {
    format!("{API}/sequences/{sequence_id}/frames/{frame}/particles")
}

/// A job.
pub fn job(id: JobId) -> String {
    format!("{API}/jobs/{id}")
}
