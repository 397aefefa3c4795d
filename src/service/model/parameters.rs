//! A sequence's detection and matching parameters as the API takes them:
//! every field optional, named as the command line's flags
//! (`--min-pixels` is `min_pixels`), defaults filled in before they are
//! stored, so a stored sequence never changes meaning when a default does.

use nalgebra::Point3;
use serde::{Deserialize, Deserializer, Serialize};
use utoipa::ToSchema;

use crate::formats::control::{calibration_options, fixed_parameters, OptionError};
use crate::formats::experiment::Experiment;
use crate::photogrammetry::background::BackgroundMode;
use crate::photogrammetry::calibrate::{mark_detection_parameters, CalibrationOptions, Parameter};
use crate::photogrammetry::correspond::{MatchingParameters, DEFAULT_TOLERANCE_PX};
use crate::photogrammetry::{
    Centroid, DetectionParameters, FrameDetection, InvalidDetectionParameters, Volume,
};

/// How to find the targets in each camera's image (all optional; the
/// defaults are `ptv detect`'s). Sequences stored before a field existed
/// read it as absent, that is as its default.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DetectionSettings {
    /// Grey threshold above the high-pass filtered background [default: 10,
    /// for 8-bit images].
    pub threshold: Option<u16>,
    /// Per camera, in camera order, its grey threshold (overrides
    /// `threshold`; OpenPTV's `gvthres`): one value per camera of the
    /// calibration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub thresholds: Option<Vec<u16>>,
    /// Radius (px) of the high-pass filter's window; 0 turns it off
    /// [default: 25, OpenPTV's and pyptv's].
    pub highpass_radius: Option<u32>,
    /// Fewest pixels of a target [default: 2].
    pub min_pixels: Option<u32>,
    /// Most pixels of a target [default: 500].
    pub max_pixels: Option<u32>,
    /// Smallest extent of a target in x, columns spanned [default: 1].
    #[serde(default)]
    pub min_nx: Option<u32>,
    /// Largest extent of a target in x [default: 50].
    #[serde(default)]
    pub max_nx: Option<u32>,
    /// Smallest extent of a target in y, rows spanned [default: 1].
    #[serde(default)]
    pub min_ny: Option<u32>,
    /// Largest extent of a target in y [default: 50].
    #[serde(default)]
    pub max_ny: Option<u32>,
    /// Smallest sum of grey values of a target [default: as `ptv detect`].
    pub min_sumg: Option<u64>,
    /// Whether to split blobs of touching particles at grey minima
    /// [default: true].
    #[serde(default)]
    pub split: Option<bool>,
    /// How far (grey levels) the fainter of two maxima must rise above the
    /// brightest path joining them for a blob to be split there; OpenPTV's
    /// `discont`. Unset or `null`: the automatic rule of `ptv detect`
    /// without `--split-depth` (relative to the maximum's height above the
    /// threshold and to the image's noise level, stricter in frames whose
    /// particle images have structure of their own).
    #[serde(default)]
    pub split_depth: Option<u16>,
    /// How a target's position is estimated: `weighted` (the grey value
    /// weighted centroid, OpenPTV's) or `gaussian` (a 3-point Gaussian fit
    /// per axis around the brightest pixel, the weighted centroid where it
    /// does not apply) [default: weighted; sequences stored without it are
    /// weighted].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<String>, example = "weighted")]
    pub centroid: Option<Centroid>,
    /// The smallest signal-to-noise ratio of a target: its sum of grey
    /// over its `n` pixels must be at least `min_snr · sigma · sqrt(n)`,
    /// `sigma` being the image's noise level after the high-pass filter,
    /// estimated per frame; 0 turns the test off (as an imported OpenPTV
    /// experiment does) [default: 12].
    #[serde(default)]
    pub min_snr: Option<u16>,
}

