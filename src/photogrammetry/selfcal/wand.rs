//! Wand (dumbbell) calibration: a bar with two marks a known distance
//! apart, moved through the whole observation volume, each position seen by
//! every camera. It reaches the corners of the volume where a plate does
//! not, and its length gives the scale.
//!
//! The problem is self-calibration's (the module above) with two
//! differences: the correspondences are known up to the order of the two
//! marks in each image, and the scale (the seventh degree of freedom of the
//! gauge, which image coordinates do not fix) comes from the wand instead of
//! the starting rig's baselines. pyptv's dumbbell calibration, MyPTV and
//! OpenLPT do the same with a penalty on each wand's length; here the
//! length fixes the scale only, and the spread of the adjusted wands'
//! lengths is left free as the calibration's check (Maas 1992's bar-length
//! test of a photogrammetric network).
//!
//! 1. **Marks**: per frame and camera the two brightest targets (largest
//!    sum of grey, then most pixels); a frame where a camera has fewer is
//!    incomplete and skipped.
//! 2. **Pairing**: camera 1's first mark is end A; of the 2^(n-1) ways the
//!    other cameras' marks can be A and B, the one whose two intersections
//!    (with the starting rig) reproject best. A position whose second-best
//!    pairing reprojects within twice the best's RMS is ambiguous (the wand
//!    lies along an epipolar line) and skipped.
//! 3. **Scale check**: the median length of the wands intersected with the
//!    starting rig must be within [`WandOptions::max_scale_change`] of the
//!    given length, or the length (or its unit) disagrees with the data:
//!    an error. Then the rig is scaled about the volume's centre to the
//!    wand's length.
//! 4. **Adjustment**: the bundle adjustment of self-calibration (`bundle.rs`:
//!    Levenberg-Marquardt on the normal equations reduced to the cameras, the
//!    refraction inside the model, the collinearity equations Eq. 1-12 of
//!    the design paper), the wands' ends as its points, the gauge's inner
//!    constraints keeping the rig's position, orientation and baselines
//!    (`gauge.rs`). After each adjustment the rig and the points are scaled
//!    about the volume's centre so that the wands' mean length is the given
//!    one, and the gauge re-anchored there; without refraction this is
//!    exact (a similarity changes no image coordinate), with it the next
//!    adjustment absorbs the walls' share, and the passes repeat until the
//!    scale moves by less than 1e-7.
//! 5. **Gross errors**: Huber weights at 2 sigma, and a wand with any
//!    residual beyond 5 sigma (sigma the residuals' robust scale; 15 sigma
//!    until that scale has settled, while the rig still moves) removed
//!    whole (a wrong pairing, a reflection taken for a mark), as in
//!    self-calibration's robust loop; parameters the wands do not determine
//!    are held by the calibration's rule.
//!
//! The report gives the reprojection per camera, each parameter's change
//! with its sigma, and the spread of the adjusted wands' lengths.

use nalgebra::{Point2, Point3, Vector2};
use serde::Serialize;

use super::bundle::{residuals, Bundle, Solution, Track};
use super::gauge::Gauge;
use super::report::{median_sorted, ParameterChange};
use super::robust::{hold_undeterminable, huber_weighted, robust_sigma, REJECT_K};
use super::{parameter_changes, State};
use crate::photogrammetry::calibrate::{Parameter, ParameterSet};
use crate::photogrammetry::camera::{Camera, CameraParameters, InvalidCamera};
use crate::photogrammetry::cancel::{Cancel, Cancelled};
use crate::photogrammetry::intersect::{intersect, Observation};
use crate::photogrammetry::target::Target;

/// The fewest usable wand positions: each gives two points, so 50 give
/// self-calibration's least particle count ([`super::MIN_PARTICLES`], 100)
/// for the 4 x 16 camera unknowns with redundancy left to judge them.
/// Labs record 200-2,000.
pub const MIN_POSITIONS: usize = 50;

/// Most passes of the robust loop (reweighting, rejection, holding, scale).
const MAX_PASSES: usize = 20;

