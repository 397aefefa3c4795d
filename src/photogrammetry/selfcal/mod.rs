//! Volume self-calibration: the cameras corrected from the particles
//! themselves (Wieneke 2008, *Volume self-calibration for 3D particle image
//! velocimetry*, Exp. Fluids 45; OpenPTV's "shaking" and MyPTV do forms of
//! it). A target calibration is rarely right to a pixel when the particles
//! are filmed: the tank is filled, a wall flexes, a camera is touched.
//!
//! The loop, per round:
//!
//! 1. **Match** every frame with the current rig and a band (the first
//!    round's is wide: the user's tolerance) ([`Matcher`]). In bands wider
//!    than 1 px the best-fitting groups are mostly ghosts (2,000 particles
//!    a frame, 8 px: 1 true group of 1,721), so those rounds **vote**
//!    instead (`vote.rs`, after Wieneke 2008, section 3): per camera pair,
//!    the peak of the signed distances of candidate targets to the
//!    epipolar curves, per image region and depth; then the groups whose
//!    every pair lies at its peak, unambiguous ones only. Simulated (4
//!    cameras, 10 frames x 2,000 particles, 0.1 px noise): from a rig
//!    moved by 0.7 mm and 1 mrad (4.7 px RMS) the vote keeps 863 groups
//!    in an 8 px band, from 2 mm and 3 mrad (13.8 px) 777 in a 20 px band;
//!    one adjustment of them leaves 0.10 px, and the next round matches
//!    at the final band. After a vote the band drops to 4 times the
//!    adjusted groups' RMS at once (they are clean); after a match by at
//!    most 30% a round.
//! 2. **Keep confident particles**: seen by at least `min_cameras` cameras
//!    (3 by default, all if fewer), every target isolated in its image (no
//!    other target within `isolation_px`: crowded targets are where wrong
//!    members come from), spread over the volume with a cap per
//!    sub-volume (the best-fitting first), so that no region dominates.
//! 3. **Adjust** (`bundle`): a bundle adjustment with the cameras' free
//!    parameters and the particles' 3D positions as unknowns and the
//!    refraction inside the model (the calibration's observation equations,
//!    section 4.3/5 of the design paper, Eq. 1-12). Robust to the
//!    remaining wrong matches by an iteratively reweighted loss: Huber
//!    weights at 2 sigma, and particles with a residual beyond 5 sigma
//!    (sigma the residuals' robust scale, from their median) rejected, then
//!    adjusted again, until none is.
//! 4. **Narrow the band** to 4 times the residuals' RMS (never below the
//!    final band) and repeat until the band is the final one and the
//!    residuals stop falling (by less than 5%).
//!
//! **Why a simultaneous bundle adjustment rather than alternating**
//! intersection and resection: the alternation converges linearly at a
//! rate set by the coupling of points and cameras, which is strong here
//! (every point is seen by the same few cameras, and the gauge's
//! similarity is only weakly held by the walls): each step moves the rig
//! by a fraction of the way, so tens of alternations do what a few
//! Gauss-Newton steps of the joint problem do. The joint normal equations
//! are small once the points are eliminated (Schur complement: a 3x3 block
//! per point, the cameras' 4 x 16 unknowns left), so the joint solution
//! costs little more than one alternation.
//!
//! **Gauge** (`gauge.rs`): particles fix the rig only up to a similarity (7
//! dof); the inner constraints of a free network on the cameras' exterior
//! orientation give the least change of camera positions and orientations
//! from the input calibration, with the scale of its baselines.
//!
//! **Parameters**: all 16 per camera are free unless fixed; as in `ptv
//! calibrate` ([`crate::photogrammetry::calibrate`]), those the data do not
//! determine (a singular normal matrix, or a correlation above the limit)
//! are held, with the reason, the same rule deciding, judged on each
//! camera's block of the reduced normal matrix (its parameters given the
//! other cameras, the points eliminated). The media ([`MediaTerm`]: the
//! glass vector per wall, the indices, the walls' thickness) are held
//! unless asked for (`free_media`); asked for, they are unknowns of the
//! bundle shared by their cameras, held by the same rule judged on their
//! block of the reduced normal matrix and, since a wall's distance trades
//! against the cameras' positions, also on their correlation with any
//! camera parameter under the gauge (the cofactor matrix).
//!
//! **Report** ([`SelfCalibrationReport`]): per camera the disparities
//! (observed minus reprojected, after intersecting each particle with the
//! rig) of the last round's particles before (input calibration) and after,
//! as RMS, median and maps over sub-volumes in the manner of Wieneke 2008;
//! each parameter's change with its sigma; the band, particles and
//! residuals of every round; the gauge.
//!
//! Pure: no I/O. The entry point is [`self_calibrate`], with a [`Cancel`]
//! token and a progress callback for jobs.

mod bundle;
mod gauge;
pub mod report;
mod vote;
pub mod wand;

use nalgebra::{DMatrix, Point2, Point3, Vector2};

