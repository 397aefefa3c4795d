//! Velocity and acceleration along a trajectory from a local polynomial
//! fit (Lüthi, Tsinober and Kinzelbach 2005, J. Fluid Mech. 528, section
//! 2.3), not from raw differences, which amplify the position noise.
//!
//! Around a point at frame `f0`, the trajectory's `2w + 1` points centred
//! on it (`w` before, `w` after; near its ends the window shifts inward
//! to keep `2w + 1` points, and across a gap it spans more frames) are
//! fitted per axis by
//!
//! ```text
//! x(t) = b0 + b1 t + b2 t² (+ b3 t³),   t = f - f0,
//! ```
//!
//! weighted by each point's `1 / sigma²` from the intersection. Then the
//! velocity is `b1` (mm per frame) and the acceleration `2 b2` (mm per
//! frame²), and their standard deviations come from the coefficients'
//! covariance `(Aᵀ W A)⁻¹`: the particles' sigmas propagated. The order
//! drops to what the window's points determine (two points: a line, no
//! acceleration).
//!
//! For a 5-point window, equal sigmas and order 2, the velocity's standard
//! deviation is `sigma / sqrt(10)` and the acceleration's
//! `2 sigma / sqrt(14)`; raw central differences would give `sigma /
//! sqrt(2)` and `sigma sqrt(6)`.
//!
//! **Points that are not their particle's.** A least-squares fit passes a
//! wrong point's error to every velocity whose window holds it, and a few
//! such points dominate the velocity's RMS error: in `track_report` at
//! 8,000 particles, the 0.45% of points whose window holds another
//! particle's point made two thirds of the squared error. Four rules,
//! each a χ² test of the fit's weighted residuals against the particles'
//! sigmas:
//!
//! - a window whose residuals fail the test at 99.9% gives way to the
//!   nearest consistent window of the same length that still holds the
//!   point, shifted up to `2 w` either way (`derivatives_at`): beside a
//!   wrong link, the window on the point's own side;
//! - with no consistent window, the sample with the largest standardized
//!   residual `r / (sigma sqrt(1 - h))` (`h` its leverage) is left out, if
//!   it fails χ²(3) at 99.9% (`robust_fit`);
//! - a trajectory's first or last point that is a gross error against the
//!   cubic through its neighbours leaves the trajectory
//!   (`end_is_intruder`): the first and last links have no fourth frame
//!   to confirm them, and most wrong points sit there.
//!
//! - a trajectory whose path breaks (`breaks_before`: the point off the
//!   cubic through the 4 points before it, the point before off the cubic
//!   through the 4 from it on) is cut there, unless the point is a single
//!   wrong one (`is_outlier`), which leaves it (see the tracker's
//!   "Paths that break").
//!
//! A point's fit is therefore final once the `2 w` points after it are
//! there (or the trajectory has ended), not `w`.

use nalgebra::{SMatrix, SVector, Vector3};

use crate::photogrammetry::statistics::chi_square_quantile;

/// One point of a trajectory for the fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Sample {
    /// Frame number.
    pub frame: i64,
    /// Position (mm).
    pub position: Vector3<f64>,
    /// Standard deviations of the position (mm), each above zero.
    pub sigma: Vector3<f64>,
}

/// The derivatives at one point, with their standard deviations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Derivatives {
    /// Velocity (mm per frame).
    pub velocity: Vector3<f64>,
    /// Its standard deviations.
    pub velocity_sigma: Vector3<f64>,
    /// Acceleration (mm per frame²), where the window has at least three
    /// points.
    pub acceleration: Option<Vector3<f64>>,
    /// Its standard deviations.
    pub acceleration_sigma: Option<Vector3<f64>>,
}

/// What [`derivatives_at`] found: the derivatives, and whether the window
/// centred on the point (shifted inward at the ends; it always holds the
/// point and the one before it) was consistent. Where it was, the path
/// does not break next to the point, and the tracker spares the test
/// ([`breaks_before`]).
pub(super) struct WindowFit {
    /// The derivatives (see [`derivatives_at`]).
    pub derivatives: Option<Derivatives>,
    /// Whether the centred window was consistent.
    pub centred_consistent: bool,
    /// The centred window's weighted squared residuals over the median of
    /// χ² with its degrees of freedom (about 1 where the sigmas are the
    /// points' true scatter), where it has redundancy: what
    /// [`NoiseScale`] gathers.
    pub centred_chi2_ratio: Option<f64>,
}