/// How to calibrate with a wand.
#[derive(Clone, Debug, PartialEq)]
pub struct WandOptions {
    /// The distance between the wand's two marks (mm).
    pub length_mm: f64,
    /// Parameters held at the start's values in every camera.
    pub fixed: Vec<Parameter>,
    /// Parameters correlated above this are held (one of the pair).
    pub max_correlation: f64,
    /// The largest relative difference allowed between the wand length
    /// measured with the starting rig and the given one (0.2: a rough rig
    /// measured with a tape, or a plate calibration, is better than 20%;
    /// a wrong unit or a different wand is not).
    pub max_scale_change: f64,
}

impl WandOptions {
    /// Every parameter free (those the wands do not determine are held),
    /// the wand `length_mm` long.
    pub fn new(length_mm: f64) -> WandOptions {
        WandOptions {
            length_mm,
            fixed: Vec::new(),
            max_correlation: 0.99,
            max_scale_change: 0.2,
        }
    }
}

/// Why a wand calibration cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WandError {
    /// Too few or too many cameras.
    #[error("wand calibration needs 2 to {max} cameras, the calibration has {0}", max = crate::photogrammetry::correspond::MAX_CAMERAS)]
    TooFewCameras(usize),
    /// A camera of the start is not a camera.
    #[error("camera {camera} of the starting calibration: {source}")]
    InvalidCamera {
        /// The camera (0-based).
        camera: usize,
        /// What is wrong.
        #[source]
        source: InvalidCamera,
    },
    /// The length is not a positive number.
    #[error("the wand length must be a positive number of millimetres, got {0}")]
    InvalidLength(f64),
    /// An option out of range.
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// A frame's target lists are not one per camera.
    #[error("wand frame {frame} has target lists for {given} cameras, but the calibration has {cameras}; give one list per camera, in camera order")]
    CameraCount {
        /// The frame (0-based).
        frame: usize,
        /// Lists given.
        given: usize,
        /// Cameras.
        cameras: usize,
    },
    /// Too few usable positions.
    #[error("only {usable} usable wand positions in {frames} frames ({incomplete} without two marks in every camera, {ambiguous} with an ambiguous pairing, {rejected} removed as gross errors); wand calibration needs at least {needed}: record more positions spread through the whole volume (200-2,000 are usual), with both marks visible to every camera")]
    TooFewPositions {
        /// Positions left.
        usable: usize,
        /// Frames given.
        frames: usize,
        /// Frames without two marks in some camera.
        incomplete: usize,
        /// Ambiguous pairings.
        ambiguous: usize,
        /// Removed by the robust loop.
        rejected: usize,
        /// The least.
        needed: usize,
    },
    /// The given length disagrees with the data.
    #[error("the wand's marks, intersected with the starting calibration, are {measured_mm:.3} mm apart (median of {positions} positions), but the wand length given is {given_mm} mm ({percent:+.1}%; at most {limit_percent:.0}% is allowed): check the length and its unit (mm), or start from a calibration with the right scale")]
    LengthDisagrees {
        /// The given length (mm).
        given_mm: f64,
        /// The median measured with the start (mm).
        measured_mm: f64,
        /// Positions measured.
        positions: usize,
        /// `given / measured - 1` in percent.
        percent: f64,
        /// The limit in percent.
        limit_percent: f64,
    },
    /// The adjustment failed.
    #[error("the wand bundle adjustment did not converge ({0}); start from a closer calibration (a plate calibration), or check that the frames show the wand")]
    Diverged(String),
    /// Stopped by its cancel token.
    #[error("wand calibration {0}")]
    Cancelled(#[from] Cancelled),
}

/// The calibrated rig and the report.
#[derive(Clone, Debug, PartialEq)]
pub struct WandCalibration {
    /// The calibrated cameras, in the start's order.
    pub cameras: Vec<CameraParameters>,
    /// What was done.
    pub report: WandReport,
    /// The adjusted wands' ends (mm), per used position, with the frame.
    pub wands: Vec<AdjustedWand>,
}