impl DetectionSettings {
    /// The core's detection parameters, defaults where unset (not yet
    /// validated), with `threshold` for every camera (`thresholds` is
    /// applied by [`DetectionSettings::frame_detection`]).
    pub fn parameters(&self) -> DetectionParameters {
        let d = DetectionParameters::default();
        DetectionParameters {
            threshold: self.threshold.unwrap_or(d.threshold),
            highpass_radius: self.highpass_radius.unwrap_or(d.highpass_radius),
            min_pixels: self.min_pixels.unwrap_or(d.min_pixels),
            max_pixels: self.max_pixels.unwrap_or(d.max_pixels),
            min_nx: self.min_nx.unwrap_or(d.min_nx),
            max_nx: self.max_nx.unwrap_or(d.max_nx),
            min_ny: self.min_ny.unwrap_or(d.min_ny),
            max_ny: self.max_ny.unwrap_or(d.max_ny),
            min_sumg: self.min_sumg.unwrap_or(d.min_sumg),
            split: self.split.unwrap_or(d.split),
            split_depth: self.split_depth.or(d.split_depth),
            centroid: self.centroid.unwrap_or(d.centroid),
            min_snr: self.min_snr.unwrap_or(d.min_snr),
        }
    }

    /// The core's detection parameters for a calibration of `cameras`
    /// cameras (not yet validated): one set per camera when `thresholds`
    /// is given, and then it must have one threshold per camera.
    pub fn frame_detection(
        &self,
        cameras: usize,
    ) -> Result<FrameDetection, InvalidDetectionParameters> {
        let parameters = self.parameters();
        match &self.thresholds {
            None => Ok(FrameDetection::AllCameras(parameters)),
            Some(list) if list.len() == cameras => Ok(FrameDetection::PerCamera(
                list.iter()
                    .map(|&threshold| DetectionParameters {
                        threshold,
                        ..parameters.clone()
                    })
                    .collect(),
            )),
            Some(list) => Err(InvalidDetectionParameters {
                field: "thresholds",
                reason: format!(
                    "gives {} thresholds but the calibration has {cameras} cameras; give one \
                     per camera, in camera order, or `threshold` for all",
                    list.len()
                ),
            }),
        }
    }

    /// Every field set: the given value, else the default.
    pub fn with_defaults(&self) -> DetectionSettings {
        let p = self.parameters();
        DetectionSettings {
            threshold: Some(p.threshold),
            thresholds: self.thresholds.clone(),
            highpass_radius: Some(p.highpass_radius),
            min_pixels: Some(p.min_pixels),
            max_pixels: Some(p.max_pixels),
            min_nx: Some(p.min_nx),
            max_nx: Some(p.max_nx),
            min_ny: Some(p.min_ny),
            max_ny: Some(p.max_ny),
            min_sumg: Some(p.min_sumg),
            split: Some(p.split),
            split_depth: p.split_depth,
            centroid: Some(p.centroid),
            min_snr: Some(p.min_snr),
        }
    }
}

/// How to solve a calibration (the `options` part of
/// `/calibrations/solve`): `ptv calibrate`'s flags, every one optional.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SolveOptions {
    /// Parameters held at the setup's values, OpenPTV's names:
    /// x0,y0,z0,omega,phi,kappa,xh,yh,c,k1,k2,k3,p1,p2,scx,she [default:
    /// none]. Case-insensitive; blank names are ignored.
    #[serde(default, deserialize_with = "fixed")]
    #[schema(value_type = Vec<String>)]
    pub fix: Vec<Parameter>,
    /// Every K-th control point (file order) is a check point, left out of
    /// the resections and intersected from all cameras (K >= 2).
    #[serde(default)]
    pub check_every: Option<usize>,
    /// Check point ids (instead of `check_every`).
    #[serde(default)]
    pub check_ids: Option<Vec<u64>>,
    /// Parameters correlated above this are held, one of each pair
    /// [default: 0.99].
    #[serde(default)]
    pub max_correlation: Option<f64>,
    /// Detection of the marks, with `image` parts (a mark's extent is
    /// bounded by `max_pixels` only).
    #[serde(default)]
    pub detection: DetectionSettings,
    /// Whether to keep the uploaded files after the calibration is solved
    /// [default: true]; a failed solve keeps them.
    #[serde(default)]
    pub keep_images: Option<bool>,
}