use crate::photogrammetry::calibrate::adjustment::{from_vector, to_vector, Statistics};
use crate::photogrammetry::calibrate::resection::undeterminable;
use crate::photogrammetry::calibrate::{Parameter, ParameterSet, ParameterStatus};
use crate::photogrammetry::camera::{Camera, CameraParameters, InvalidCamera};
use crate::photogrammetry::cancel::{Cancel, Cancelled};
use crate::photogrammetry::correspond::{MatchError, Matcher, MatchingParameters, Particle};
use crate::photogrammetry::intersect::{intersect, Observation};
use crate::photogrammetry::target::Target;
use crate::photogrammetry::volume::Volume;
pub use bundle::MediaTerm;
use bundle::{media_unknowns, residuals, Bundle, MediaUnknown, Track};
use gauge::{baseline_scale, Gauge};
pub use report::{
    CameraSelfCalibration, DisparityCell, DisparityMap, DisparityStats, GaugeReport, MediaChange,
    Outcome, ParameterChange, RoundReport, SelfCalibrationReport,
};

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

/// The refined rig and the report.
#[derive(Clone, Debug, PartialEq)]
pub struct SelfCalibration {
    /// The refined cameras, in the input's order (the input's own when the
    /// adjustment diverged: see the report's outcome).
    pub cameras: Vec<CameraParameters>,
    /// What was done.
    pub report: SelfCalibrationReport,
}

/// Checks the inputs cheaply, with the same errors as [`self_calibrate`].
pub fn check_inputs(
    cameras: &[CameraParameters],
    frames: &[Vec<Vec<Target>>],
    options: &SelfCalibrationOptions,
) -> Result<(), SelfCalibrationError> {
    if cameras.len() < 2 {
        return Err(SelfCalibrationError::TooFewCameras(cameras.len()));
    }
    for (camera, p) in cameras.iter().enumerate() {
        Camera::new(p.clone())
            .map_err(|source| SelfCalibrationError::InvalidCamera { camera, source })?;
    }
    if frames.is_empty() {
        return Err(SelfCalibrationError::NoFrames);
    }
    if let Some((frame, f)) = frames
        .iter()
        .enumerate()
        .find(|(_, f)| f.len() != cameras.len())
    {
        return Err(SelfCalibrationError::CameraCount {
            frame,
            given: f.len(),
            cameras: cameras.len(),
        });
    }
    let o = options;
    let bad = |m: String| Err(SelfCalibrationError::InvalidOption(m));
    if !(o.final_tolerance_px > 0.0 && o.final_tolerance_px.is_finite()) {
        return bad(format!(
            "the final band must be a positive number of pixels, got {}",
            o.final_tolerance_px
        ));
    }
    if !(o.start_tolerance_px >= o.final_tolerance_px && o.start_tolerance_px.is_finite()) {
        return bad(format!(
            "the starting band ({} px) must be finite and at least the final band ({} px)",
            o.start_tolerance_px, o.final_tolerance_px
        ));
    }
    if o.min_cameras < 2 {
        return bad(format!(
            "a confident particle needs at least 2 cameras, got {}",
            o.min_cameras
        ));
    }
    if o.grid.iter().any(|&g| g == 0 || g > 64) {
        return bad(format!(
            "the sub-volume grid needs 1..64 cells per axis, got {:?}",
            o.grid
        ));
    }
    if o.max_particles < MIN_PARTICLES {
        return bad(format!(
            "at most {} particles is below the least an adjustment takes ({MIN_PARTICLES})",
            o.max_particles
        ));
    }
    if !(o.isolation_px >= 0.0 && o.isolation_px.is_finite()) {
        return bad(format!(
            "the isolation distance must be a non-negative number of pixels, got {}",
            o.isolation_px
        ));
    }
    if !(o.max_correlation > 0.0 && o.max_correlation <= 1.0) {
        return bad(format!(
            "the correlation limit must be in (0, 1], got {}",
            o.max_correlation
        ));
    }
    if o.max_rounds == 0 {
        return bad("at least one round is needed".into());
    }
    if !o.free_media.is_empty() && cameras.iter().all(|c| c.media.is_homogeneous()) {
        return bad(format!(
            "media terms ({}) cannot be adjusted: no camera looks through refracting media \
             (all indices equal); drop them from the free list",
            o.free_media
                .iter()
                .map(|t| t.name())
                .collect::<Vec<_>>()
                .join(",")
        ));
    }
    Ok(())
}

/// Self-calibrates `cameras` from the targets of `frames` (per frame, per
/// camera, its targets): see the module's documentation. `progress` is
/// called as frames are matched; `cancel` is checked between frames and in
/// the matcher.
pub fn self_calibrate(
    cameras: &[CameraParameters],
    frames: &[Vec<Vec<Target>>],
    options: &SelfCalibrationOptions,
    cancel: &Cancel,
    progress: &mut dyn FnMut(Progress),
) -> Result<SelfCalibration, SelfCalibrationError> {
    check_inputs(cameras, frames, options)?;
    let setup = Setup::new(cameras, options)?;
    let mut state = State {
        cameras: setup.start.clone(),
        free: vec![setup.fixed.complement(); cameras.len()],
        held: vec![Vec::new(); cameras.len()],
        media: media_unknowns(&setup.start, &options.free_media),
        media_held: Vec::new(),
    };
    let media_all = state.media.clone();
    let rounds = run_rounds(&setup, &mut state, frames, options, cancel, progress)?;
    Ok(finish(
        setup,
        state,
        &media_all,
        frames.len(),
        options,
        rounds,
    ))
}

/// What stays as it is through the rounds: the input rig and its models,
/// the volume (the start band's matcher's), the gauge, the parameters the
/// options hold, and the cameras a confident particle needs.
struct Setup {
    start: Vec<CameraParameters>,
    models: Vec<Camera>,
    volume: Volume,
    gauge: Gauge,
    fixed: ParameterSet,
    min_cameras: usize,
}

