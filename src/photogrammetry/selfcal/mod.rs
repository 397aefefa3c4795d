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
mod options;
pub mod report;
mod robust;
mod selection;
mod vote;
pub mod wand;

use nalgebra::{Point3, Vector2};

use crate::photogrammetry::calibrate::adjustment::to_vector;
use crate::photogrammetry::calibrate::{Parameter, ParameterSet, ParameterStatus};
use crate::photogrammetry::camera::{Camera, CameraParameters};
use crate::photogrammetry::cancel::Cancel;
use crate::photogrammetry::correspond::Matcher;
use crate::photogrammetry::intersect::{intersect, Observation};
use crate::photogrammetry::target::Target;
use crate::photogrammetry::volume::Volume;
pub use bundle::MediaTerm;
use bundle::{media_unknowns, MediaUnknown, Track};
use gauge::{baseline_scale, Gauge};
pub use options::{
    default_fixed, Progress, SelfCalibrationError, SelfCalibrationOptions, MIN_PARTICLES,
};
pub use report::{
    CameraSelfCalibration, DisparityCell, DisparityMap, DisparityStats, GaugeReport, MediaChange,
    Outcome, ParameterChange, RoundReport, SelfCalibrationReport,
};
use robust::{residual_vectors, rms, robust_adjustment};
use selection::{matched_tracks, matching, models, models_or_diverged, Matched, VOTE_ABOVE_PX};

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