/// The derivatives at the `k`-th of a trajectory's consecutive points
/// `track` (all that it has within `2 w` points of `k` on each side, in
/// order), from a window of `2 w + 1` of them (all of them if there are
/// fewer) fitted with a polynomial of at most `order`.
///
/// The window is centred on the point where the trajectory allows
/// (shifted inward at its ends), unless its fit is *inconsistent*: its
/// weighted squared residuals beyond the 99.9% quantile of χ² with
/// `3 (n - order - 1)` degrees of freedom. A window is inconsistent when
/// it holds a point that is not where its particle is: a wrong link (the
/// trajectory took another particle's point, or went on as another
/// particle), or a point whose images belong to several particles. Its
/// error would pass into the velocity of every point whose window holds
/// it, and near a switch of particles no centred window is clean. Then
/// the consistent window nearest the centred one serves (the next one
/// shifted, either way, within `k`'s reach); with none, the centred
/// window without its worst sample ([`OUTLIER_CHI2`]).
///
/// No derivatives with fewer than two points or a singular system (two
/// points at one frame).
pub(super) fn derivatives_at(
    track: &[Sample],
    k: usize,
    half_window: usize,
    order: usize,
) -> WindowFit {
    let found = |derivatives| WindowFit {
        derivatives,
        centred_consistent: false,
        centred_chi2_ratio: None,
    };
    let Some(at) = track.get(k).map(|s| s.frame) else {
        return found(None);
    };
    let span = 2 * half_window + 1;
    if track.len() <= span {
        return found(robust_fit(track, at, order));
    }
    let latest = track.len() - span;
    let centred = k.saturating_sub(half_window).min(latest);
    let Some(fit) = fit_once(&track[centred..centred + span], at, order, false) else {
        return found(None);
    };
    let centred_chi2_ratio = fit.chi2_ratio();
    if fit.consistent() {
        return WindowFit {
            derivatives: Some(fit.derivatives),
            centred_consistent: true,
            centred_chi2_ratio,
        };
    }
    let found = |derivatives| WindowFit {
        derivatives,
        centred_consistent: false,
        centred_chi2_ratio,
    };
    // Other starts that keep `k` in the window, nearest the centred first.
    let (low, high) = (k.saturating_sub(span - 1), k.min(latest));
    for shift in 1..span {
        for start in [centred.checked_sub(shift), centred.checked_add(shift)]
            .into_iter()
            .flatten()
            .filter(|s| (low..=high).contains(s))
        {
            if let Some(other) = fit_once(&track[start..start + span], at, order, false) {
                if other.consistent() {
                    return found(Some(other.derivatives));
                }
            }
        }
    }
    found(robust_fit(&track[centred..centred + span], at, order))
}