impl Setup {
    fn new(
        cameras: &[CameraParameters],
        options: &SelfCalibrationOptions,
    ) -> Result<Setup, SelfCalibrationError> {
        let fixed: ParameterSet = options.fixed.iter().copied().collect();
        let start = cameras.to_vec();
        let models = models(&start)?;
        let volume = Matcher::new(&models, &matching(options.start_tolerance_px, options))
            .map_err(|source| SelfCalibrationError::Matching {
                band_px: options.start_tolerance_px,
                source,
            })?
            .volume()
            .to_owned();
        let gauge = Gauge::new(&start, &volume.centre(), fixed);
        Ok(Setup {
            min_cameras: options.min_cameras.min(cameras.len()),
            start,
            models,
            volume,
            gauge,
            fixed,
        })
    }
}

/// What the rounds left: their reports, the last adjustment's particles
/// and solution, how they ended and why.
struct Rounds {
    reports: Vec<RoundReport>,
    last: Option<(Vec<Track>, bundle::Solution)>,
    outcome: Outcome,
    message: Option<String>,
}

impl Rounds {
    fn diverged(&mut self, message: String) {
        self.message = Some(message);
        self.outcome = Outcome::Diverged;
    }
}

/// The rounds: match (or vote) with the band, adjust, narrow the band to
/// the residuals, until they no longer improve at the final band.
fn run_rounds(
    setup: &Setup,
    state: &mut State,
    frames: &[Vec<Vec<Target>>],
    options: &SelfCalibrationOptions,
    cancel: &Cancel,
    progress: &mut dyn FnMut(Progress),
) -> Result<Rounds, SelfCalibrationError> {
    let mut band = options.start_tolerance_px;
    let mut rounds = Rounds {
        reports: Vec::new(),
        last: None,
        outcome: Outcome::RoundLimit,
        message: None,
    };
    for round in 0..options.max_rounds {
        let Some(models) = models_or_diverged(&state.cameras) else {
            rounds.diverged(format!(
                "round {}: the adjusted parameters are not a valid camera",
                round + 1
            ));
            break;
        };
        let (tracks, matched_by_cameras, candidate_count) = round_tracks(
            setup, frames, &models, band, round, options, cancel, progress,
        )?;
        if tracks.len() < MIN_PARTICLES && rounds.last.is_some() {
            // A later round that finds too few: keep the last adjustment.
            rounds.message = Some(format!(
                "round {}: only {} confident particles with a band of {band:.3} px; the \
                 previous round's calibration is kept",
                round + 1,
                tracks.len()
            ));
            break;
        }
        if tracks.len() < MIN_PARTICLES {
            return Err(SelfCalibrationError::TooFewParticles {
                selected: tracks.len(),
                matched: matched_by_cameras.iter().sum(),
                frames: frames.len(),
                band_px: band,
                round: round + 1,
                min_cameras: setup.min_cameras,
                needed: MIN_PARTICLES,
            });
        }
        let selected = tracks.len();
        let rms_before = rms(&residual_vectors(&models, &tracks));
        let adjusted =
            robust_adjustment(state, tracks, &setup.gauge, &setup.start, options, cancel)?;
        let Some((tracks, solution, rejected, sigma)) = adjusted else {
            rounds.diverged(format!(
                "round {}: the bundle adjustment did not converge (band {band} px)",
                round + 1
            ));
            break;
        };
        let Some(after_models) = models_or_diverged(&state.cameras) else {
            rounds.diverged(format!(
                "round {}: the adjusted parameters are not a valid camera",
                round + 1
            ));
            break;
        };
        let rms_after = rms(&residual_vectors(&after_models, &tracks));
        rounds.reports.push(RoundReport {
            band_px: band,
            matched_by_cameras,
            candidates: candidate_count,
            selected,
            rejected,
            rms_before_px: rms_before,
            rms_after_px: rms_after,
            sigma_px: sigma,
            iterations: solution.iterations,
        });
        rounds.last = Some((tracks, solution));
        let previous = rounds
            .reports
            .iter()
            .rev()
            .nth(1)
            .map(|r: &RoundReport| r.rms_after_px);
        let at_final = band <= options.final_tolerance_px;
        if at_final && previous.is_some_and(|p| rms_after > 0.95 * p) {
            rounds.outcome = Outcome::Converged;
            break;
        }
        // After a vote the groups are clean and their residuals measure
        // the rig's error: the band may drop to them at once. After a
        // match, by at most 30% a round (a band that shrinks too fast
        // loses the true groups before the rig has followed).
        let shrink = if band > VOTE_ABOVE_PX { 1.0 } else { 0.7 };
        band = (4.0 * rms_after).clamp(
            options.final_tolerance_px,
            (shrink * band).max(options.final_tolerance_px),
        );
    }
    Ok(rounds)
}

