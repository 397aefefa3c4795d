//! A tracking run's settings, as a client sends them and the store keeps
//! them (JSON), checked and mapped onto the core's tracking parameters.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::photogrammetry::track::{TrackError, TrackingParameters};
use crate::photogrammetry::Volume;
use crate::service::model::ids::{FrameNumber, MAX_FRAME_NUMBER};

/// How to track a sequence (all but `max_velocity` optional; the defaults
/// are `ptv track`'s).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TrackingSettings {
    /// The largest displacement of a particle between two frames (mm per
    /// frame): above zero, and at most the diagonal of the sequence's
    /// observation volume (its `matching.volume`, else its calibration's
    /// default volume): a larger limit describes no motion in the volume
    /// and only makes every particle a candidate for every trajectory.
    pub max_velocity: f64,
    /// The largest change of velocity between two frames (mm per frame²),
    /// at most twice the volume's diagonal [default: half of max_velocity].
    #[serde(default)]
    pub max_acceleration: Option<f64>,
    /// Frames a trajectory may miss and continue, 0 to 2 [default: 1].
    #[serde(default)]
    pub max_gap: Option<usize>,
    /// The fewest points of a trajectory that is stored, 1 to 100
    /// (trajectories are held in memory until they have that many)
    /// [default: 3].
    #[serde(default)]
    pub min_length: Option<usize>,
    /// Points on each side of a point in its polynomial fit, 1 to 5
    /// [default: 2].
    #[serde(default)]
    pub fit_half_window: Option<usize>,
    /// The fit's order, 1 to 3 [default: 2].
    #[serde(default)]
    pub fit_order: Option<usize>,
    /// The sequence's first frame: tracking starts there and waits for it
    /// [default: 0].
    #[serde(default)]
    #[schema(value_type = Option<i64>, minimum = 0, maximum = 4_294_967_295_u64)]
    pub first_frame: Option<FrameNumber>,
    /// Look in each frame's targets for the particles the correspondences
    /// missed, where a trajectory's prediction has none (Willneff's
    /// image-space recovery, as `ptv track` does unless `--no-recovery`;
    /// within the sequence's matching `tolerance`, with the calibration
    /// the sequence has when the run starts) [default: true]. A recovered
    /// particle is a point of its trajectory whose `particle` index is at
    /// or above its frame's particle count. Runs stored before this
    /// setting existed show false: they were tracked without.
    #[serde(default)]
    pub recovery: Option<bool>,
    /// Once the run finishes (`POST .../tracking/finish` and every frame
    /// tracked), extend every trajectory backwards in time from its first
    /// points with the same criteria (`ptv track`'s pass; OpenPTV's
    /// `trackback_c`): points before the trajectories' starts, and
    /// trajectories joined onto the one ending before them; the run's
    /// `backward` says what it added [default: true: on the simulated
    /// flows of docs/tracking.md it raises the link recall by 0.16-0.24%
    /// and lengthens the trajectories by 1.2-1.8 frames, the share of
    /// wrong links and the velocity error unchanged]. The pass reads the
    /// stored run, so it costs nothing while frames are tracked; at the
    /// finish it takes memory from the budget (160 bytes a particle of the
    /// run and 768 a point). Runs stored before this setting existed show
    /// false: they finished without it.
    #[serde(default)]
    pub backward: Option<bool>,
}

/// Whether a run extends its trajectories backwards unless told: yes
/// (docs/tracking.md has the figures: the points the pass adds are as
/// accurate as the trajectories' own ends, and the whole run's wrong
/// links and velocity error stay the forward pass's).
pub const BACKWARD_BY_DEFAULT: bool = true;

/// Settings the tracker refuses.
#[derive(Debug, thiserror::Error)]
pub enum InvalidTrackingSettings {
    /// A parameter out of range (the core's check).
    #[error("tracking: {0}")]
    Parameter(#[from] TrackError),
    /// A first frame that is no frame number.
    #[error("tracking: first_frame must be a frame number, 0 to {MAX_FRAME_NUMBER}, got {0}")]
    FirstFrame(FrameNumber),
}

impl TrackingSettings {
    /// The core's parameters.
    pub fn parameters(&self) -> TrackingParameters {
        let defaults = TrackingParameters::new(self.max_velocity);
        TrackingParameters {
            max_acceleration: self.max_acceleration.unwrap_or(defaults.max_acceleration),
            max_gap: self.max_gap.unwrap_or(defaults.max_gap),
            min_length: self.min_length.unwrap_or(defaults.min_length),
            fit_half_window: self.fit_half_window.unwrap_or(defaults.fit_half_window),
            fit_order: self.fit_order.unwrap_or(defaults.fit_order),
            ..defaults
        }
    }

    /// The settings with every default filled in, checked.
    pub fn with_defaults(&self) -> Result<TrackingSettings, InvalidTrackingSettings> {
        let p = self.parameters();
        p.validate()?;
        let first_frame = self.first_frame.unwrap_or(FrameNumber(0));
        if !(0..=MAX_FRAME_NUMBER).contains(&first_frame.0) {
            return Err(InvalidTrackingSettings::FirstFrame(first_frame));
        }
        Ok(TrackingSettings {
            max_velocity: p.max_velocity,
            max_acceleration: Some(p.max_acceleration),
            max_gap: Some(p.max_gap),
            min_length: Some(p.min_length),
            fit_half_window: Some(p.fit_half_window),
            fit_order: Some(p.fit_order),
            first_frame: Some(first_frame),
            recovery: Some(self.recovery.unwrap_or(true)),
            backward: Some(self.backward.unwrap_or(BACKWARD_BY_DEFAULT)),
        })
    }

    /// Checks the limits against the sequence's observation volume (its
    /// matcher's: the `matching.volume` given, else the default volume of
    /// its calibration), by the rule `ptv track` applies too
    /// ([`TrackingParameters::check_volume`]: `max_velocity` at most the
    /// volume's diagonal, `max_acceleration` at most twice that).
    pub fn check_volume(&self, volume: &Volume) -> Result<(), InvalidTrackingSettings> {
        Ok(self.parameters().check_volume(volume)?)
    }

    pub fn first_frame(&self) -> FrameNumber {
        self.first_frame.unwrap_or(FrameNumber(0))
    }

    /// Whether a stored run recovers particles from the images. Every run
    /// is stored with its settings filled in ([`TrackingSettings::with_defaults`]:
    /// true unless switched off), so `recovery` is absent only from runs
    /// stored before the setting existed, which were tracked without it:
    /// those go on without it (a replay with it would not give what they
    /// stored).
    pub fn recovers(&self) -> bool {
        self.recovery.unwrap_or(false)
    }

    /// Whether a stored run extends its trajectories backwards once it
    /// finishes: runs are stored with their settings filled in, so an
    /// absent `backward` is a run stored before the setting existed,
    /// which finishes as it would have then (without).
    pub fn extends_backward(&self) -> bool {
        self.backward.unwrap_or(false)
    }

    /// The settings of a stored run as the API shows them (`recovery`
    /// as [`TrackingSettings::recovers`] reads it, `backward` as
    /// [`TrackingSettings::extends_backward`]).
    pub fn as_stored(self) -> TrackingSettings {
        TrackingSettings {
            recovery: Some(self.recovers()),
            backward: Some(self.extends_backward()),
            ..self
        }
    }
}
