//! The robust adjustment of a round: Huber-weighted bundle passes with
//! wrong matches rejected, and the parameters and media terms the
//! observations cannot determine held (module docs of [`super`]).

use nalgebra::{DMatrix, Vector2};

use super::bundle::{self, residuals, Bundle, Track};
use super::gauge::Gauge;
use super::report;
use super::{
    selection::models_or_diverged, SelfCalibrationError, SelfCalibrationOptions, State,
    MIN_PARTICLES,
};
use crate::photogrammetry::calibrate::adjustment::{from_vector, to_vector, Statistics};
use crate::photogrammetry::calibrate::resection::undeterminable;
use crate::photogrammetry::calibrate::ParameterSet;
use crate::photogrammetry::camera::{Camera, CameraParameters};
use crate::photogrammetry::cancel::Cancel;

pub(super) fn residual_vectors(models: &[Camera], tracks: &[Track]) -> Vec<Vector2<f64>> {
    residuals(models, tracks)
        .into_iter()
        .flatten()
        .flatten()
        .collect()
}

pub(super) fn rms(d: &[Vector2<f64>]) -> f64 {
    if d.is_empty() {
        return 0.0;
    }
    (d.iter().map(|v| v.norm_squared()).sum::<f64>() / d.len() as f64).sqrt()
}

/// The robust scale per coordinate of 2D residuals: the median length over
/// the Rayleigh median `sqrt(2 ln 2)` (1.1774).
pub(super) fn robust_sigma(r: &[Vector2<f64>]) -> f64 {
    let mut lengths: Vec<f64> = r.iter().map(|v| v.norm()).collect();
    lengths.sort_by(f64::total_cmp);
    report::median_sorted(&lengths) / (2.0 * std::f64::consts::LN_2).sqrt()
}

/// Huber's weights at this many sigma.
pub(super) const HUBER_K: f64 = 2.0;
/// A particle with a residual beyond this many sigma is a wrong match.
pub(super) const REJECT_K: f64 = 5.0;
/// Most passes of the robust loop (reweighting, rejection, holding).
pub(super) const MAX_PASSES: usize = 12;

pub(super) type Adjusted = (Vec<Track>, bundle::Solution, usize, f64);

/// The bundle adjustment with reweighting, rejection of wrong matches and
/// holding of undeterminable parameters; `None` if it diverged.
pub(super) fn robust_adjustment(
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
        let Some((mut solution, adjusted)) = adjust_once(state, tracks, gauge) else {
            return Ok(None);
        };
        iterations += solution.iterations;
        solution.iterations = iterations;
        tracks = adjusted;
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
    let Some((mut solution, tracks)) = adjust_once(state, tracks, gauge) else {
        return Ok(None);
    };
    solution.iterations += iterations;
    Ok(Some((tracks, solution, rejected, previous_sigma)))
}

/// One bundle adjustment of `tracks` from the state's cameras (at most 30
/// iterations); the state takes the adjusted cameras. `None` if it failed.
fn adjust_once(
    state: &mut State,
    tracks: Vec<Track>,
    gauge: &Gauge,
) -> Option<(bundle::Solution, Vec<Track>)> {
    let mut bundle = Bundle {
        cameras: state.cameras.clone(),
        free: state.free.clone(),
        tracks,
        gauge,
        media: state.media.clone(),
    };
    let solution = bundle.adjust(30)?;
    state.cameras = bundle.cameras;
    Some((solution, bundle.tracks))
}

/// `track` with each observation's Huber weight at `sigma`: 1 within
/// `HUBER_K` sigma, `HUBER_K sigma / |v|` beyond, 0 where it does not image.
pub(super) fn huber_weighted(
    mut track: Track,
    residuals: &[Option<Vector2<f64>>],
    sigma: f64,
) -> Track {
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
pub(super) fn hold_undeterminable(
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
pub(super) fn undeterminable_media(
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