/// Whether a trajectory's end point is an intruder: a point of another
/// particle (or a ghost) that the linking took at the trajectory's first
/// or last link, which no fourth frame confirms (the 4-frame cost of
/// Malik et al. needs a point on each side). `track` is the trajectory's
/// first or last points (at least `2 w + 1` of them), and the point judged
/// is the end one that `at_start` names.
///
/// It is an intruder when a gross error shows twice: the end window of
/// `2 w + 1` points fails the χ² test at the level [`GROSS_ERROR_LEVEL`]
/// (where [`derivatives_at`] tests at 99.9%), and the end point lies off
/// the cubic through the window's other points beyond χ² with 3 degrees
/// of freedom at that level, in the standardized squared distance (its
/// own variance and the cubic's extrapolation variance, per axis). The
/// level is that of a test meant to remove no real point: over 10⁶
/// trajectory ends, about one real end point. An intruder lies a
/// particle's image or more away, tens of sigmas.
///
/// A window with a second gross error (a wrong point at its far end as
/// well) is judged against a cubic that the other error bends, and a right
/// end point may then go: the trajectory is wrong there in any case. We
/// tried requiring the other points to hold no gross error: on
/// `track_report` at 8,000 particles that kept 77 points of which about
/// half were real, but it kept the wrong ends of those windows too, and
/// the velocity's RMS error rose from 1.56% to 1.94%. The cubic, one order above the fit's
/// usual quadratic, takes up the path's own change of acceleration, which
/// a quadratic extrapolated to the end would mistake for an intruder on
/// tightly curved paths; its extrapolation variance (`69 sigma²` from four
/// points) keeps the test to the gross errors that spoil the velocities.
pub(super) fn end_is_intruder(
    track: &[Sample],
    at_start: bool,
    half_window: usize,
    order: usize,
) -> bool {
    let span = 2 * half_window + 1;
    if track.len() < span || span > MAX_SAMPLES {
        return false;
    }
    let (window, point, others) = if at_start {
        (&track[..span], track[0], &track[1..span])
    } else {
        let window = &track[track.len() - span..];
        (window, window[span - 1], &window[..span - 1])
    };
    match fit_once(window, point.frame, order, false) {
        Some(f) if f.chi2 > f.quantile(Z_GROSS) => {}
        _ => return false,
    }
    off_path(&point, others)
}

/// Whether a trajectory's path breaks between its points `k - 1` and `k`
/// (`track` its consecutive points, at least 4 on each side of the
/// break): point `k` is off the path of the 4 points before it, and point
/// `k - 1` off the path of the 4 points from `k` on, each beyond the
/// gross-error level against the cubic through those 4 points
/// extrapolated to it ([`off_path`]). With fewer than 4 points before `k`
/// nothing is tested; with fewer than 4 from `k` on (the last points of a
/// trajectory that ended), the path before is the only evidence.
///
/// A trajectory that lost its particle (its images were missed, or it
/// left the volume) may go on through a free particle near its
/// prediction, and from there through another each frame, or switch to
/// a neighbour's path: every such point is a real particle's, so no test
/// of the particles catches it, and each link's cost is within the
/// search's limits, which the flow's own accelerations set. What does not
/// fit is the path on each side of the switch. On `track_report` at 0.44
/// of the mean spacing per frame, points whose windows hold no other point
/// of their particle made 92% of the squared velocity error.
pub(super) fn breaks_before(track: &[Sample], k: usize) -> bool {
    const PATH: usize = 4;
    if k < PATH || k >= track.len() || !off_path(&track[k], &track[k - PATH..k]) {
        return false;
    }
    // Fewer than 4 points from `k` on (the trajectory's last points): the
    // path before is the evidence.
    k + PATH > track.len() || off_path(&track[k - 1], &track[k..k + PATH])
}

/// Whether point `k` of `track` is a single wrong point: off the cubic
/// through the other points ([`off_path`]), while those are one smooth
/// path ([`is_smooth`]; at least 6 of them, so that the cubic has
/// redundancy to be tested with). The trajectory took another particle's
/// point for one frame and came back.
pub(super) fn is_outlier(track: &[Sample], k: usize) -> bool {
    let Some(point) = track.get(k) else {
        return false;
    };
    let mut others = [*point; MAX_SAMPLES];
    let mut n = 0;
    for (i, s) in track.iter().enumerate() {
        if i != k && n < MAX_SAMPLES {
            others[n] = *s;
            n += 1;
        }
    }
    n >= 6 && is_smooth(&others[..n], 3) && off_path(point, &others[..n])
}

/// Whether `point` is off the path of `path` (at least 4 points): beyond
/// χ² with 3 degrees of freedom at the gross-error level
/// ([`GROSS_ERROR_LEVEL`]) in its standardized squared distance from the
/// cubic fitted to `path`, evaluated at its frame, counting its own
/// variance and the cubic's (an extrapolation's, where the point lies
/// outside the path's frames).
fn off_path(point: &Sample, path: &[Sample]) -> bool {
    let Some(cubic) = fit_once(path, point.frame, 3, false) else {
        return false;
    };
    let d2: f64 = (0..3)
        .map(|axis| {
            let r = point.position[axis] - cubic.position[axis];
            r * r / (point.sigma[axis].powi(2) + cubic.position_variance[axis])
        })
        .sum();
    d2 > chi_square_quantile(3.0, Z_GROSS)
}

