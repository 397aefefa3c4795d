//! Candidate links of one trajectory into the next frame and their cost:
//! the linking's steps 1 and 2 (module docs of [`super`]), the same forward
//! and backward in time.

use nalgebra::{Point3, Vector3};

use super::grid::Grid;
use super::kinematics::{is_smooth_scaled, MAX_SAMPLES};
use super::live::Live;
use super::{ParticlePosition, TrackingParameters, MAX_CANDIDATES};

/// A candidate link, ordered by its rank (without a look-ahead partner
/// after all with one, then by cost), then its trajectory and particle.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(super) struct Link {
    /// [`Link::rank`].
    pub(super) rank: u64,
    pub(super) live: usize,
    pub(super) particle: usize,
}

impl Link {
    /// The rank as one integer: a cost's bits (for a cost of zero or
    /// above, its IEEE 754 bits order as the cost does), with the top (the
    /// sign) bit set for a link without a look-ahead partner. Sorting
    /// integers is cheaper than comparing floats, and an infinite or NaN
    /// cost (which finite positions never give) ranks last instead of
    /// stopping the sort.
    pub(super) fn rank(unconfirmed: bool, cost: f64) -> u64 {
        debug_assert!(cost >= 0.0, "a cost is a norm plus a penalty");
        // `+ 0.0` turns a -0.0 into 0.0.
        (cost + 0.0).to_bits() | u64::from(unconfirmed) << 63
    }
}

/// A trajectory's search in the next frame ([`Tracker::prediction`]).
#[derive(Clone, Copy)]
pub(super) struct Search {
    pub(super) predicted: Point3<f64>,
    pub(super) radius: f64,
    /// Its last position.
    pub(super) from: Point3<f64>,
    /// Frames from its last point to the next frame.
    pub(super) dt: f64,
    /// Its last velocity, with two points or more.
    pub(super) velocity: Option<Vector3<f64>>,
    /// The noise floor of its last point ([`noise_floor`]).
    pub(super) floor: f64,
    /// Cameras missed by its point, for a trajectory of one point (else 0):
    /// the ghost penalty's share from the source.
    pub(super) source: usize,
}

/// Whether a trajectory that ended shorter than its start test's window
/// (`2 w + 1` points) is one smooth path: its points fitted with the
/// highest order that leaves 3 degrees of freedom (a quadratic through 4
/// points, a line through 3), consistent at the gross-error level
/// ([`is_smooth`]). The start test of longer trajectories (a cubic through
/// their first `2 w + 1` points) never sees these, and a chain of other
/// particles' points (a particle that lost its own trajectory for a frame
/// or two, taken up by a new one that goes on through its neighbours)
/// passes every link's search: on `examples/track_report` at 8,000
/// particles, 188 points in trajectories of 3 and 4 points, all such
/// chains, made 64% of the squared velocity error. A real particle's 4
/// points lie on a quadratic within their noise; its 3 points lie on a
/// line within the gross-error level unless its acceleration exceeds about
/// 13 sigma of its position per frame² (`sqrt(χ²₃) ≈ 5.5` times the
/// second difference's `sigma sqrt 6`), a path too curved for 3 points to
/// give it a velocity in any case.
///
/// The sigmas are trusted only as far as the run's own fits bear them out:
/// the test's χ² bound is scaled by the median ratio of the fits'
/// residuals to their sigmas (`scale`, [`NoiseScale`]; at least 1), and
/// before 100 fits have shown it (a recording of a few frames, whose
/// trajectories are all short) nothing is tested. On the 4 frames of the
/// real test_cavity recording, whose sigmas from the intersection are
/// several times too small for its frame-to-frame scatter, the unscaled
/// test would drop 441 of its 728 trajectories.
pub(super) fn short_path_is_smooth(live: &Live, scale: Option<f64>) -> bool {
    let n = live.nodes.len();
    let Some(scale) = scale else {
        return true;
    };
    if n != live.length || !(3..MAX_SAMPLES).contains(&n) {
        return true;
    }
    let mut window = [live.nodes[0].sample(); MAX_SAMPLES];
    for (slot, node) in window.iter_mut().zip(&live.nodes) {
        *slot = node.sample();
    }
    is_smooth_scaled(&window[..n], (n - 2).min(3), scale.max(1.0))
}

/// Reused buffers of [`candidate_links`].
#[derive(Default)]
pub(super) struct Scratch {
    pub(super) near: Vec<usize>,
    pub(super) candidates: Vec<(f64, usize)>,
    pub(super) near_ahead: Vec<usize>,
    pub(super) partner: Vec<(f64, usize)>,
}

