//! The API's URLs, built in one place: `Location` headers, the links in
//! accepted uploads, a job's `result`. The store keeps ids, never URLs.

use crate::service::store::{CalibrationId, FrameNumber, JobId, JobResult, SequenceId};

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

/// Where a job's result is.
pub fn job_result(result: &JobResult) -> String {
    match result {
        JobResult::Calibration(id) => calibration(*id),
        JobResult::Frame { sequence_id, frame } => frame_particles(*sequence_id, *frame),
        JobResult::Link(link) => link.clone(),
    }
}