/// Whether a window of consecutive points is consistent with its fit by
/// a polynomial of at most `order`, at the level at which
/// [`derivatives_at`] takes a window as it is (99.9%), or cannot be tested
/// (no redundancy, a singular system). Backward tracking adds a point only
/// where the window its velocity is fitted from passes this
/// ([`super::backward`]).
pub(super) fn is_consistent(window: &[Sample], order: usize) -> bool {
    let Some(first) = window.first() else {
        return true;
    };
    !fit_once(window, first.frame, order, false).is_some_and(|fit| !fit.consistent())
}

/// Whether a window of consecutive points is one smooth path: its fit
/// with a polynomial of at most `order` is consistent at the gross-error
/// level ([`GROSS_ERROR_LEVEL`]), or cannot be tested (no redundancy, a
/// singular system).
pub(super) fn is_smooth(window: &[Sample], order: usize) -> bool {
    is_smooth_scaled(window, order, 1.0)
}

/// [`is_smooth`] with the χ² quantile multiplied by `scale`, the ratio of
/// the points' observed scatter to their sigmas, squared ([`NoiseScale`]).
pub(super) fn is_smooth_scaled(window: &[Sample], order: usize, scale: f64) -> bool {
    let Some(first) = window.first() else {
        return true;
    };
    !fit_once(window, first.frame, order, false)
        .is_some_and(|fit| fit.chi2 > scale * fit.quantile(Z_GROSS))
}

/// The scale of a run's fit residuals against the sigmas its points carry:
/// the median, over the centred fit windows so far, of their weighted
/// squared residuals divided by the median of χ² with their degrees of
/// freedom. With sigmas that are the points' true scatter it is about 1
/// (the simulator's); on a real rig the sigmas, from the intersection's
/// residuals, leave out what moves a particle from frame to frame as its
/// cameras change (a calibration's systematic error), and it is larger.
/// A median of ratios in a histogram of 1/8 octaves between 2⁻⁸ and 2²⁴:
/// a fixed 256 counters, whatever the run's length, within 9% of the exact
/// median.
#[derive(Clone, Debug)]
pub(super) struct NoiseScale {
    counts: [u64; NoiseScale::BINS],
    total: u64,
}

impl NoiseScale {
    const BINS: usize = 256;
    const PER_OCTAVE: f64 = 8.0;
    const LOWEST_OCTAVE: f64 = -8.0;
    /// Fewest fits before the scale is known.
    const FEWEST: u64 = 100;

    pub(super) fn new() -> Self {
        NoiseScale {
            counts: [0; Self::BINS],
            total: 0,
        }
    }

    pub(super) fn add(&mut self, ratio: f64) {
        if !ratio.is_finite() || ratio <= 0.0 {
            return;
        }
        let bin = ((ratio.log2() - Self::LOWEST_OCTAVE) * Self::PER_OCTAVE).floor();
        let bin = bin.clamp(0.0, (Self::BINS - 1) as f64) as usize;
        self.counts[bin] += 1;
        self.total += 1;
    }

    /// The median ratio (the middle of its bin), once [`Self::FEWEST`]
    /// fits are in.
    pub(super) fn median(&self) -> Option<f64> {
        if self.total < Self::FEWEST {
            return None;
        }
        let mut below = 0;
        for (bin, &count) in self.counts.iter().enumerate() {
            below += count;
            if 2 * below >= self.total {
                let octave = Self::LOWEST_OCTAVE + (bin as f64 + 0.5) / Self::PER_OCTAVE;
                return Some(octave.exp2());
            }
        }
        None
    }
}