/// One used wand position after the adjustment.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AdjustedWand {
    /// The frame (0-based in the input).
    pub frame: usize,
    /// End A (camera 1's first mark) (mm).
    pub a: Point3<f64>,
    /// End B (mm).
    pub b: Point3<f64>,
}

/// The spread of the wand's length.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct LengthSpread {
    /// Positions.
    pub count: usize,
    /// Mean (mm).
    pub mean_mm: f64,
    /// Standard deviation (mm).
    pub std_mm: f64,
    /// Smallest and largest (mm).
    pub min_mm: f64,
    /// Largest (mm).
    pub max_mm: f64,
    /// Median (mm).
    pub median_mm: f64,
}

impl LengthSpread {
    /// The statistics of `lengths`.
    pub fn of(lengths: &[f64]) -> LengthSpread {
        if lengths.is_empty() {
            return LengthSpread::default();
        }
        let n = lengths.len() as f64;
        let mean = lengths.iter().sum::<f64>() / n;
        let var = lengths.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
        let mut sorted = lengths.to_vec();
        sorted.sort_by(f64::total_cmp);
        LengthSpread {
            count: lengths.len(),
            mean_mm: mean,
            std_mm: var.sqrt(),
            min_mm: sorted[0],
            max_mm: sorted[sorted.len() - 1],
            median_mm: median_sorted(&sorted),
        }
    }
}

/// One camera's wand calibration.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct WandCamera {
    /// The camera's name.
    pub name: String,
    /// RMS reprojection of the used wands' marks with the start (px),
    /// each end intersected with the starting rig.
    pub rms_before_px: f64,
    /// RMS reprojection after (px), the adjusted ends.
    pub rms_after_px: f64,
    /// The 16 parameters.
    pub parameters: Vec<ParameterChange>,
}

/// What a wand calibration did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct WandReport {
    /// Frames given.
    pub frames: usize,
    /// Frames without two marks in every camera (skipped).
    pub incomplete: usize,
    /// Positions with an ambiguous pairing (skipped).
    pub ambiguous: usize,
    /// Positions removed as gross errors by the robust loop.
    pub rejected: usize,
    /// Positions used.
    pub positions: usize,
    /// The given length (mm).
    pub length_mm: f64,
    /// The wands' lengths intersected with the starting rig.
    pub length_before: LengthSpread,
    /// The adjusted wands' lengths (mean = the given length).
    pub length_after: LengthSpread,
    /// The factor the starting rig's scale was multiplied by.
    pub scale_factor: f64,
    /// A posteriori standard deviation of unit weight (px).
    pub sigma0_px: f64,
    /// RMS reprojection of every used mark (px).
    pub rms_px: f64,
    /// Passes of the robust loop.
    pub passes: usize,
    /// Per camera.
    pub cameras: Vec<WandCamera>,
}

/// One wand position's marks per camera, `[A, B]` in camera order.
type Pairing = Vec<[Point2<f64>; 2]>;

/// Checks the inputs cheaply, with the same errors as [`wand_calibrate`].
pub fn check_inputs(
    cameras: &[CameraParameters],
    frames: &[Vec<Vec<Target>>],
    options: &WandOptions,
) -> Result<(), WandError> {
    // The pairing tries 2^(cameras - 1) flips of the marks: bounded by the
    // cameras any calibration may have.
    if !(2..=crate::photogrammetry::correspond::MAX_CAMERAS).contains(&cameras.len()) {
        return Err(WandError::TooFewCameras(cameras.len()));
    }
    for (camera, p) in cameras.iter().enumerate() {
        Camera::new(p.clone()).map_err(|source| WandError::InvalidCamera { camera, source })?;
    }
    if !(options.length_mm > 0.0 && options.length_mm.is_finite()) {
        return Err(WandError::InvalidLength(options.length_mm));
    }
    if !(options.max_correlation > 0.0 && options.max_correlation <= 1.0) {
        return Err(WandError::InvalidOption(format!(
            "the correlation limit must be in (0, 1], got {}",
            options.max_correlation
        )));
    }
    if !(options.max_scale_change > 0.0 && options.max_scale_change < 1.0) {
        return Err(WandError::InvalidOption(format!(
            "the allowed scale change must be in (0, 1), got {}",
            options.max_scale_change
        )));
    }
    if let Some((frame, f)) = frames
        .iter()
        .enumerate()
        .find(|(_, f)| f.len() != cameras.len())
    {
        return Err(WandError::CameraCount {
            frame,
            given: f.len(),
            cameras: cameras.len(),
        });
    }
    if frames.len() < MIN_POSITIONS {
        // Not paired yet: at most every frame is a usable position.
        return Err(WandError::TooFewPositions {
            usable: frames.len(),
            frames: frames.len(),
            incomplete: 0,
            ambiguous: 0,
            rejected: 0,
            needed: MIN_POSITIONS,
        });
    }
    Ok(())
}