impl SolveOptions {
    /// The core's options, checked.
    pub fn calibration_options(&self) -> Result<CalibrationOptions, OptionError> {
        calibration_options(
            self.fix.clone(),
            self.check_every,
            self.check_ids.clone(),
            self.max_correlation
                .unwrap_or(CalibrationOptions::default().max_correlation),
        )
    }

    /// The detection parameters for calibration marks, checked.
    pub fn mark_detection(&self) -> Result<DetectionParameters, InvalidDetectionParameters> {
        mark_detection_parameters(&self.detection.parameters())
    }
}

/// `fix` as the command line's `--fix` reads it (not as `Parameter`'s own
/// serde, which takes exact lower-case names only: queued jobs' payloads
/// keep the names as they were given).
fn fixed<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<Parameter>, D::Error> {
    let names = Vec::<String>::deserialize(deserializer)?;
    fixed_parameters(&names).map_err(|e| serde::de::Error::custom(e.reason))
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

/// The most frames a computed background is taken from.
pub const MAX_BACKGROUND_FRAMES: u32 = 1000;

/// How many frames a computed background is taken from by default: the
/// median of 10 frames removes a particle from a pixel as long as it is
/// there in fewer than half of them.
pub const DEFAULT_BACKGROUND_FRAMES: u32 = 10;

/// A background the service computes from the sequence's own frames: per
/// camera, the median or minimum of each pixel over the sequence's `frames`
/// lowest-numbered frames, subtracted from every frame before the
/// high-pass filter. A frame's job waits (queued, retried every few
/// seconds, other jobs going first) until that many frames have arrived;
/// then one job computes the background and every frame, those first ones
/// included, is processed with it. A sequence with fewer frames than
/// `frames` is never processed: upload a background instead
/// (`POST /sequences/{id}/background`) for short ones.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ComputedBackground {
    /// `median` or `min` of each pixel over the frames [default: median].
    #[serde(default = "median")]
    #[schema(value_type = String, example = "median")]
    pub mode: BackgroundMode,
    /// How many frames, 2..=1000 [default: 10].
    #[serde(default = "default_background_frames")]
    pub frames: u32,
}

fn median() -> BackgroundMode {
    BackgroundMode::Median
}

fn default_background_frames() -> u32 {
    DEFAULT_BACKGROUND_FRAMES
}

impl ComputedBackground {
    /// Checks the frame count.
    pub fn validate(&self) -> Result<(), String> {
        if !(2..=MAX_BACKGROUND_FRAMES).contains(&self.frames) {
            return Err(format!(
                "background.frames: {} is outside 2..={MAX_BACKGROUND_FRAMES}",
                self.frames
            ));
        }
        Ok(())
    }
}

/// How a sequence's calibration health is watched
/// ([`crate::photogrammetry::health::DriftMonitor`]): a camera's alarm
/// fires at the first frame at which the mean of its last `window` frames'
/// mean disparity vectors has moved more than `threshold_px` from the mean
/// of the run's first `window` frames. Sequences stored before the setting
/// existed read it as absent, that is as the defaults.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct HealthSettings {
    /// The drift (px) that raises a camera's alarm, above 0 and at most
    /// 100 [default: 0.3].
    #[serde(default = "default_threshold_px")]
    pub threshold_px: f64,
    /// Frames per window, 1..=500 [default: 50].
    #[serde(default = "default_window")]
    pub window: u32,
}

/// The largest health window: the monitor keeps one window of frame means
/// per camera (3 numbers a frame), so its stored state stays under about
/// 16 cameras x 500 frames x 60 bytes = 480 KB of JSON.
pub const MAX_HEALTH_WINDOW: u32 = 500;

fn default_threshold_px() -> f64 {
    crate::photogrammetry::health::DriftMonitor::DEFAULT_THRESHOLD_PX
}

fn default_window() -> u32 {
    crate::photogrammetry::health::DriftMonitor::DEFAULT_WINDOW as u32
}

impl Default for HealthSettings {
    fn default() -> Self {
        HealthSettings {
            threshold_px: default_threshold_px(),
            window: default_window(),
        }
    }
}

