//! The kinds of job. A job row's `kind` column holds [`JobKind::as_str`]'s
//! name; the workers parse it ([`str::parse`]) and dispatch by `match`
//! (`ops::jobs`). The row keeps the text: a database shared with another
//! release may hold a kind this one does not know, and such a job fails
//! with [`UnknownJobKind`]'s message instead of breaking the claim.

use std::fmt;
use std::str::FromStr;

/// What a job does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum JobKind {
    /// Processes one uploaded frame (`process_frame`).
    ProcessFrame,
    /// Solves a calibration by resection (`solve_calibration`).
    SolveCalibration,
    /// Self-calibrates a sequence's calibration (`self_calibrate`).
    SelfCalibrate,
    /// Re-matches a sequence's frames with a calibration
    /// (`reprocess_sequence`).
    ReprocessSequence,
}

impl JobKind {
    /// Every kind.
    pub const ALL: [JobKind; 4] = [
        JobKind::ProcessFrame,
        JobKind::SolveCalibration,
        JobKind::SelfCalibrate,
        JobKind::ReprocessSequence,
    ];

    /// The name stored in the `jobs` table and shown by `GET /jobs/{id}`.
    pub fn as_str(self) -> &'static str {
        match self {
            JobKind::ProcessFrame => "process_frame",
            JobKind::SolveCalibration => "solve_calibration",
            JobKind::SelfCalibrate => "self_calibrate",
            JobKind::ReprocessSequence => "reprocess_sequence",
        }
    }
}

impl fmt::Display for JobKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A stored kind this service does not know.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("this service does not know jobs of kind `{0}`")]
pub struct UnknownJobKind(pub String);

impl FromStr for JobKind {
    type Err = UnknownJobKind;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        JobKind::ALL
            .into_iter()
            .find(|kind| kind.as_str() == name)
            .ok_or_else(|| UnknownJobKind(name.to_owned()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The stored names are the ones rows already hold: changing one
    /// would orphan the queued jobs of a database written before.
    #[test]
    fn the_stored_names_stay_and_read_back() {
        let names: Vec<&str> = JobKind::ALL.iter().map(|k| k.as_str()).collect();
        assert_eq!(
            names,
            [
                "process_frame",
                "solve_calibration",
                "self_calibrate",
                "reprocess_sequence"
            ]
        );
        for kind in JobKind::ALL {
            assert_eq!(kind.as_str().parse::<JobKind>(), Ok(kind));
        }
        let unknown = "echo".parse::<JobKind>().unwrap_err();
        assert_eq!(
            unknown.to_string(),
            "this service does not know jobs of kind `echo`"
        );
    }
}
