//! A sequence's detection and matching parameters as the API takes them:
//! every field optional, named as the command line's flags
//! (`--min-pixels` is `min_pixels`), defaults filled in before they are
//! stored, so a stored sequence never changes meaning when a default does.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::photogrammetry::correspond::{MatchingParameters, DEFAULT_TOLERANCE_PX};
use crate::photogrammetry::{DetectionParameters, FrameDetection, Volume};

/// How to find the targets in each camera's image (all optional; the
/// defaults are `ptv detect`'s).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DetectionSettings {
    /// Grey threshold above the high-pass filtered background [default: 10,
    /// for 8-bit images].
    pub threshold: Option<u16>,
    /// Radius (px) of the high-pass filter's window; 0 turns it off
    /// [default: 10].
    pub highpass_radius: Option<u32>,
    /// Fewest pixels of a target [default: 2].
    pub min_pixels: Option<u32>,
    /// Most pixels of a target [default: 500].
    pub max_pixels: Option<u32>,
    /// Smallest sum of grey values of a target [default: as `ptv detect`].
    pub min_sumg: Option<u64>,
}

/// How to match targets across cameras (all optional; the defaults are
/// `ptv match`'s).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MatchingSettings {
    /// Half-width (px) of the epipolar band and the largest residual of an
    /// accepted particle [default: 1].
    pub tolerance: Option<f64>,
    /// Observation volume (mm) `[xmin, xmax, ymin, ymax, zmin, zmax]`
    /// [default: a cube around the point all cameras look at].
    pub volume: Option<[f64; 6]>,
    /// Fewest cameras that must see a particle [default: 2].
    pub min_cameras: Option<usize>,
}

/// The parameters a sequence is processed with, defaults filled in.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct SequenceParameters {
    /// Detection, every field set.
    pub detection: DetectionSettings,
    /// Matching, every field set but `volume` (absent: the default volume).
    pub matching: MatchingSettings,
}

impl SequenceParameters {
    /// Fills in the defaults.
    pub fn with_defaults(detection: DetectionSettings, matching: MatchingSettings) -> Self {
        let d = DetectionParameters::default();
        SequenceParameters {
            detection: DetectionSettings {
                threshold: Some(detection.threshold.unwrap_or(d.threshold)),
                highpass_radius: Some(detection.highpass_radius.unwrap_or(d.highpass_radius)),
                min_pixels: Some(detection.min_pixels.unwrap_or(d.min_pixels)),
                max_pixels: Some(detection.max_pixels.unwrap_or(d.max_pixels)),
                min_sumg: Some(detection.min_sumg.unwrap_or(d.min_sumg)),
            },
            matching: MatchingSettings {
                tolerance: Some(matching.tolerance.unwrap_or(DEFAULT_TOLERANCE_PX)),
                volume: matching.volume,
                min_cameras: Some(matching.min_cameras.unwrap_or(2)),
            },
        }
    }

    /// The core's detection parameters (not yet validated).
    pub fn detection(&self) -> FrameDetection {
        let d = DetectionParameters::default();
        let s = &self.detection;
        FrameDetection::AllCameras(DetectionParameters {
            threshold: s.threshold.unwrap_or(d.threshold),
            highpass_radius: s.highpass_radius.unwrap_or(d.highpass_radius),
            min_pixels: s.min_pixels.unwrap_or(d.min_pixels),
            max_pixels: s.max_pixels.unwrap_or(d.max_pixels),
            min_sumg: s.min_sumg.unwrap_or(d.min_sumg),
            ..d
        })
    }

    /// The core's matching parameters (not yet validated).
    pub fn matching(&self) -> MatchingParameters {
        let m = &self.matching;
        MatchingParameters {
            tolerance: m.tolerance.unwrap_or(DEFAULT_TOLERANCE_PX),
            volume: m.volume.map(|v| Volume {
                min: Point3::new(v[0], v[2], v[4]),
                max: Point3::new(v[1], v[3], v[5]),
            }),
            min_cameras: m.min_cameras.unwrap_or(2),
            ..MatchingParameters::default()
        }
    }
}