impl HealthSettings {
    /// Checks the threshold and the window.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.threshold_px.is_finite() && self.threshold_px > 0.0 && self.threshold_px <= 100.0)
        {
            return Err(format!(
                "health.threshold_px: {} is not a drift in pixels above 0 and at most 100",
                self.threshold_px
            ));
        }
        if !(1..=MAX_HEALTH_WINDOW).contains(&self.window) {
            return Err(format!(
                "health.window: {} is outside 1..={MAX_HEALTH_WINDOW} frames",
                self.window
            ));
        }
        Ok(())
    }
}

/// The parameters a sequence is processed with, defaults filled in.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct SequenceParameters {
    /// Detection, every field set.
    pub detection: DetectionSettings,
    /// Matching, every field set but `volume` (absent: the default volume).
    pub matching: MatchingSettings,
    /// The background the service computes from the frames, if any
    /// (absent: none, or an uploaded one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub background: Option<ComputedBackground>,
    /// How its calibration health is watched (absent in sequences stored
    /// before the setting existed: the defaults).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub health: Option<HealthSettings>,
}

impl SequenceParameters {
    /// Fills in the defaults.
    pub fn with_defaults(detection: DetectionSettings, matching: MatchingSettings) -> Self {
        SequenceParameters {
            detection: detection.with_defaults(),
            matching: MatchingSettings {
                tolerance: Some(matching.tolerance.unwrap_or(DEFAULT_TOLERANCE_PX)),
                volume: matching.volume,
                min_cameras: Some(matching.min_cameras.unwrap_or(2)),
            },
            background: None,
            health: Some(HealthSettings::default()),
        }
    }

    /// The health settings, the defaults where the stored sequence has none.
    pub fn health(&self) -> HealthSettings {
        self.health.clone().unwrap_or_default()
    }