/// The fit at frame `at` of `samples` (the window's points, any order),
/// with a polynomial of at most `order` (1..=3). `None` with fewer than two
/// samples, more than [`MAX_SAMPLES`], or a singular system (two samples
/// at one frame).
///
/// One outlier is left out: after the fit, each sample's residual is
/// standardized by its own variance, `sigma² (1 - h)` per axis (`h` the
/// sample's leverage, the hat matrix's diagonal: a window's end points
/// carry most of the fit, and their residuals are correspondingly small),
/// and summed over the axes. If the largest such sum exceeds
/// [`OUTLIER_CHI2`] (χ² with 3 degrees of freedom at 99.9%) and the
/// window stays over-determined without that sample, the fit is repeated
/// without it.
pub(super) fn robust_fit(samples: &[Sample], at: i64, order: usize) -> Option<Derivatives> {
    let first = fit_once(samples, at, order, true)?;
    let Some((worst, chi2)) = first.worst else {
        return Some(first.derivatives);
    };
    let order = order.clamp(1, 3);
    // Without it, still one more sample than the polynomial's terms.
    if chi2 <= OUTLIER_CHI2 || samples.len() < order + 3 {
        return Some(first.derivatives);
    }
    let mut rest = [samples[0]; MAX_SAMPLES];
    let mut n = 0;
    for (i, s) in samples.iter().enumerate() {
        if i != worst {
            rest[n] = *s;
            n += 1;
        }
    }
    Some(
        fit_once(&rest[..n], at, order, false)
            .map(|f| f.derivatives)
            .unwrap_or(first.derivatives),
    )
}

/// The 99.9% quantile of χ² with 3 degrees of freedom: a sample whose
/// standardized residuals' squares sum beyond it is left out of the fit.
/// At that level a window of 5 correct samples loses one in about 200
/// fits, which costs those fits a little precision and no bias.
pub const OUTLIER_CHI2: f64 = 16.27;

/// The normal's 99.9% quantile: the level of the windows' consistency.
const Z_999: f64 = 3.0902;

/// The normal's quantile at `1 - GROSS_ERROR_LEVEL`.
const Z_GROSS: f64 = 4.7534;

/// The level of the test for intruders at a trajectory's ends: a
/// real point is taken for one with about this probability.
pub const GROSS_ERROR_LEVEL: f64 = 1e-6;

/// The most samples a fit takes without allocating (a window of at most
/// `2 w + 1`, `w <= 5`).
pub(super) const MAX_SAMPLES: usize = 11;

/// A fit's derivatives, its weighted squared residuals and their degrees
/// of freedom, and the sample with the largest standardized residual (its
/// index and χ²), where the fit has redundancy.
struct Fit {
    derivatives: Derivatives,
    /// The polynomial at `at` (mm), and its variance per axis.
    position: Vector3<f64>,
    position_variance: Vector3<f64>,
    chi2: f64,
    dof: usize,
    worst: Option<(usize, f64)>,
}

impl Fit {
    /// Its residuals within the 99.9% quantile of their χ² (trivially
    /// without redundancy).
    fn consistent(&self) -> bool {
        self.chi2 <= self.quantile(Z_999)
    }

    /// Its weighted squared residuals over the median of χ² with its
    /// degrees of freedom, where it has redundancy.
    fn chi2_ratio(&self) -> Option<f64> {
        (self.dof > 0).then(|| self.chi2 / chi_square_quantile(self.dof as f64, 0.0))
    }

    /// The χ² quantile of its degrees of freedom at the normal quantile
    /// `z` (infinite without redundancy).
    fn quantile(&self, z: f64) -> f64 {
        if self.dof == 0 {
            f64::INFINITY
        } else {
            chi_square_quantile(self.dof as f64, z)
        }
    }
}