/// The two brightest marks of a camera's targets, or `None` with fewer.
fn two_marks(targets: &[Target]) -> Option<[Point2<f64>; 2]> {
    if targets.len() < 2 {
        return None;
    }
    let mut order: Vec<&Target> = targets.iter().collect();
    order.sort_by(|a, b| b.sumg.cmp(&a.sumg).then(b.n.cmp(&a.n)));
    Some([
        Point2::new(order[0].x, order[0].y),
        Point2::new(order[1].x, order[1].y),
    ])
}

/// The best pairing of one position's marks with `models`: the marks as
/// `[A, B]` per camera, the ends, and whether it is ambiguous.
fn pair(
    models: &[Camera],
    marks: &[[Point2<f64>; 2]],
) -> Option<(Pairing, [Point3<f64>; 2], bool)> {
    let n = marks.len();
    let mut scored: Vec<(f64, Pairing, [Point3<f64>; 2])> = Vec::new();
    for flips in 0..(1usize << (n - 1)) {
        let pairing: Pairing = marks
            .iter()
            .enumerate()
            .map(|(c, m)| {
                if c > 0 && flips & (1 << (c - 1)) != 0 {
                    [m[1], m[0]]
                } else {
                    *m
                }
            })
            .collect();
        let end = |e: usize| {
            let obs: Vec<Observation> = pairing
                .iter()
                .enumerate()
                .map(|(camera, m)| Observation {
                    camera,
                    pixel: m[e],
                })
                .collect();
            intersect(models, &obs).ok()
        };
        if let (Some(a), Some(b)) = (end(0), end(1)) {
            let cost = a.rms_px.powi(2) + b.rms_px.powi(2);
            scored.push((cost, pairing, [a.point, b.point]));
        }
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut it = scored.into_iter();
    let (best, pairing, ends) = it.next()?;
    // Within twice the RMS: four times the squares.
    let ambiguous = it.next().is_some_and(|(second, _, _)| second < 4.0 * best);
    Some((pairing, ends, ambiguous))
}

/// One position being adjusted.
struct Position {
    frame: usize,
    pairing: Pairing,
}

fn tracks_of(positions: &[Position], ends: &[[Point3<f64>; 2]]) -> Vec<Track> {
    positions
        .iter()
        .zip(ends)
        .flat_map(|(p, e)| {
            (0..2).map(move |k| Track {
                observations: p
                    .pairing
                    .iter()
                    .enumerate()
                    .map(|(c, m)| (c, m[k], 1.0))
                    .collect(),
                point: e[k],
            })
        })
        .collect()
}

fn lengths(tracks: &[Track]) -> Vec<f64> {
    tracks
        .chunks(2)
        .map(|w| (w[0].point - w[1].point).norm())
        .collect()
}

/// Scales the rig's positions and the points about `centre` by `s`.
fn scale_about(
    cameras: &mut [CameraParameters],
    tracks: &mut [Track],
    centre: &Point3<f64>,
    s: f64,
) {
    for p in cameras.iter_mut() {
        p.exterior.position = centre.coords + (p.exterior.position - centre.coords) * s;
    }
    for t in tracks.iter_mut() {
        t.point = centre + (t.point - centre) * s;
    }
}

fn models_of(cameras: &[CameraParameters]) -> Option<Vec<Camera>> {
    cameras
        .iter()
        .map(|p| Camera::new(p.clone()).ok())
        .collect()
}

/// Per camera the RMS of its residuals (px), and over all.
fn rms_per_camera(models: &[Camera], tracks: &[Track]) -> (Vec<f64>, f64) {
    let n = models.len();
    let mut sum = vec![0.0; n];
    let mut count = vec![0usize; n];
    for (t, r) in tracks.iter().zip(residuals(models, tracks)) {
        for (o, v) in t.observations.iter().zip(r) {
            if let Some(v) = v {
                sum[o.0] += v.norm_squared();
                count[o.0] += 1;
            }
        }
    }
    let all = (sum.iter().sum::<f64>() / count.iter().sum::<usize>().max(1) as f64).sqrt();
    let per = sum
        .iter()
        .zip(&count)
        .map(|(s, &c)| (s / c.max(1) as f64).sqrt())
        .collect();
    (per, all)
}

/// Calibrates `cameras` (a rough rig or a plate calibration) from the
/// wand's marks in `frames` (per frame, per camera, its targets): see the
/// module's documentation.
pub fn wand_calibrate(
    cameras: &[CameraParameters],
    frames: &[Vec<Vec<Target>>],
    options: &WandOptions,
    cancel: &Cancel,
) -> Result<WandCalibration, WandError> {
    check_inputs(cameras, frames, options)?;
    let (setup, mut wands) = Setup::new(cameras, frames, options, cancel)?;
    let mut state = State {
        cameras: setup.start.clone(),
        free: vec![setup.fixed.complement(); cameras.len()],
        held: vec![Vec::new(); cameras.len()],
        media: Vec::new(),
        media_held: Vec::new(),
    };
    let passes = run_passes(&setup, &mut state, &mut wands, options, cancel)?;
    finish(&setup, state, wands, passes, options)
}

/// What stays as it is through the passes (steps 1-3): the input rig, the
/// parameters the options hold, the wands' centre (the scaling's fixed
/// point), the counts of skipped frames and what the start measured.
struct Setup {
    start: Vec<CameraParameters>,
    fixed: ParameterSet,
    centre: Point3<f64>,
    frames: usize,
    incomplete: usize,
    ambiguous: usize,
    length_before: LengthSpread,
    rms_before: Vec<f64>,
}

/// The wand positions being adjusted and their ends as the bundle's tracks
/// (two per position: end A, end B).
struct Wands {
    positions: Vec<Position>,
    tracks: Vec<Track>,
}

/// What the passes (steps 4-5) left.
struct Passes {
    solution: Solution,
    scale_factor: f64,
    rejected: usize,
    passes: usize,
}

impl Setup {
    /// Steps 1-3: the marks, their pairing, the scale check.
    fn new(
        cameras: &[CameraParameters],
        frames: &[Vec<Vec<Target>>],
        options: &WandOptions,
        cancel: &Cancel,
    ) -> Result<(Setup, Wands), WandError> {
        let start = cameras.to_vec();
        let models =
            models_of(&start).ok_or_else(|| WandError::Diverged("invalid start".into()))?;
        let mut setup = Setup {
            start,
            fixed: options.fixed.iter().copied().collect(),
            centre: Point3::origin(),
            frames: frames.len(),
            incomplete: 0,
            ambiguous: 0,
            length_before: LengthSpread::default(),
            rms_before: Vec::new(),
        };
        let mut positions: Vec<Position> = Vec::new();
        let mut ends: Vec<[Point3<f64>; 2]> = Vec::new();
        for (frame, targets) in frames.iter().enumerate() {
            if frame % 64 == 0 {
                cancel.check()?;
            }
            let Some(marks) = targets
                .iter()
                .map(|t| two_marks(t))
                .collect::<Option<Vec<_>>>()
            else {
                setup.incomplete += 1;
                continue;
            };
            match pair(&models, &marks) {
                Some((_, _, true)) => setup.ambiguous += 1,
                Some((pairing, e, false)) => {
                    positions.push(Position { frame, pairing });
                    ends.push(e);
                }
                None => setup.incomplete += 1,
            }
        }
        if positions.len() < MIN_POSITIONS {
            return Err(setup.too_few(positions.len(), 0));
        }
        let tracks = tracks_of(&positions, &ends);
        setup.length_before = LengthSpread::of(&lengths(&tracks));
        let ratio = options.length_mm / setup.length_before.median_mm;
        if !ratio.is_finite() || (ratio - 1.0).abs() > options.max_scale_change {
            return Err(WandError::LengthDisagrees {
                given_mm: options.length_mm,
                measured_mm: setup.length_before.median_mm,
                positions: positions.len(),
                percent: 100.0 * (ratio - 1.0),
                limit_percent: 100.0 * options.max_scale_change,
            });
        }
        setup.centre = Point3::from(
            tracks
                .iter()
                .map(|t| t.point.coords)
                .sum::<nalgebra::Vector3<f64>>()
                / tracks.len() as f64,
        );
        setup.rms_before = rms_per_camera(&models, &tracks).0;
        Ok((setup, Wands { positions, tracks }))
    }

    /// The error of `usable` positions left, `rejected` by the passes.
    fn too_few(&self, usable: usize, rejected: usize) -> WandError {
        WandError::TooFewPositions {
            usable,
            frames: self.frames,
            incomplete: self.incomplete,
            ambiguous: self.ambiguous,
            rejected,
            needed: MIN_POSITIONS,
        }
    }
}

impl Wands {
    /// The wands' mean length (mm).
    fn mean_length(&self) -> f64 {
        lengths(&self.tracks).iter().sum::<f64>() / self.positions.len() as f64
    }

    /// Step 5's removal: the whole wand where either end has a residual
    /// beyond `limit` (px), the rest Huber-weighted at `sigma`; how many
    /// were removed.
    fn remove_gross_errors(
        &mut self,
        residuals: &[Vec<Option<Vector2<f64>>>],
        limit: f64,
        sigma: f64,
    ) -> usize {
        let before = self.positions.len();
        let mut kept_positions = Vec::with_capacity(before);
        let mut kept_tracks = Vec::with_capacity(self.tracks.len());
        for ((position, pair), r) in std::mem::take(&mut self.positions)
            .into_iter()
            .zip(self.tracks.chunks(2))
            .zip(residuals.chunks(2))
        {
            let good = r
                .iter()
                .flatten()
                .all(|v| v.is_some_and(|v| v.norm() <= limit));
            if !good {
                continue;
            }
            kept_positions.push(position);
            for (t, r) in pair.iter().zip(r) {
                kept_tracks.push(huber_weighted(t.clone(), r, sigma));
            }
        }
        self.positions = kept_positions;
        self.tracks = kept_tracks;
        before - self.positions.len()
    }
}

/// Step 4's adjustment and step 5, pass after pass, until nothing is held
/// or removed, the residuals' scale has settled twice and the wands' mean
/// length is the given one (or [`MAX_PASSES`]).
fn run_passes(
    setup: &Setup,
    state: &mut State,
    wands: &mut Wands,
    options: &WandOptions,
    cancel: &Cancel,
) -> Result<Passes, WandError> {
    let mut scale_factor = 1.0;
    let mut rejected = 0;
    let mut previous_sigma = f64::INFINITY;
    let mut settled_once = false;
    let mut passes = 0;
    loop {
        cancel.check()?;
        passes += 1;
        scale_factor *= scale_to_length(setup, state, wands, options.length_mm);
        let solution = adjust_pass(setup, state, wands, passes)?;
        let models = models_of(&state.cameras).ok_or_else(|| {
            WandError::Diverged(format!(
                "pass {passes}: the adjusted parameters are not a valid camera"
            ))
        })?;
        let res = residuals(&models, &wands.tracks);
        let flat: Vec<Vector2<f64>> = res.iter().flatten().flatten().copied().collect();
        let sigma = robust_sigma(&flat).max(1e-6);
        let held = hold_undeterminable(state, &solution, &setup.start, options.max_correlation);
        // Whole wands out where either end has a gross error. Until the
        // residuals' scale has settled the rig is still moving and the
        // volume's edges carry model error beyond 5 sigma (simulated: 29
        // good wands of 1,000 lost at the edges in the first pass), so
        // only the grossest (beyond 3 x 5 sigma) go then.
        let limit = if settled_once {
            REJECT_K
        } else {
            3.0 * REJECT_K
        };
        let dropped = wands.remove_gross_errors(&res, limit * sigma, sigma);
        rejected += dropped;
        if wands.positions.len() < MIN_POSITIONS {
            return Err(setup.too_few(wands.positions.len(), rejected));
        }
        let settled = (previous_sigma - sigma).abs() <= 0.01 * sigma;
        previous_sigma = sigma;
        let strict = settled_once;
        settled_once |= settled;
        let scaled = (options.length_mm / wands.mean_length() - 1.0).abs() < 1e-7;
        if (!held && dropped == 0 && settled && strict && scaled) || passes >= MAX_PASSES {
            return Ok(Passes {
                solution,
                scale_factor,
                rejected,
                passes,
            });
        }
    }
}

/// Scales the rig and the wands about the centre so that the wands' mean
/// length is `length_mm`; the factor.
fn scale_to_length(setup: &Setup, state: &mut State, wands: &mut Wands, length_mm: f64) -> f64 {
    let s = length_mm / wands.mean_length();
    scale_about(&mut state.cameras, &mut wands.tracks, &setup.centre, s);
    s
}

/// Step 4: one bundle adjustment of the rig and the wands' ends, the gauge
/// anchored at the rig as scaled.
fn adjust_pass(
    setup: &Setup,
    state: &mut State,
    wands: &mut Wands,
    pass: usize,
) -> Result<Solution, WandError> {
    let gauge = Gauge::new(&state.cameras, &setup.centre, setup.fixed);
    let mut bundle = Bundle {
        cameras: state.cameras.clone(),
        free: state.free.clone(),
        tracks: std::mem::take(&mut wands.tracks),
        gauge: &gauge,
        media: Vec::new(),
    };
    let solution = bundle
        .adjust(30)
        .ok_or_else(|| WandError::Diverged(format!("pass {pass}")))?;
    state.cameras = bundle.cameras;
    wands.tracks = bundle.tracks;
    Ok(solution)
}

/// The last pass's scale, exactly; the report and the adjusted wands.
fn finish(
    setup: &Setup,
    mut state: State,
    mut wands: Wands,
    passes: Passes,
    options: &WandOptions,
) -> Result<WandCalibration, WandError> {
    let scale_factor =
        passes.scale_factor * scale_to_length(setup, &mut state, &mut wands, options.length_mm);
    let models =
        models_of(&state.cameras).ok_or_else(|| WandError::Diverged("final rig".into()))?;
    let (rms_after, rms_all) = rms_per_camera(&models, &wands.tracks);
    let solution = &passes.solution;
    let sigma0 = (solution.cost / solution.redundancy.max(1) as f64).sqrt();
    let report = WandReport {
        frames: setup.frames,
        incomplete: setup.incomplete,
        ambiguous: setup.ambiguous,
        rejected: passes.rejected,
        positions: wands.positions.len(),
        length_mm: options.length_mm,
        length_before: setup.length_before.clone(),
        length_after: LengthSpread::of(&lengths(&wands.tracks)),
        scale_factor,
        sigma0_px: sigma0,
        rms_px: rms_all,
        passes: passes.passes,
        cameras: (0..setup.start.len())
            .map(|c| WandCamera {
                name: setup.start[c].name.clone(),
                rms_before_px: setup.rms_before[c],
                rms_after_px: rms_after[c],
                parameters: parameter_changes(
                    c,
                    &setup.start[c],
                    &state,
                    setup.fixed,
                    solution,
                    sigma0,
                ),
            })
            .collect(),
    };
    let wands = wands
        .positions
        .iter()
        .zip(wands.tracks.chunks(2))
        .map(|(p, t)| AdjustedWand {
            frame: p.frame,
            a: t[0].point,
            b: t[1].point,
        })
        .collect();
    Ok(WandCalibration {
        cameras: state.cameras,
        report,
        wands,
    })
}