/// One round's confident particles as tracks: voted for in the sub-volumes
/// while the band is wide ([`VOTE_ABOVE_PX`]), matched frame by frame
/// after.
#[allow(clippy::too_many_arguments)]
fn round_tracks(
    setup: &Setup,
    frames: &[Vec<Vec<Target>>],
    models: &[Camera],
    band: f64,
    round: usize,
    options: &SelfCalibrationOptions,
    cancel: &Cancel,
    progress: &mut dyn FnMut(Progress),
) -> Result<Matched, SelfCalibrationError> {
    let mut report = |frames_matched| {
        progress(Progress {
            round,
            rounds: options.max_rounds,
            frames_matched,
            frames: frames.len(),
            band_px: band,
        })
    };
    if band <= VOTE_ABOVE_PX {
        return matched_tracks(
            frames,
            models,
            band,
            setup.min_cameras,
            &setup.volume,
            options,
            cancel,
            &mut report,
        );
    }
    let radius = (band / 8.0).clamp(0.5, 1.0);
    let vote = vote::vote(
        frames,
        models,
        &setup.volume,
        options.grid,
        band,
        radius,
        setup.min_cameras.max(3.min(models.len())),
        options.max_particles,
        cancel,
    )?;
    report(frames.len());
    Ok((vote.tracks, vote.by_cameras, vote.candidates))
}

/// The result of the rounds: the refined rig and its report, or the input
/// rig where the rounds diverged or the refined rig reprojects the last
/// round's particles worse than the input one.
fn finish(
    setup: Setup,
    state: State,
    media_all: &[MediaUnknown],
    frame_count: usize,
    options: &SelfCalibrationOptions,
    rounds: Rounds,
) -> SelfCalibration {
    let Rounds {
        reports,
        last,
        outcome,
        message,
    } = rounds;
    let Setup {
        start,
        models,
        volume,
        gauge,
        fixed,
        ..
    } = setup;
    let sigma0 = last
        .as_ref()
        .map_or(0.0, |(_, s)| (s.cost / s.redundancy.max(1) as f64).sqrt());
    let Some((tracks, solution)) = last else {
        return diverged(
            &start,
            frame_count,
            volume,
            options,
            &gauge,
            reports,
            message,
        );
    };
    // The final disparities: the last round's particles intersected with
    // the input rig and with the refined one.
    let before = disparities(&models, &tracks);
    let refined_models = models_or_diverged(&state.cameras);
    let after = refined_models.as_ref().map(|m| disparities(m, &tracks));
    let worse = match &after {
        Some(after) => {
            let all = |d: &[Vec<(Point3<f64>, Vector2<f64>)>]| {
                rms(&d.iter().flatten().map(|(_, v)| *v).collect::<Vec<_>>())
            };
            all(after) > all(&before)
        }
        None => true,
    };
    if outcome == Outcome::Diverged || worse {
        let message = message.or(Some(
            "the refined calibration reprojects the particles worse than the input one".into(),
        ));
        return diverged(
            &start,
            frame_count,
            volume,
            options,
            &gauge,
            reports,
            message,
        );
    }
    let after = after.unwrap_or_default();
    let cameras_report = (0..start.len())
        .map(|c| {
            let points: Vec<Point3<f64>> = after[c].iter().map(|(p, _)| *p).collect();
            let db: Vec<Vector2<f64>> = before[c].iter().map(|(_, v)| *v).collect();
            let da: Vec<Vector2<f64>> = after[c].iter().map(|(_, v)| *v).collect();
            let points_before: Vec<Point3<f64>> = before[c].iter().map(|(p, _)| *p).collect();
            CameraSelfCalibration {
                name: start[c].name.clone(),
                before: DisparityStats::of(&db),
                after: DisparityStats::of(&da),
                map_before: DisparityMap::of(&volume, options.grid, &points_before, &db),
                map_after: DisparityMap::of(&volume, options.grid, &points, &da),
                parameters: parameter_changes(c, &start[c], &state, fixed, &solution, sigma0),
                glass_vector_mm: state.cameras[c].media.glass_vector.into(),
                glass_vector_reason: glass_vector_reason(c, &state),
            }
        })
        .collect();
    let media = media_changes(media_all, &start, &state, Some((&solution, sigma0)));
    let report = SelfCalibrationReport {
        outcome,
        message,
        frames: frame_count,
        volume,
        grid: options.grid,
        sigma0_px: sigma0,
        rounds: reports,
        cameras: cameras_report,
        media,
        gauge: gauge_report(&gauge, &start, &state.cameras),
    };
    SelfCalibration {
        cameras: state.cameras,
        report,
    }
}

/// Why the glass vector is not adjusted when not asked for.
const GLASS_VECTOR_HELD: &str = "held at the input's value: not among the adjusted terms \
    (`--free glass` adjusts it, per wall, where the particles determine it)";

/// Whether camera `c`'s glass vector was adjusted, or why not.
fn glass_vector_reason(c: usize, state: &State) -> String {
    let glass = |m: &MediaUnknown| m.term == MediaTerm::Glass && m.cameras.contains(&c);
    if state.media.iter().any(glass) {
        let held: Vec<String> = state
            .media_held
            .iter()
            .filter(|(m, _)| glass(m))
            .map(|(m, r)| format!("{} held: {r}", m.name()))
            .collect();
        if held.is_empty() {
            "adjusted (see the report's media)".into()
        } else {
            format!("adjusted, except: {}", held.join("; "))
        }
    } else if state.media_held.iter().any(|(m, _)| glass(m)) {
        let reasons: Vec<String> = state
            .media_held
            .iter()
            .filter(|(m, _)| glass(m))
            .map(|(m, r)| format!("{} held: {r}", m.name()))
            .collect();
        reasons.join("; ")
    } else {
        GLASS_VECTOR_HELD.into()
    }
}

