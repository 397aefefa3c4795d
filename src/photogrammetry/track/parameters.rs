//! The tracking's settings and their bounds ([`TrackingParameters`]).

use super::{readable, TrackError, Volume, MAX_DECISION_LENGTH};

/// How to track.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackingParameters {
    /// The largest displacement of a particle between two frames (mm per
    /// frame): the search radius of a trajectory's first link.
    pub max_velocity: f64,
    /// The largest change of velocity between two frames (mm per frame²):
    /// the search radius around a prediction.
    pub max_acceleration: f64,
    /// Frames a trajectory may miss and still continue (0..=2).
    pub max_gap: usize,
    /// The fewest points of a trajectory that is reported.
    pub min_length: usize,
    /// Points on each side of a point in its polynomial fit (1..=5).
    pub fit_half_window: usize,
    /// The order of the fit (1..=3; lower where the window has fewer
    /// points).
    pub fit_order: usize,
}

impl TrackingParameters {
    /// Parameters for particles moving at most `max_velocity` mm per
    /// frame: velocity changes up to half of that per frame, gaps of one
    /// frame bridged, trajectories of 3 points or more, a 5-point
    /// quadratic fit.
    pub fn new(max_velocity: f64) -> Self {
        TrackingParameters {
            max_velocity,
            max_acceleration: max_velocity / 2.0,
            max_gap: 1,
            min_length: 3,
            fit_half_window: 2,
            fit_order: 2,
        }
    }

    /// How many frames behind the newest frame given a point may still be
    /// handed out: a trajectory waits for up to
    /// `max(min_length, MAX_DECISION_LENGTH)` points (the test for ghosts)
    /// spread over gaps, then for its fit window, plus the look-ahead. A
    /// caller holding per-frame data for the points (the command line's
    /// target indices) needs this many frames.
    pub fn report_delay(&self) -> usize {
        self.min_length
            .max(MAX_DECISION_LENGTH)
            .max(2 * self.fit_half_window + 1)
            * (self.max_gap + 1)
            + 2 * self.fit_half_window
            + 4
    }

    /// Checks every field; the error names it, its value and its range.
    ///
    /// Without a volume to compare with, the limits are bounded by
    /// [`MAX_DISPLACEMENT`]; where the observation volume is known,
    /// [`TrackingParameters::check_volume`] bounds them by its size.
    pub fn validate(&self) -> Result<(), TrackError> {
        let invalid = |what: String| Err(TrackError::InvalidParameter(what));
        if !(self.max_velocity.is_finite() && self.max_velocity > 0.0) {
            return invalid(format!(
                "max_velocity must be a positive number of mm per frame, got {}",
                self.max_velocity
            ));
        }
        if self.max_velocity > MAX_DISPLACEMENT {
            return invalid(format!(
                "max_velocity {} mm per frame is above the bound of {MAX_DISPLACEMENT} mm (1 km, \
                 MAX_DISPLACEMENT): no particle tracking volume is that large, and a larger \
                 limit only makes every particle a candidate for every trajectory; give the \
                 largest displacement per frame of the flow",
                readable(self.max_velocity)
            ));
        }
        if !(self.max_acceleration.is_finite() && self.max_acceleration > 0.0) {
            return invalid(format!(
                "max_acceleration must be a positive number of mm per frame², got {}",
                self.max_acceleration
            ));
        }
        if self.max_acceleration > 2.0 * MAX_DISPLACEMENT {
            return invalid(format!(
                "max_acceleration {} mm per frame² is above the bound of {} mm (twice \
                 MAX_DISPLACEMENT, 1 km): a change of velocity between two frames is at most \
                 twice the largest displacement; give the largest change of velocity per frame \
                 of the flow",
                readable(self.max_acceleration),
                2.0 * MAX_DISPLACEMENT
            ));
        }
        if self.max_gap > MAX_GAP {
            return invalid(format!(
                "max_gap must be 0..={MAX_GAP} frames (a prediction over a longer gap is a guess), got {}",
                self.max_gap
            ));
        }
        if self.min_length == 0 {
            return invalid("min_length must be at least 1 point".into());
        }
        if self.min_length > MAX_MIN_LENGTH {
            return invalid(format!(
                "min_length {} is above the bound of {MAX_MIN_LENGTH} points (MAX_MIN_LENGTH): \
                 every new trajectory is held in memory until it has min_length points; \
                 track with a shorter one and keep the long trajectories when reading them \
                 (the service's `?min_length=`, or filter `ptv track`'s output)",
                self.min_length
            ));
        }
        if !(1..=5).contains(&self.fit_half_window) {
            return invalid(format!(
                "fit_half_window must be 1..=5 points, got {}",
                self.fit_half_window
            ));
        }
        if !(1..=3).contains(&self.fit_order) {
            return invalid(format!(
                "fit_order must be 1, 2 or 3, got {}",
                self.fit_order
            ));
        }
        Ok(())
    }

