//! How to self-calibrate ([`SelfCalibrationOptions`]) and how it fails
//! ([`SelfCalibrationError`]).

use super::bundle::MediaTerm;
use crate::photogrammetry::calibrate::{Parameter, ParameterSet};
use crate::photogrammetry::camera::InvalidCamera;
use crate::photogrammetry::cancel::Cancelled;
use crate::photogrammetry::correspond::MatchError;
use crate::photogrammetry::volume::Volume;

/// The fewest particles an adjustment takes: with 4 cameras of 16
/// parameters, 64 unknowns besides the points', each particle adding at
/// least one redundant coordinate; 100 leaves a redundancy for sigma0 and
/// for judging which parameters are determined.
pub const MIN_PARTICLES: usize = 100;

/// How to self-calibrate.
#[derive(Clone, Debug, PartialEq)]
pub struct SelfCalibrationOptions {
    /// The first round's band (px): wide enough for the input
    /// calibration's disparities.
    pub start_tolerance_px: f64,
    /// The narrowest band (px): about 3-5 times the image noise.
    pub final_tolerance_px: f64,
    /// The observation volume; `None` for the region the cameras see.
    pub volume: Option<Volume>,
    /// The fewest cameras a confident particle must be seen by (3 by
    /// default; capped at the rig's cameras).
    pub min_cameras: usize,
    /// Most particles in one adjustment.
    pub max_particles: usize,
    /// Sub-volumes per axis for the cap and the disparity maps.
    pub grid: [usize; 3],
    /// A target with another within this distance (px) in its image is
    /// not confident.
    pub isolation_px: f64,
    /// Parameters held at the input's values in every camera.
    pub fixed: Vec<Parameter>,
    /// Media terms adjusted with the cameras (none by default: held at
    /// the input's values).
    pub free_media: Vec<MediaTerm>,
    /// Parameters correlated above this are held (one of the pair).
    pub max_correlation: f64,
    /// Most rounds (match, select, adjust).
    pub max_rounds: usize,
}

impl SelfCalibrationOptions {
    /// The names [`SelfCalibrationOptions::free`] takes.
    pub const FREEABLE: &'static str =
        "xh,yh,c,k1,k2,k3,p1,p2,scx,she or glass,n_wall,n_object,thickness";

    /// Frees the interior or distortion parameter, or the media term, of
    /// `name` (OpenPTV's names, case-insensitive: `xh`, `yh`, `c`, `k1`,
    /// `k2`, `k3`, `p1`, `p2`, `scx`, `she`; `glass`, `n_wall`,
    /// `n_object`, `thickness`). The exterior orientation is always free.
    /// An unknown name is an error naming the choices.
    pub fn free(&mut self, name: &str) -> Result<(), String> {
        let name = name.trim().to_ascii_lowercase();
        if let Some(term) = MediaTerm::from_name(&name) {
            if !self.free_media.contains(&term) {
                self.free_media.push(term);
            }
            return Ok(());
        }
        let freeable = ParameterSet::interior() | ParameterSet::distortion();
        match Parameter::from_name(&name).filter(|p| freeable.iter().any(|q| q == *p)) {
            Some(p) => {
                self.fixed.retain(|q| *q != p);
                Ok(())
            }
            None => Err(format!(
                "`{name}` is not a parameter the particles can adjust; give names among {} \
                 (the exterior orientation is always adjusted)",
                Self::FREEABLE
            )),
        }
    }
}

impl Default for SelfCalibrationOptions {
    fn default() -> Self {
        SelfCalibrationOptions {
            start_tolerance_px: 4.0,
            final_tolerance_px: 0.5,
            volume: None,
            min_cameras: 3,
            max_particles: 4000,
            grid: [4, 4, 4],
            isolation_px: 1.5,
            fixed: default_fixed(),
            free_media: Vec::new(),
            max_correlation: 0.99,
            max_rounds: 10,
        }
    }
}

/// The parameters fixed unless asked for: the interior orientation and
/// the distortion. Particles in a volume seen from afar (a narrow field of
/// view) leave the principal distance and point nearly interchangeable
/// with the camera's distance and angles (simulated: correlations of
/// 0.99-0.9996 per camera, and a flat valley along which the rig drifts by
/// millimetres); a target calibration determines them better. Free them
/// (`--free c,xh,yh,k1,...`) where the particles fill a deep volume at
/// close range.
pub fn default_fixed() -> Vec<Parameter> {
    (ParameterSet::interior() | ParameterSet::distortion())
        .iter()
        .collect()
}

/// Where the work stands, for a progress bar.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Progress {
    /// The round (0-based).
    pub round: usize,
    /// The most rounds.
    pub rounds: usize,
    /// Frames matched in this round so far.
    pub frames_matched: usize,
    /// Frames in all.
    pub frames: usize,
    /// This round's band (px).
    pub band_px: f64,
}

/// Why self-calibration cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SelfCalibrationError {
    /// Too few cameras.
    #[error("self-calibration needs at least 2 cameras, the calibration has {0}")]
    TooFewCameras(usize),
    /// A camera of the input is not a camera.
    #[error("camera {camera} of the calibration: {source}")]
    InvalidCamera {
        /// The camera (0-based).
        camera: usize,
        /// What is wrong.
        #[source]
        source: InvalidCamera,
    },
    /// No frames.
    #[error("no frames of targets were given; give the targets of at least one frame")]
    NoFrames,
    /// A frame's target lists are not one per camera.
    #[error("frame {frame} has target lists for {given} cameras, but the calibration has {cameras}; give one list per camera, in camera order")]
    CameraCount {
        /// The frame (0-based in the input).
        frame: usize,
        /// Lists given.
        given: usize,
        /// Cameras.
        cameras: usize,
    },
    /// An option out of range.
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// Matching failed.
    #[error("matching with a band of {band_px} px: {source}")]
    Matching {
        /// The band.
        band_px: f64,
        /// Why.
        #[source]
        source: MatchError,
    },
    /// Too few confident particles.
    #[error("only {selected} confident particles (seen by at least {min_cameras} cameras, isolated) were found in {frames} frames with a band of {band_px} px (round {round}), of {matched} matched; self-calibration needs at least {needed}: give more frames, a wider band (--tolerance) if the calibration is far off, or --min-cameras 2")]
    TooFewParticles {
        /// Confident particles found.
        selected: usize,
        /// Particles matched.
        matched: usize,
        /// Frames.
        frames: usize,
        /// The band (px).
        band_px: f64,
        /// The round (1-based).
        round: usize,
        /// The camera count asked.
        min_cameras: usize,
        /// The least.
        needed: usize,
    },
    /// Stopped by its cancel token.
    #[error("self-calibration {0}")]
    Cancelled(#[from] Cancelled),
}