/// Each media unknown asked for: its change, sigma and status.
fn media_changes(
    all: &[MediaUnknown],
    start: &[CameraParameters],
    state: &State,
    solution: Option<(&bundle::Solution, f64)>,
) -> Vec<MediaChange> {
    all.iter()
        .map(|m| {
            let c0 = m.cameras[0];
            let before = m.value(&start[c0]);
            let after = m.value(&state.cameras[c0]);
            let free = state.media.iter().position(|q| q == m);
            let (status, sigma, reason) = match (free, solution) {
                (Some(k), Some((solution, sigma0))) => {
                    let i = solution.media_offset + k;
                    let sigma = solution
                        .cofactor
                        .as_ref()
                        .map(|q| sigma0 * q[(i, i)].max(0.0).sqrt());
                    (ParameterStatus::Free, sigma, None)
                }
                _ => {
                    let reason = state
                        .media_held
                        .iter()
                        .find(|(h, _)| h == m)
                        .map(|(_, r)| r.clone())
                        .or_else(|| Some("the adjustment diverged: the input is kept".into()));
                    (ParameterStatus::Held, None, reason)
                }
            };
            MediaChange {
                name: m.name(),
                cameras: m.cameras.iter().map(|c| c + 1).collect(),
                before,
                after,
                change: after - before,
                sigma,
                status,
                reason,
            }
        })
        .collect()
}

/// Bands wider than this (px) vote ([`vote`]) rather than match: in them
/// the matcher's best-fitting groups are mostly ghosts.
const VOTE_ABOVE_PX: f64 = 1.0;

type Matched = (Vec<Track>, Vec<usize>, usize);

/// The confident particles of every frame matched with `band`, as tracks;
/// the particles matched by camera count; the confident ones.
#[allow(clippy::too_many_arguments)]
fn matched_tracks(
    frames: &[Vec<Vec<Target>>],
    models: &[Camera],
    band: f64,
    min_cameras: usize,
    volume: &Volume,
    options: &SelfCalibrationOptions,
    cancel: &Cancel,
    progress: &mut dyn FnMut(usize),
) -> Result<Matched, SelfCalibrationError> {
    let matcher = Matcher::new(models, &matching(band, options)).map_err(|source| {
        SelfCalibrationError::Matching {
            band_px: band,
            source,
        }
    })?;
    let mut matched_by_cameras = vec![0; models.len() + 1];
    let mut candidates: Vec<Candidate> = Vec::new();
    for (f, frame) in frames.iter().enumerate() {
        cancel.check()?;
        let particles = matcher
            .match_frame_until(frame, cancel)
            .map_err(|e| match e {
                MatchError::Cancelled(c) => SelfCalibrationError::Cancelled(c),
                source => SelfCalibrationError::Matching {
                    band_px: band,
                    source,
                },
            })?;
        let crowded = crowded_targets(frame, options.isolation_px);
        for p in &particles {
            matched_by_cameras[p.camera_count()] += 1;
            if confident(p, &crowded, min_cameras) {
                candidates.push(Candidate {
                    frame: f,
                    particle: p.clone(),
                });
            }
        }
        progress(f + 1);
    }
    let candidate_count = candidates.len();
    let selected = select(candidates, volume, options);
    let tracks = selected
        .iter()
        .map(|c| Track {
            observations: c
                .particle
                .targets
                .iter()
                .enumerate()
                .filter_map(|(cam, t)| {
                    t.map(|t| {
                        let target = &frames[c.frame][cam][t];
                        (cam, Point2::new(target.x, target.y), 1.0)
                    })
                })
                .collect(),
            point: c.particle.position,
        })
        .collect();
    Ok((tracks, matched_by_cameras, candidate_count))
}

/// The cameras, their free parameters and the held ones as the adjustment
/// goes.
struct State {
    cameras: Vec<CameraParameters>,
    free: Vec<ParameterSet>,
    held: Vec<Vec<(Parameter, String)>>,
    /// The media unknowns being adjusted.
    media: Vec<MediaUnknown>,
    /// The media unknowns held, with the reason.
    media_held: Vec<(MediaUnknown, String)>,
}

/// A matched particle of one frame.
struct Candidate {
    frame: usize,
    particle: Particle,
}

fn matching(band: f64, options: &SelfCalibrationOptions) -> MatchingParameters {
    MatchingParameters {
        tolerance: band,
        volume: options.volume,
        min_cameras: 2,
        similarity: None,
    }
}

fn models(cameras: &[CameraParameters]) -> Result<Vec<Camera>, SelfCalibrationError> {
    cameras
        .iter()
        .enumerate()
        .map(|(camera, p)| {
            Camera::new(p.clone())
                .map_err(|source| SelfCalibrationError::InvalidCamera { camera, source })
        })
        .collect()
}

fn models_or_diverged(cameras: &[CameraParameters]) -> Option<Vec<Camera>> {
    cameras
        .iter()
        .map(|p| Camera::new(p.clone()).ok())
        .collect()
}

/// Per camera of a frame, which targets have another within `radius` px.
fn crowded_targets(frame: &[Vec<Target>], radius: f64) -> Vec<Vec<bool>> {
    frame
        .iter()
        .map(|targets| {
            let mut order: Vec<usize> = (0..targets.len()).collect();
            order.sort_by(|&a, &b| targets[a].x.total_cmp(&targets[b].x));
            let mut crowded = vec![false; targets.len()];
            for (k, &i) in order.iter().enumerate() {
                for &j in &order[k + 1..] {
                    if targets[j].x - targets[i].x > radius {
                        break;
                    }
                    let d = (targets[j].x - targets[i].x).hypot(targets[j].y - targets[i].y);
                    if d <= radius {
                        crowded[i] = true;
                        crowded[j] = true;
                    }
                }
            }
            crowded
        })
        .collect()
}