    /// Checks the limits against the observation volume the particles
    /// are found in (the matcher's, [`crate::photogrammetry::correspond::Matcher::volume`]):
    /// `max_velocity` at most the volume's diagonal and `max_acceleration`
    /// at most twice that. No particle of the volume moves farther than its
    /// diagonal between two frames, and no velocity changes by more than
    /// twice that, so a larger limit describes no motion the volume can
    /// hold: it only widens every search to the whole volume. The bound is
    /// the diagonal, not the volume's smallest side, so that a flow
    /// through a thin light sheet or along a long channel keeps whatever
    /// limit its geometry allows. A volume with an unbounded axis (as
    /// OpenPTV's depth-only bounds) bounds nothing here: [`MAX_DISPLACEMENT`]
    /// still holds.
    pub fn check_volume(&self, volume: &Volume) -> Result<(), TrackError> {
        let diagonal = (volume.max - volume.min).norm();
        if !diagonal.is_finite() {
            return Ok(());
        }
        let describe = || {
            format!(
                "x {}..{}, y {}..{}, z {}..{} mm",
                volume.min.x, volume.max.x, volume.min.y, volume.max.y, volume.min.z, volume.max.z
            )
        };
        if self.max_velocity > diagonal {
            return Err(TrackError::InvalidParameter(format!(
                "max_velocity {} mm per frame is above the bound of {} mm, the diagonal of the \
                 observation volume ({}): no particle moves farther than that between two \
                 frames, and a larger limit only makes every particle a candidate for every \
                 trajectory; give the largest displacement per frame of the flow",
                readable(self.max_velocity),
                readable(diagonal),
                describe()
            )));
        }
        if self.max_acceleration > 2.0 * diagonal {
            return Err(TrackError::InvalidParameter(format!(
                "max_acceleration {} mm per frame² is above the bound of {} mm, twice the \
                 diagonal of the observation volume ({}): a velocity within the volume changes \
                 by at most that between two frames; give the largest change of velocity per \
                 frame of the flow",
                readable(self.max_acceleration),
                readable(2.0 * diagonal),
                describe()
            )));
        }
        Ok(())
    }
}

/// The largest `max_velocity` any tracking takes (mm per frame), whatever
/// its volume: 10^6 mm, a kilometre per frame. The largest volumes
/// tracked (helium bubbles or snowflakes in the atmospheric surface
/// layer) are tens of metres across; where the volume is known
/// ([`TrackingParameters::check_volume`]) its diagonal bounds the limit
/// far more tightly. `max_acceleration` is bounded by twice this.
pub const MAX_DISPLACEMENT: f64 = 1e6;

/// The longest `min_length` (points): 100. A new trajectory is held in
/// memory, about 80 bytes a point, until it has `min_length` points (or
/// the test for ghosts decided, at [`MAX_DECISION_LENGTH`] points for
/// the default), so this bounds what each live particle holds at 8 KB
/// (80 MB at 10,000 particles a frame); longer trajectories are chosen
/// when reading the result.
pub const MAX_MIN_LENGTH: usize = 100;

/// The most candidates a trajectory's search keeps in the next frame: the
/// 32 nearest its prediction (all of them where there are fewer, as at
/// any sane limit: a limit of the particle spacing puts 4 on average in
/// the search). With limits as large as the volume every particle is in
/// every search; this keeps a frame's links at `32 N` and its work at
/// about `N` searches of a few cells each (each look-ahead is a search for
/// the single best partner), instead of `N³` (5,000 particles a frame at
/// 10^308 mm per frame: 85 s a frame before this bound).
pub const MAX_CANDIDATES: usize = 32;

/// The longest gap bridged.
pub const MAX_GAP: usize = 2;