/// The candidate links of one trajectory's `search` (trajectory `live`)
/// in the frame of grid `next`, judged with the frame after it (`ahead`:
/// its grid and the frames from `next` to it), appended to `links`: the
/// linking's steps 1 and 2 (module docs), the same whichever way in time
/// the trajectory is extended (forward, or backward from its first points:
/// [`backward`]). `accept` says which entries of `next` may be taken at
/// all (the backward pass takes only particles no trajectory holds).
#[allow(clippy::too_many_arguments)]
pub(super) fn candidate_links(
    p: &TrackingParameters,
    next: &Grid,
    ahead: Option<(&Grid, f64)>,
    search: &Search,
    live: usize,
    accept: impl Fn(usize) -> bool,
    scratch: &mut Scratch,
    links: &mut Vec<Link>,
) {
    let Scratch {
        near,
        candidates,
        near_ahead,
        partner,
    } = scratch;
    let Search {
        predicted,
        radius,
        from,
        dt,
        velocity,
        floor,
        source,
    } = *search;
    // The candidates: within the radius and the velocity limit, at
    // most MAX_CANDIDATES of them (the nearest the prediction).
    let moves =
        |e: usize| ((next.points[e] - from) / dt).norm() <= p.max_velocity + floor && accept(e);
    if next.is_small(radius) {
        near.clear();
        next.within(&predicted, radius, near);
        candidates.clear();
        candidates.extend(near.iter().filter(|&&e| moves(e)).map(|&e| (0.0, e)));
        if candidates.len() > MAX_CANDIDATES {
            for candidate in candidates.iter_mut() {
                candidate.0 = (next.points[candidate.1] - predicted).norm_squared();
            }
            candidates.select_nth_unstable_by(MAX_CANDIDATES - 1, |a, b| {
                a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
            });
            candidates.truncate(MAX_CANDIDATES);
        }
    } else {
        next.nearest(&predicted, radius, MAX_CANDIDATES, moves, candidates);
    }
    // Entries of the grids: each candidate's data is read there, in
    // cell order next to its neighbours', not from the frame's
    // arrays in input order (at 10,000+ particles a cache miss
    // for each).
    for &(_, e) in candidates.iter() {
        let c = next.order[e] as usize;
        let position = next.points[e];
        let sigma = next.sigma[e];
        let step = (position - from) / dt;
        // The acceleration this link implies (none known for a
        // trajectory of one point).
        let a1 = velocity.map(|v| (step - v) / dt);
        let mut best: Option<f64> = None;
        if let Some((ahead, dt2)) = ahead {
            let predicted2 = position + step * dt2;
            let floor2 = noise_floor(&sigma);
            let radius2 = p.max_acceleration * dt2 * dt2 + floor2;
            let cost = |d: usize| {
                let step2 = (ahead.points[d] - position) / dt2;
                if step2.norm() > p.max_velocity + floor2 {
                    return None;
                }
                let a2 = (step2 - step) / dt2;
                Some(match a1 {
                    Some(a1) => (a2 - a1).norm(),
                    None => a2.norm(),
                })
            };
            if ahead.is_small(radius2) {
                near_ahead.clear();
                ahead.within(&predicted2, radius2, near_ahead);
                for &d in near_ahead.iter() {
                    if let Some(cost) = cost(d) {
                        best = Some(best.map_or(cost, |b: f64| b.min(cost)));
                    }
                }
            } else {
                // A partner's cost is its distance from where the
                // link's acceleration carries on to, `predicted2 +
                // a1 dt2²` (from `predicted2` for a trajectory of
                // one point), over dt2²: the best is the nearest
                // one there within the radius.
                let carried = predicted2 + a1.unwrap_or_else(Vector3::zeros) * dt2 * dt2;
                ahead.nearest(
                    &carried,
                    (carried - predicted2).norm() + radius2,
                    1,
                    |d| {
                        (ahead.points[d] - predicted2).norm_squared() <= radius2 * radius2
                            && cost(d).is_some()
                    },
                    partner,
                );
                best = partner.first().and_then(|&(_, d)| cost(d));
            }
        }
        // A candidate missed by some cameras may be a ghost, and so
        // may a trajectory of one such point (one with more points
        // has its history as evidence): the link ranks after one
        // between points seen by all whose cost is within the
        // noise's.
        let penalty = (next.missing[e] + source) as f64 * WEAK_PENALTY * cost_noise(&sigma);
        let link = match best {
            Some(cost) => Link {
                rank: Link::rank(false, cost + penalty),
                live,
                particle: c,
            },
            // A new trajectory's first link needs a look-ahead
            // partner, unless there is no frame to look ahead to.
            None if a1.is_none() && ahead.is_some() => continue,
            None => Link {
                rank: Link::rank(
                    true,
                    a1.map_or((position - from).norm(), |a| a.norm()) + penalty,
                ),
                live,
                particle: c,
            },
        };
        links.push(link);
    }
}

/// Raises every sigma below the frame's median (per axis) to it. The
/// intersection's sigmas are a posteriori, from the particle's own
/// residuals: with few redundant observations they scatter widely (a
/// 2-camera particle has one degree of freedom, and a near-zero residual
/// gives a near-zero sigma), and such a point would pin its trajectory's
/// fit and its search radius. The frame's median is a steadier estimate of
/// the precision of the points that claim better.
pub(super) fn floor_sigmas(particles: &mut [ParticlePosition]) -> Vector3<f64> {
    if particles.is_empty() {
        return Vector3::zeros();
    }
    let mut median = Vector3::zeros();
    let mut values = Vec::with_capacity(particles.len());
    for axis in 0..3 {
        values.clear();
        values.extend(particles.iter().map(|p| p.sigma[axis]));
        let mid = values.len() / 2;
        median[axis] = *values.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
    }
    for p in particles {
        p.sigma = p.sigma.sup(&median);
    }
    median
}

/// The ranking's penalty for each camera that missed a candidate, in
/// units of `cost_noise`: a candidate seen by all cameras wins unless
/// its cost is worse by more than this many times the noise's.
pub const WEAK_PENALTY: f64 = 2.0;

/// The RMS of a link's cost (the change of acceleration over four
/// positions, `x_{t+2} - 3 x_{t+1} + 3 x_t - x_{t-1}`) from the positions'
/// noise alone, each position with the candidate's `sigma`: `sqrt(1 + 9 +
/// 9 + 1) |sigma|`.
pub(super) fn cost_noise(sigma: &Vector3<f64>) -> f64 {
    20f64.sqrt() * sigma.norm()
}

/// A search radius's allowance for the positions' noise: the prediction
/// from two points and the candidate carry about `sqrt(6)` times a
/// position's sigma per axis; 3 of those over the three axes.
pub(super) fn noise_floor(sigma: &Vector3<f64>) -> f64 {
    3.0 * 6f64.sqrt() * sigma.norm()
}