fn confident(p: &Particle, crowded: &[Vec<bool>], min_cameras: usize) -> bool {
    p.camera_count() >= min_cameras
        && p.targets
            .iter()
            .enumerate()
            .all(|(c, t)| t.map_or(true, |t| !crowded[c][t]))
}

/// At most `max_particles / cells` per sub-volume, the most cameras and
/// then the best fitting first.
fn select(
    mut candidates: Vec<Candidate>,
    volume: &Volume,
    options: &SelfCalibrationOptions,
) -> Vec<Candidate> {
    let grid = options.grid;
    let cells = grid[0] * grid[1] * grid[2];
    let cap = options.max_particles.div_ceil(cells).max(1);
    candidates.sort_by(|a, b| {
        b.particle
            .camera_count()
            .cmp(&a.particle.camera_count())
            .then(a.particle.rms_px.total_cmp(&b.particle.rms_px))
    });
    let mut filled = vec![0usize; cells];
    candidates
        .into_iter()
        .filter(|c| {
            let cell = report::flat(grid, report::cell_of(volume, grid, &c.particle.position));
            filled[cell] += 1;
            filled[cell] <= cap
        })
        .take(options.max_particles)
        .collect()
}

fn residual_vectors(models: &[Camera], tracks: &[Track]) -> Vec<Vector2<f64>> {
    residuals(models, tracks)
        .into_iter()
        .flatten()
        .flatten()
        .collect()
}

fn rms(d: &[Vector2<f64>]) -> f64 {
    if d.is_empty() {
        return 0.0;
    }
    (d.iter().map(|v| v.norm_squared()).sum::<f64>() / d.len() as f64).sqrt()
}

/// The robust scale per coordinate of 2D residuals: the median length over
/// the Rayleigh median `sqrt(2 ln 2)` (1.1774).
fn robust_sigma(r: &[Vector2<f64>]) -> f64 {
    let mut lengths: Vec<f64> = r.iter().map(|v| v.norm()).collect();
    lengths.sort_by(f64::total_cmp);
    report::median_sorted(&lengths) / (2.0 * std::f64::consts::LN_2).sqrt()
}

/// Huber's weights at this many sigma.
const HUBER_K: f64 = 2.0;
/// A particle with a residual beyond this many sigma is a wrong match.
const REJECT_K: f64 = 5.0;
/// Most passes of the robust loop (reweighting, rejection, holding).
const MAX_PASSES: usize = 12;

type Adjusted = (Vec<Track>, bundle::Solution, usize, f64);

/// The bundle adjustment with reweighting, rejection of wrong matches and
/// holding of undeterminable parameters; `None` if it diverged.
fn robust_adjustment(
    state: &mut State,
    mut tracks: Vec<Track>,
    gauge: &Gauge,
    start: &[CameraParameters],
    options: &SelfCalibrationOptions,
    cancel: &Cancel,
) -> Result<Option<Adjusted>, SelfCalibrationError> {
    let mut rejected = 0;
    let mut iterations = 0;
    let mut previous_sigma = f64::INFINITY;
    for pass in 0..MAX_PASSES {
        cancel.check()?;
        let mut bundle = Bundle {
            cameras: state.cameras.clone(),
            free: state.free.clone(),
            tracks,
            gauge,
            media: state.media.clone(),
        };
        let Some(mut solution) = bundle.adjust(30) else {
            return Ok(None);
        };
        iterations += solution.iterations;
        solution.iterations = iterations;
        state.cameras = bundle.cameras;
        tracks = bundle.tracks;
        let Some(models) = models_or_diverged(&state.cameras) else {
            return Ok(None);
        };
        let res = residuals(&models, &tracks);
        let flat: Vec<Vector2<f64>> = res.iter().flatten().flatten().copied().collect();
        let sigma = robust_sigma(&flat).max(1e-6);
        // Hold what the data cannot determine, one parameter per camera.
        let held = hold_undeterminable(state, &solution, start, options.max_correlation);
        // Reject wrong matches, reweight the rest.
        let before = tracks.len();
        let kept: Vec<Track> = tracks
            .into_iter()
            .zip(&res)
            .filter(|(_, r)| {
                r.iter()
                    .all(|v| v.is_some_and(|v| v.norm() <= REJECT_K * sigma))
            })
            .map(|(t, r)| huber_weighted(t, r, sigma))
            .collect();
        let dropped = before - kept.len();
        rejected += dropped;
        tracks = kept;
        let settled = (previous_sigma - sigma).abs() <= 0.01 * sigma;
        previous_sigma = sigma;
        if !held && dropped == 0 && (settled || pass + 1 == MAX_PASSES) {
            return Ok(Some((tracks, solution, rejected, sigma)));
        }
        if tracks.len() < MIN_PARTICLES {
            return Ok(None);
        }
    }
    // The passes ran out: one last adjustment with the final weights.
    let mut bundle = Bundle {
        cameras: state.cameras.clone(),
        free: state.free.clone(),
        tracks,
        gauge,
        media: state.media.clone(),
    };
    let Some(mut solution) = bundle.adjust(30) else {
        return Ok(None);
    };
    solution.iterations += iterations;
    state.cameras = bundle.cameras;
    Ok(Some((bundle.tracks, solution, rejected, previous_sigma)))
}