    /// The core's detection parameters (not yet validated): per camera
    /// when `thresholds` is set (the frame pipeline then checks their count
    /// against the calibration's cameras; [`DetectionSettings::frame_detection`]
    /// checks it with the field's name).
    pub fn detection(&self) -> FrameDetection {
        let parameters = self.detection.parameters();
        match &self.detection.thresholds {
            None => FrameDetection::AllCameras(parameters),
            Some(list) => FrameDetection::PerCamera(
                list.iter()
                    .map(|&threshold| DetectionParameters {
                        threshold,
                        ..parameters.clone()
                    })
                    .collect(),
            ),
        }
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

/// The sequence settings of an experiment, as the service takes them.
pub fn experiment_settings(experiment: &Experiment) -> (DetectionSettings, MatchingSettings) {
    let first = &experiment.detection[0];
    let detection = DetectionSettings {
        threshold: Some(first.threshold),
        thresholds: Some(experiment.detection.iter().map(|d| d.threshold).collect()),
        highpass_radius: Some(first.highpass_radius),
        min_pixels: Some(first.min_pixels),
        max_pixels: Some(first.max_pixels),
        min_nx: Some(first.min_nx),
        max_nx: Some(first.max_nx),
        min_ny: Some(first.min_ny),
        max_ny: Some(first.max_ny),
        min_sumg: Some(first.min_sumg),
        split: Some(first.split),
        split_depth: first.split_depth,
        centroid: Some(first.centroid),
        min_snr: Some(first.min_snr),
    };
    let m = &experiment.matching;
    let matching = MatchingSettings {
        tolerance: Some(m.tolerance),
        volume: m
            .volume
            .map(|v| [v.min.x, v.max.x, v.min.y, v.max.y, v.min.z, v.max.z]),
        min_cameras: Some(m.min_cameras),
    };
    (detection, matching)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fix_takes_the_command_lines_names_and_writes_them_back_in_lower_case() {
        let options: SolveOptions = serde_json::from_str(r#"{"fix": ["k3", " C", ""]}"#).unwrap();
        assert_eq!(options.fix, vec![Parameter::K3, Parameter::C]);
        let json = serde_json::to_value(&options).unwrap();
        assert_eq!(json["fix"], serde_json::json!(["k3", "c"]));
        let error = serde_json::from_str::<SolveOptions>(r#"{"fix": ["k4"]}"#)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains(
                "unknown parameter `k4`; the names are \
                 x0,y0,z0,omega,phi,kappa,xh,yh,c,k1,k2,k3,p1,p2,scx,she"
            ),
            "{error}"
        );
    }

    #[test]
    fn the_significance_test_reaches_the_core_and_is_stored() {
        // Absent: the core's default, written out when stored.
        let absent: DetectionSettings = serde_json::from_str("{}").unwrap();
        assert_eq!(
            absent.parameters().min_snr,
            DetectionParameters::default().min_snr
        );
        assert_eq!(
            absent.with_defaults().min_snr,
            Some(DetectionParameters::default().min_snr)
        );
        // 0 turns it off, as an imported OpenPTV experiment does.
        let off: DetectionSettings = serde_json::from_str(r#"{"min_snr": 0}"#).unwrap();
        assert_eq!(off.parameters().min_snr, 0);
        assert_eq!(off.with_defaults().min_snr, Some(0));
    }

    #[test]
    fn per_camera_thresholds_and_the_split_rule_reach_the_core() {
        let settings: DetectionSettings = serde_json::from_str(
            r#"{"thresholds": [9, 9, 11], "split_depth": 100, "min_nx": 2, "max_ny": 80}"#,
        )
        .unwrap();
        let FrameDetection::PerCamera(list) = settings.frame_detection(3).unwrap() else {
            panic!("thresholds give one set per camera")
        };
        assert_eq!(
            list.iter().map(|p| p.threshold).collect::<Vec<_>>(),
            vec![9, 9, 11]
        );
        assert!(list
            .iter()
            .all(|p| p.split_depth == Some(100) && p.min_nx == 2 && p.max_ny == 80 && p.split));
        let error = settings.frame_detection(4).unwrap_err();
        assert_eq!(error.field, "thresholds");
        assert!(error
            .reason
            .contains("gives 3 thresholds but the calibration has 4 cameras"));
        // with_defaults fills every field and keeps the list.
        let filled = SequenceParameters::with_defaults(settings, MatchingSettings::default());
        let d = DetectionParameters::default();
        assert_eq!(filled.detection.split, Some(d.split));
        assert_eq!(filled.detection.max_nx, Some(d.max_nx));
        assert_eq!(filled.detection.thresholds, Some(vec![9, 9, 11]));
        assert_eq!(
            filled.detection().clone(),
            filled.detection.frame_detection(3).unwrap()
        );
    }

    #[test]
    fn the_centroid_is_weighted_unless_asked_for_and_stored_once_filled_in() {
        let unset: DetectionSettings = serde_json::from_str("{}").unwrap();
        assert_eq!(unset.parameters().centroid, Centroid::Weighted);
        assert_eq!(unset.with_defaults().centroid, Some(Centroid::Weighted));
        let gaussian: DetectionSettings =
            serde_json::from_str(r#"{"centroid": "gaussian"}"#).unwrap();
        assert_eq!(gaussian.parameters().centroid, Centroid::Gaussian);
        let json = serde_json::to_value(gaussian.with_defaults()).unwrap();
        assert_eq!(json["centroid"], "gaussian");
        let error = serde_json::from_str::<DetectionSettings>(r#"{"centroid": "fit"}"#)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("unknown variant `fit`, expected `weighted` or `gaussian`"),
            "{error}"
        );
    }

    #[test]
    fn parameters_stored_before_the_new_fields_still_read() {
        // A sequence's stored JSON as it was written before the extent
        // bounds, the split rule and per-camera thresholds existed.
        let stored = r#"{"detection": {"threshold": 12, "highpass_radius": 10, "min_pixels": 2,
            "max_pixels": 500, "min_sumg": 0},
            "matching": {"tolerance": 1.0, "volume": null, "min_cameras": 2}}"#;
        let parameters: SequenceParameters = serde_json::from_str(stored).unwrap();
        let FrameDetection::AllCameras(p) = parameters.detection() else {
            panic!("no thresholds list: one set for all")
        };
        assert_eq!(
            p,
            DetectionParameters {
                threshold: 12,
                highpass_radius: 10,
                ..DetectionParameters::default()
            }
        );
    }
}