/// The weighted least-squares fit of `samples` at `at`; with `standardize`
/// also each sample's standardized residual (its leverage costs a
/// quadratic form per sample and axis), for [`Fit::worst`].
fn fit_once(samples: &[Sample], at: i64, order: usize, standardize: bool) -> Option<Fit> {
    if samples.len() < 2 || samples.len() > MAX_SAMPLES {
        return None;
    }
    let order = order.clamp(1, 3).min(samples.len() - 1);
    let mut velocity = Vector3::zeros();
    let mut velocity_sigma = Vector3::zeros();
    let mut acceleration = Vector3::zeros();
    let mut acceleration_sigma = Vector3::zeros();
    let mut standardized = [0.0; MAX_SAMPLES];
    let mut chi2 = 0.0;
    let mut position = Vector3::zeros();
    let mut position_variance = Vector3::zeros();
    for axis in 0..3 {
        // Normal equations of the weighted least squares, per axis (the
        // weights differ per axis), in fixed-size matrices: no allocation.
        let residuals = standardize.then_some(&mut standardized);
        let ([b0, b1, b2], [var0, var1, var2]) = match order {
            1 => solve::<2>(samples, at, axis, residuals, &mut chi2)?,
            2 => solve::<3>(samples, at, axis, residuals, &mut chi2)?,
            _ => solve::<4>(samples, at, axis, residuals, &mut chi2)?,
        };
        position[axis] = b0;
        position_variance[axis] = var0.max(0.0);
        velocity[axis] = b1;
        velocity_sigma[axis] = var1.max(0.0).sqrt();
        if order >= 2 {
            acceleration[axis] = 2.0 * b2;
            acceleration_sigma[axis] = 2.0 * var2.max(0.0).sqrt();
        }
    }
    let dof = 3 * (samples.len() - order - 1);
    let worst = (standardize && dof > 0)
        .then(|| {
            standardized[..samples.len()]
                .iter()
                .copied()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(&b.1))
        })
        .flatten();
    Some(Fit {
        derivatives: Derivatives {
            velocity,
            velocity_sigma,
            acceleration: (order >= 2).then_some(acceleration),
            acceleration_sigma: (order >= 2).then_some(acceleration_sigma),
        },
        position,
        position_variance,
        chi2,
        dof,
        worst,
    })
}