/// `track` with each observation's Huber weight at `sigma`: 1 within
/// `HUBER_K` sigma, `HUBER_K sigma / |v|` beyond, 0 where it does not image.
fn huber_weighted(mut track: Track, residuals: &[Option<Vector2<f64>>], sigma: f64) -> Track {
    for (o, v) in track.observations.iter_mut().zip(residuals) {
        let length = v.map_or(f64::INFINITY, |v| v.norm());
        o.2 = if length <= HUBER_K * sigma {
            1.0
        } else {
            HUBER_K * sigma / length
        };
    }
    track
}

/// Per camera, holds the parameter the data determine least (singular
/// block, or a correlation above the limit), by the calibration's rule,
/// judged on the camera's block of the reduced normal matrix; whether any
/// was held.
fn hold_undeterminable(
    state: &mut State,
    solution: &bundle::Solution,
    start: &[CameraParameters],
    max_correlation: f64,
) -> bool {
    let mut any = false;
    for (c, setup) in start.iter().enumerate() {
        let u = state.free[c].len();
        if u == 0 {
            continue;
        }
        let off = solution.offsets[c];
        let block = solution.reduced.view((off, off), (u, u)).into_owned();
        let diag: Vec<f64> = (0..u)
            .map(|k| {
                let d = block[(k, k)];
                if d > 0.0 {
                    1.0 / d.sqrt()
                } else {
                    0.0
                }
            })
            .collect();
        let scaled_normal = DMatrix::from_fn(u, u, |i, j| block[(i, j)] * diag[i] * diag[j]);
        let cofactor = block.clone().cholesky().map(|ch| ch.inverse());
        let stats = Statistics {
            residuals: Vec::new(),
            sigma0: 1.0,
            redundancy: solution.redundancy,
            cofactor,
            scaled_normal,
            normal: block.clone(),
            test: Vec::new(),
        };
        if let Some((p, reason)) = undeterminable(&stats, state.free[c], max_correlation, true) {
            state.free[c].remove(p);
            if ParameterSet::distortion().contains(p) {
                let mut v = to_vector(&state.cameras[c]);
                v[p.index()] = to_vector(setup)[p.index()];
                state.cameras[c] = from_vector(&state.cameras[c], &v);
            }
            state.held[c].push((p, reason));
            any = true;
        }
    }
    if let Some((k, reason)) = undeterminable_media(state, solution, max_correlation) {
        let m = state.media.remove(k);
        // Back to the input's value.
        for &c in &m.cameras {
            let delta = m.value(&start[c]) - m.value(&state.cameras[c]);
            m.apply(&mut state.cameras[c], delta);
        }
        state.media_held.push((m, reason));
        any = true;
    }
    any
}

/// The media unknown the data determine least, by `calibrate`'s rule: a
/// singular block of the reduced normal matrix (the media given the
/// cameras), or a correlation above the limit within it; and, since a
/// wall's position and the indices trade against the cameras' positions
/// and principal distances, a correlation above the limit with any camera
/// parameter under the gauge constraints (the cofactor matrix), or no
/// regular cofactor matrix at all. The index and the reason.
fn undeterminable_media(
    state: &State,
    solution: &bundle::Solution,
    max_correlation: f64,
) -> Option<(usize, String)> {
    let m = state.media.len();
    if m == 0 {
        return None;
    }
    let off = solution.media_offset;
    let block = solution.reduced.view((off, off), (m, m)).into_owned();
    if let Some(k) =
        (0..m).find(|&k| block[(k, k)].partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater))
    {
        return Some((k, "the particles do not constrain it (zero normal)".into()));
    }
    let d: Vec<f64> = (0..m).map(|k| 1.0 / block[(k, k)].sqrt()).collect();
    let scaled = DMatrix::from_fn(m, m, |i, j| block[(i, j)] * d[i] * d[j]);
    let Some(inverse) = scaled.cholesky().map(|ch| ch.inverse()) else {
        return Some((
            m - 1,
            "singular normal matrix with the other media terms".into(),
        ));
    };
    let mut worst: Option<(f64, usize, String)> = None;
    for i in 0..m {
        for j in 0..i {
            let r = inverse[(i, j)] / (inverse[(i, i)] * inverse[(j, j)]).sqrt();
            if r.abs() > max_correlation && worst.as_ref().map_or(true, |w| r.abs() > w.0) {
                worst = Some((r.abs(), i, state.media[j].name()));
            }
        }
    }
    if let Some((r, i, other)) = worst {
        return Some((
            i,
            format!("correlation {r:.4} with {other} (limit {max_correlation})"),
        ));
    }
    let Some(q) = &solution.cofactor else {
        return Some((m - 1, "the adjustment's cofactor matrix is singular".into()));
    };
    let mut worst: Option<(f64, usize, String)> = None;
    for k in 0..m {
        let i = off + k;
        for (c, free) in state.free.iter().enumerate() {
            for (col, p) in free.iter().enumerate() {
                let j = solution.offsets[c] + col;
                let r = q[(i, j)] / (q[(i, i)] * q[(j, j)]).sqrt();
                if r.abs() > max_correlation && worst.as_ref().map_or(true, |w| r.abs() > w.0) {
                    worst = Some((r.abs(), k, format!("camera {}'s {}", c + 1, p.name())));
                }
            }
        }
    }
    worst.map(|(r, k, other)| {
        (
            k,
            format!("correlation {r:.4} with {other} under the gauge (limit {max_correlation})"),
        )
    })
}

/// Per camera, each track's point (intersected with `models` from all its
/// observations) and the camera's disparity.
fn disparities(models: &[Camera], tracks: &[Track]) -> Vec<Vec<(Point3<f64>, Vector2<f64>)>> {
    let mut out = vec![Vec::new(); models.len()];
    for t in tracks {
        let observations: Vec<Observation> = t
            .observations
            .iter()
            .map(|&(camera, pixel, _)| Observation { camera, pixel })
            .collect();
        if let Ok(x) = intersect(models, &observations) {
            for (o, r) in observations.iter().zip(&x.residuals_px) {
                out[o.camera].push((x.point, *r));
            }
        }
    }
    out
}

fn parameter_changes(
    c: usize,
    start: &CameraParameters,
    state: &State,
    fixed: ParameterSet,
    solution: &bundle::Solution,
    sigma0: f64,
) -> Vec<ParameterChange> {
    let before = to_vector(start);
    let after = to_vector(&state.cameras[c]);
    let free = state.free[c];
    Parameter::ALL
        .iter()
        .map(|&p| {
            let (status, sigma, reason) = if free.contains(p) {
                let k = free.iter().position(|q| q == p).unwrap_or(0);
                let i = solution.offsets[c] + k;
                let sigma = solution
                    .cofactor
                    .as_ref()
                    .map(|q| sigma0 * q[(i, i)].max(0.0).sqrt());
                (ParameterStatus::Free, sigma, None)
            } else if fixed.contains(p) {
                (ParameterStatus::Fixed, None, None)
            } else {
                let reason = state.held[c]
                    .iter()
                    .find(|(h, _)| *h == p)
                    .map(|(_, r)| r.clone());
                (ParameterStatus::Held, None, reason)
            };
            ParameterChange {
                name: p,
                before: before[p.index()],
                after: after[p.index()],
                change: after[p.index()] - before[p.index()],
                sigma,
                status,
                reason,
            }
        })
        .collect()
}

fn gauge_report(
    gauge: &Gauge,
    start: &[CameraParameters],
    after: &[CameraParameters],
) -> GaugeReport {
    let n = start.len().max(1) as f64;
    let centroid = |c: &[CameraParameters]| {
        c.iter()
            .map(|p| p.exterior.position)
            .sum::<nalgebra::Vector3<f64>>()
            / n
    };
    let moved = start
        .iter()
        .zip(after)
        .map(|(a, b)| (a.exterior.position - b.exterior.position).norm_squared())
        .sum::<f64>();
    GaugeReport {
        method: if gauge.constrained {
            "inner constraints on the cameras' exterior orientation: the change from the input \
             calibration has no component along the 7 similarity motions of the rig (3 \
             translations, 3 rotations about the cameras' centroid, a scaling about it), angles \
             weighed as displacements at the reference length: the least change of camera \
             positions and orientations, the scale of the input's baselines kept (to first \
             order)"
                .into()
        } else {
            "by the exterior parameters the user fixed (no constraint added)".into()
        },
        reference_length_mm: gauge.length,
        baseline_rms_before_mm: baseline_scale(start),
        baseline_rms_after_mm: baseline_scale(after),
        centroid_shift_mm: (centroid(start) - centroid(after)).norm(),
        position_change_rms_mm: (moved / n).sqrt(),
    }
}

fn diverged(
    start: &[CameraParameters],
    frames: usize,
    volume: Volume,
    options: &SelfCalibrationOptions,
    gauge: &Gauge,
    rounds: Vec<RoundReport>,
    message: Option<String>,
) -> SelfCalibration {
    let cameras = start
        .iter()
        .map(|p| {
            let v = to_vector(p);
            CameraSelfCalibration {
                name: p.name.clone(),
                before: DisparityStats::default(),
                after: DisparityStats::default(),
                map_before: DisparityMap::default(),
                map_after: DisparityMap::default(),
                parameters: Parameter::ALL
                    .iter()
                    .map(|&q| ParameterChange {
                        name: q,
                        before: v[q.index()],
                        after: v[q.index()],
                        change: 0.0,
                        sigma: None,
                        status: ParameterStatus::Held,
                        reason: Some("the adjustment diverged: the input is kept".into()),
                    })
                    .collect(),
                glass_vector_mm: p.media.glass_vector.into(),
                glass_vector_reason: GLASS_VECTOR_HELD.into(),
            }
        })
        .collect();
    let all = media_unknowns(start, &options.free_media);
    let state = State {
        cameras: start.to_vec(),
        free: Vec::new(),
        held: Vec::new(),
        media: Vec::new(),
        media_held: Vec::new(),
    };
    let media = media_changes(&all, start, &state, None);
    SelfCalibration {
        cameras: start.to_vec(),
        report: SelfCalibrationReport {
            outcome: Outcome::Diverged,
            message,
            frames,
            volume,
            grid: options.grid,
            sigma0_px: 0.0,
            rounds,
            cameras,
            media,
            gauge: gauge_report(gauge, start, start),
        },
    }
}