/// One axis's fit with `D` terms: the coefficients of order 0, 1 and 2 and
/// their variances (the second order's 0 for a line). Adds each sample's
/// standardized squared residual, `r² / (sigma² (1 - h))`, to
/// `standardized`, and the weighted squared residuals `r² / sigma²` to
/// `chi2`.
fn solve<const D: usize>(
    samples: &[Sample],
    at: i64,
    axis: usize,
    mut standardized: Option<&mut [f64; MAX_SAMPLES]>,
    chi2: &mut f64,
) -> Option<([f64; 3], [f64; 3])> {
    let powers = |s: &Sample| {
        let t = (s.frame - at) as f64;
        let mut powers = SVector::<f64, D>::repeat(1.0);
        for k in 1..D {
            powers[k] = powers[k - 1] * t;
        }
        powers
    };
    let mut normal = SMatrix::<f64, D, D>::zeros();
    let mut rhs = SVector::<f64, D>::zeros();
    for s in samples {
        let w = s.sigma[axis].powi(-2);
        let a = powers(s);
        rhs += a * (w * s.position[axis]);
        normal += a * a.transpose() * w;
    }
    let inverse = normal.try_inverse()?;
    let b = inverse * rhs;
    for (i, s) in samples.iter().enumerate() {
        let w = s.sigma[axis].powi(-2);
        let a = powers(s);
        let residual = s.position[axis] - a.dot(&b);
        *chi2 += residual * residual * w;
        if let Some(standardized) = standardized.as_deref_mut() {
            let leverage = w * (a.transpose() * inverse * a)[0];
            let free = 1.0 - leverage;
            if free > 1e-9 {
                standardized[i] += residual * residual * w / free;
            }
        }
    }
    Some(if D > 2 {
        (
            [b[0], b[1], b[2]],
            [inverse[(0, 0)], inverse[(1, 1)], inverse[(2, 2)]],
        )
    } else {
        ([b[0], b[1], 0.0], [inverse[(0, 0)], inverse[(1, 1)], 0.0])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples(frames: &[i64], f: impl Fn(f64) -> Vector3<f64>, sigma: f64) -> Vec<Sample> {
        frames
            .iter()
            .map(|&frame| Sample {
                frame,
                position: f(frame as f64),
                sigma: Vector3::repeat(sigma),
            })
            .collect()
    }

    #[test]
    fn a_parabola_is_differentiated_exactly() {
        let path = |t: f64| Vector3::new(1.0 + 2.0 * t + 0.5 * t * t, -t, 3.0 - 0.25 * t * t);
        let s = samples(&[8, 9, 10, 11, 12], path, 0.01);
        let d = robust_fit(&s, 10, 2).unwrap();
        assert!((d.velocity - Vector3::new(12.0, -1.0, -5.0)).norm() < 1e-9);
        assert!((d.acceleration.unwrap() - Vector3::new(1.0, 0.0, -0.5)).norm() < 1e-9);
        // sigma / sqrt(10) and 2 sigma / sqrt(14), the module doc's values.
        assert!((d.velocity_sigma.x - 0.01 / 10f64.sqrt()).abs() < 1e-12);
        assert!((d.acceleration_sigma.unwrap().x - 0.02 / 14f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn a_cubic_is_differentiated_exactly_by_order_3() {
        let path = |t: f64| Vector3::new(t * t * t - 2.0 * t, 0.5 * t * t, 1.0);
        for frames in [&[8, 9, 10, 11, 12][..], &[10, 11, 12, 13], &[7, 8, 10, 11]] {
            let d = robust_fit(&samples(frames, path, 0.01), 10, 3).unwrap();
            assert!(
                (d.velocity - Vector3::new(298.0, 10.0, 0.0)).norm() < 1e-6,
                "{frames:?}: {}",
                d.velocity
            );
        }
    }

    #[test]
    fn at_an_end_and_across_a_gap_the_window_is_what_there_is() {
        let path = |t: f64| Vector3::new(t * t, 0.0, 0.0);
        // One-sided at the start, with frame 2 missing.
        let d = robust_fit(&samples(&[0, 1, 3, 4], path, 0.01), 0, 2).unwrap();
        assert!(
            (d.velocity.x - 0.0).abs() < 1e-9 && (d.acceleration.unwrap().x - 2.0).abs() < 1e-9
        );
        // Two points: a line, no acceleration.
        let d = robust_fit(&samples(&[5, 6], path, 0.01), 6, 2).unwrap();
        assert!((d.velocity.x - 11.0).abs() < 1e-9 && d.acceleration.is_none());
        assert!(robust_fit(&samples(&[5], path, 0.01), 5, 2).is_none());
    }

    /// A path with small deterministic noise (a fixed pattern of about
    /// `sigma`), so that the χ² tests see residuals of the size the sigmas
    /// claim.
    fn noisy(
        frames: std::ops::Range<i64>,
        f: impl Fn(f64) -> Vector3<f64>,
        sigma: f64,
    ) -> Vec<Sample> {
        let pattern = [0.7, -1.1, 0.4, 1.2, -0.6, -0.9, 1.0, -0.3, 0.8, -1.2];
        frames
            .map(|frame| {
                let k = frame.rem_euclid(10) as usize;
                let e = Vector3::new(pattern[k], pattern[(k + 3) % 10], pattern[(k + 7) % 10]);
                Sample {
                    frame,
                    position: f(frame as f64) + e * sigma,
                    sigma: Vector3::repeat(sigma),
                }
            })
            .collect()
    }

    #[test]
    fn beside_a_switch_of_particles_the_window_on_the_points_own_side_serves() {
        let sigma = 0.01;
        let a = |t: f64| Vector3::new(t, 0.2 * t * t, 0.0);
        let b = |t: f64| Vector3::new(3.0 - 0.5 * t, 1.0, 2.0);
        // Frames 0..=5 are particle A's, 6..=9 particle B's.
        let mut track = noisy(0..6, a, sigma);
        track.extend(noisy(6..10, b, sigma));
        for k in [4usize, 5] {
            let d = derivatives_at(&track[k - 4..], 4, 2, 2)
                .derivatives
                .unwrap();
            let truth = Vector3::new(1.0, 0.4 * k as f64, 0.0);
            // A's own window's velocity noise (at most sigma sqrt(1.24)
            // per axis at a window's end), far from B's.
            assert!(
                (d.velocity - truth).norm() < 5.0 * sigma,
                "k {k}: {} against {truth}",
                d.velocity
            );
        }
        // Without the switch the centred window serves, as before.
        let clean = noisy(0..10, a, sigma);
        let d = derivatives_at(&clean[1..], 3, 2, 2).derivatives.unwrap();
        let centred = robust_fit(&clean[2..7], 4, 2).unwrap();
        assert_eq!(d, centred);
    }

    #[test]
    fn one_wrong_point_is_left_out_of_the_fit() {
        let sigma = 0.01;
        let path = |t: f64| Vector3::new(2.0 * t, -t, 0.1 * t * t);
        let mut window = noisy(0..7, path, sigma);
        window[5].position.y += 1.0;
        let d = robust_fit(&window, 3, 2).unwrap();
        assert!((d.velocity - Vector3::new(2.0, -1.0, 0.6)).norm() < 5.0 * sigma);
    }

    #[test]
    fn a_gross_error_at_an_end_is_an_intruder_and_the_noise_is_not() {
        let sigma = 0.01;
        let path = |t: f64| Vector3::new(t, 0.3 * t * t, -0.002 * t * t * t);
        let track = noisy(0..5, path, sigma);
        assert!(!end_is_intruder(&track, true, 2, 2));
        assert!(!end_is_intruder(&track, false, 2, 2));
        for (k, at_start) in [(0usize, true), (4, false)] {
            let mut wrong = track.clone();
            // Another particle's point, 1 mm away: 100 sigmas.
            wrong[k].position += Vector3::new(0.6, -0.8, 0.0);
            assert!(end_is_intruder(&wrong, at_start, 2, 2));
        }
        // Too short to judge.
        assert!(!end_is_intruder(&track[..4], true, 2, 2));
    }

    #[test]
    fn a_path_breaks_where_it_goes_on_as_another_particle() {
        let sigma = 0.01;
        // Tightly curved (a cubic's jerk): no break anywhere on one path.
        let path = |t: f64| Vector3::new(t, 0.3 * t * t, -0.01 * t * t * t);
        let track = noisy(0..12, path, sigma);
        for k in 0..track.len() {
            assert!(!breaks_before(&track, k), "one path, k {k}");
        }
        // From point 6 on, another particle's path 1 mm away (100 sigmas)
        // with another velocity: the break is before 6 and nowhere else.
        let mut switched = track.clone();
        for (i, s) in switched.iter_mut().enumerate().skip(6) {
            s.position += Vector3::new(0.6, -0.8, 0.0) + Vector3::new(0.1, 0.05, 0.0) * i as f64;
        }
        // (Beyond it the 4 points before straddle the switch: the
        // tracker cuts at the first break and judges the rest anew.)
        for k in 0..=6 {
            assert_eq!(breaks_before(&switched, k), k == 6, "k {k}");
        }
        assert!(!is_outlier(&switched, 6));
        // The last points, too few to show a path of their own: the path
        // before is the evidence.
        let mut tail = track.clone();
        for s in &mut tail[10..] {
            s.position += Vector3::new(0.6, -0.8, 0.0);
        }
        assert!(breaks_before(&tail, 10));
        // One wrong point inside: a break before it, and it is an outlier
        // (the points around it are one path without it).
        let mut one = track.clone();
        one[6].position += Vector3::new(0.6, -0.8, 0.0);
        assert!(breaks_before(&one, 6));
        assert!(is_outlier(&one[2..11], 4));
        assert!(!is_outlier(&track[2..11], 4));
        // Too few points before: nothing is tested.
        assert!(!breaks_before(&one[3..], 3));
    }

    #[test]
    fn a_smooth_window_is_consistent_at_the_gross_level() {
        let sigma = 0.01;
        let path = |t: f64| Vector3::new(t, 0.3 * t * t, -0.01 * t * t * t);
        let track = noisy(0..5, path, sigma);
        assert!(is_smooth(&track, 3));
        let mut chain = track.clone();
        chain[2].position.x += 1.0;
        chain[3].position.y -= 1.0;
        assert!(!is_smooth(&chain, 3));
        // Four points determine a cubic: nothing to test.
        assert!(is_smooth(&chain[..4], 3));
    }
}
