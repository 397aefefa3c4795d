//! Backward tracking: after the forward pass, every trajectory is
//! extended backwards in time from its first points, with the forward
//! linking's criteria run the other way (as OpenPTV's `trackback_c` does
//! after its forward pass; Willneff 2003, section 5.3.4, reports that it
//! lengthens the trajectories the forward pass started late).
//!
//! **Why starts are found late.** Forward, a trajectory of one point has
//! no velocity: its first link is searched within `max_velocity` of it and
//! needs a look-ahead partner, and a new trajectory's first window of
//! `2 w + 1` points must be one smooth path or it loses its leading
//! points. A particle entering the volume (or found again after a loss
//! longer than `max_gap`) whose second image is lost, or whose first link
//! is ambiguous among its neighbours, starts its trajectory some frames
//! after its first point. Backward, the same particle's trajectory has a
//! velocity: its search is the acceleration limit's, around a prediction.
//!
//! **The pass** runs from the sequence's last frame to its first. In
//! frame `t`, every trajectory of two or more points whose first point is
//! in `t + 1 ..= t + 1 + max_gap` predicts `x̂ = x_1 + v Δ` (`v` its
//! velocity from its first two points, reversed in time; `Δ` the frames
//! from `t` to its first point), searched within `max_acceleration Δ²`
//! plus the noise floor; the candidates are the particles of `t` no
//! trajectory holds, and the last points of trajectories that end at `t`
//! (a link to one *joins* the two: a trajectory broken by a loss longer
//! than the gap, or cut where a link was missed). Each candidate is judged
//! with the frame before `t` as the forward pass judges with the frame
//! after (the change of acceleration over four positions, Malik et al.
//! 1993; the ghost penalty for cameras missed), and all the frame's links
//! are resolved globally, best first ([`super::candidate_links`], the
//! same code). A link is taken only where the forward pass's own tests
//! pass: the trajectory's first window with its new point (and, for a
//! join, the window across the junction) is one smooth path at the
//! gross-error level ([`super::kinematics::is_smooth`]), the new point is
//! no gross error at the start ([`super::kinematics::end_is_intruder`]),
//! and a join's path does not break at the junction
//! ([`super::kinematics::breaks_before`], the test that cuts a trajectory
//! forward: a join does not undo a cut). The points whose fit windows
//! reach a new point get their derivatives fitted again.
//!
//! **Only points as good as the forward pass's.** Those tests alone let
//! in links to other particles: the cubic through the new point and the
//! next four has one degree of freedom per axis, and across a gap the new
//! point has nearly all the leverage, so a neighbour tens of sigmas off
//! the path passes (its χ² share is `1 - h ≈ 0.001` of its squared
//! offset). On `examples/track_report` (50 frames, 0.31 of the spacing a
//! frame) the pass added 172 / 700 / 2,492 points at 2,000 / 8,000 /
//! 20,000 particles with velocity RMS errors of 25% / 14% / 35% of the RMS
//! velocity; sorted by the truth, the error was nearly all in the few
//! linked to another particle (8 points at 117% at 2,000, 61 at 47% at
//! 8,000, 352 at 89% at 20,000), while the right ones had 4-10% at a new
//! first point and 1-2% further in, as the forward pass's ends. So a new
//! point must also leave the window its velocity is fitted from (the
//! quadratic through it and the next `2 w` points) consistent at the level
//! the fits take a window as it is, 99.9%
//! ([`super::kinematics::is_consistent`]): a right point is refused once
//! in a thousand, a neighbour off the path by more than about
//! `sqrt(χ²₆(0.999) / (1 - h))` sigmas (14 without a gap, 28 across one)
//! always. With it the added points' RMS errors are 1.4% / 3.0% / 3.2%
//! (128 / 646 / 2,230 points, 1 / 10 / 28 linked to another particle), and
//! the whole velocity RMS error is the forward pass's or below: 2.10% /
//! 1.51% / 2.72% against 2.10% / 1.52% / 2.73%, wrong links 0.09% / 0.23% /
//! 0.49% as forward, link recall 0.9927 / 0.9908 / 0.9890 against 0.9911 /
//! 0.9886 / 0.9866 (docs/tracking.md). The 7-point window of a cut
//! trajectory's probation (a cubic with 3 degrees of freedom per axis)
//! was tried instead: at 8,000 the added points' error went to 5.8%,
//! above the forward pass's ends (5.3%), with fewer points added (628).
//!
//! **Memory.** The pass needs the whole sequence: every frame's particles
//! (56 bytes each) and every trajectory point (about 130 bytes), held
//! until the end. A tracker without it streams in memory bounded by its
//! window ([`super::Tracker::held_points`]).

use std::collections::VecDeque;

use nalgebra::Vector3;

use super::grid::Grid;
use super::kinematics::{
    breaks_before, derivatives_at, end_is_intruder, is_consistent, is_smooth, Sample, MAX_SAMPLES,
};
use super::links::{candidate_links, noise_floor, Link, Scratch, Search};
use super::{Derivatives, Gathered, ParticlePosition, TrackPoint, TrackingParameters};

/// What backward tracking added.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BackwardSummary {
    /// Points added before the trajectories' first points.
    pub points: usize,
    /// Trajectories that gained points at their start.
    pub lengthened: usize,
    /// Trajectories joined to the one that ended just before them (each
    /// join makes two trajectories one).
    pub joined: usize,
}

/// A frame as the pass reads it: its particles with the sigmas the
/// forward pass used (floored), and the cameras that missed each.
pub(super) struct Stored {
    pub number: i64,
    pub particles: Vec<ParticlePosition>,
    pub missing: Vec<usize>,
}

/// A trajectory during the pass.
struct Path {
    id: u64,
    points: VecDeque<TrackPoint>,
    /// Their sigmas, in the same order.
    sigma: VecDeque<Vector3<f64>>,
    /// Per point, whether its neighbourhood changed (a point added, or
    /// the last point before a junction): the fits whose windows reach it
    /// are done again.
    fresh: VecDeque<bool>,
    /// Joined into another trajectory: its points are there.
    gone: bool,
    /// Gained points at its start.
    lengthened: bool,
}

impl Path {
    fn sample(&self, k: usize) -> Sample {
        Sample {
            frame: self.points[k].frame,
            position: self.points[k].position.coords,
            sigma: self.sigma[k],
        }
    }
}

/// Marks a particle held by no trajectory.
const FREE: u32 = u32::MAX;

/// Extends the trajectories of `points` (all the forward pass handed
/// out) backwards over `frames` (every frame it linked, in order);
/// returns every point, each trajectory keeping its number (one joined
/// onto the trajectory before it is gone, its points under that one's
/// number), each in frame order, and what was added.
pub(super) fn extend(
    frames: &[Stored],
    points: Vec<TrackPoint>,
    parameters: &TrackingParameters,
    cell: f64,
) -> (Vec<TrackPoint>, BackwardSummary) {
    let (paths, summary) = extend_paths(frames, points, parameters, cell);
    let w = parameters.fit_half_window;
    (refitted(paths, w, parameters.fit_order), summary)
}

/// A frame of a finished run, for [`extend_run`]: the particles the
/// tracker was given (their sigmas as given) and, after them, those it
/// recovered from the images (`given` says where they start).
#[derive(Clone, Debug, PartialEq)]
pub struct RunFrame {
    /// The frame number.
    pub number: i64,
    /// Its particles: the `given` ones, then the recovered ones.
    pub particles: Vec<ParticlePosition>,
    /// How many of `particles` were given (the rest were recovered).
    pub given: usize,
}

/// Backward tracking over a run tracked forward already and held
/// elsewhere (the service's store): `frames` are the frames the tracker
/// took, in increasing order (numbers skipped are empty frames, as
/// [`super::Tracker::push`] takes them), `points` every point it handed
/// out. Returns every point, each trajectory keeping its number (a
/// trajectory joined onto the one before it is gone: its points carry
/// that one's number), and what was added. The same pass as
/// [`super::Tracker::extending_backward`]'s: the given particles' sigmas
/// are floored by their frame's median, the cameras that missed a
/// particle counted against the most seen so far, as the forward pass
/// does; a recovered particle's sigma is floored by its frame's median
/// only (the forward pass also floors it by its trajectory's last point's,
/// which a stored run does not keep).
///
/// Memory: every frame's particles (about 80 bytes each) and every point
/// (about 200 bytes), as the CLI's pass.
pub fn extend_run(
    frames: Vec<RunFrame>,
    points: Vec<TrackPoint>,
    parameters: &TrackingParameters,
) -> Result<(Vec<TrackPoint>, BackwardSummary), super::TrackError> {
    parameters.validate()?;
    let mut stored: Vec<Stored> = Vec::with_capacity(frames.len());
    let mut rig = 0usize;
    let mut last: Option<i64> = None;
    for frame in frames {
        if let Some(last) = last {
            if frame.number <= last {
                return Err(super::TrackError::FrameOrder {
                    frame: frame.number,
                    last,
                });
            }
            // Skipped numbers are empty frames, as the forward pass takes
            // them.
            let skipped = (frame.number - last - 1).min(super::MAX_GAP as i64 + 2);
            for k in 0..skipped {
                stored.push(Stored {
                    number: frame.number - skipped + k,
                    particles: Vec::new(),
                    missing: Vec::new(),
                });
            }
        }
        last = Some(frame.number);
        let mut particles = frame.particles;
        let given = frame.given.min(particles.len());
        let median = super::floor_sigmas(&mut particles[..given]);
        for p in &mut particles[given..] {
            p.sigma = p.sigma.sup(&median);
        }
        rig = particles[..given]
            .iter()
            .map(|p| p.cameras)
            .fold(rig, usize::max);
        let missing = particles
            .iter()
            .map(|p| match p.cameras {
                0 => 0,
                c => rig.saturating_sub(c),
            })
            .collect();
        stored.push(Stored {
            number: frame.number,
            particles,
            missing,
        });
    }
    for point in &points {
        let known = stored
            .binary_search_by_key(&point.frame, |f| f.number)
            .ok()
            .is_some_and(|f| point.particle < stored[f].particles.len());
        if !known {
            return Err(super::TrackError::InvalidParticle {
                frame: point.frame,
                index: point.particle,
                reason: format!(
                    "trajectory {}'s point is no particle of the frames given",
                    point.trajectory
                ),
            });
        }
    }
    let cell = parameters.max_velocity.max(parameters.max_acceleration);
    let (paths, summary) = extend_paths(&stored, points, parameters, cell);
    let w = parameters.fit_half_window;
    Ok((refitted(paths, w, parameters.fit_order), summary))
}

/// The pass: the trajectories as paths after it (those joined into
/// another marked gone), and what it added.
fn extend_paths(
    frames: &[Stored],
    points: Vec<TrackPoint>,
    parameters: &TrackingParameters,
    cell: f64,
) -> (Vec<Path>, BackwardSummary) {
    let mut gathered = Gathered::default();
    gathered.extend(points);
    let index_of = |number: i64| frames.binary_search_by_key(&number, |f| f.number).ok();
    let (mut paths, mut holder) = paths_of(frames, gathered);
    let p = parameters;
    let mut summary = BackwardSummary::default();
    let mut scratch = Scratch::default();
    let mut links: Vec<Link> = Vec::new();
    let mut grids: Vec<Option<Grid>> = frames.iter().map(|_| None).collect();
    for k in (0..frames.len().saturating_sub(1)).rev() {
        let frame = &frames[k];
        let n = frame.number;
        let starting = starting_at(&paths, n, p.max_gap);
        // Grids of this frame and the one before it (the look-ahead, in
        // reverse); those of later frames are no longer needed.
        for g in [k, k.wrapping_sub(1)] {
            if g < frames.len() && grids[g].is_none() {
                grids[g] = Some(Grid::new(&frames[g].particles, &frames[g].missing, cell));
            }
        }
        if let Some(done) = grids.get_mut(k + 1) {
            *done = None;
        }
        if starting.is_empty() {
            continue;
        }
        let grid = grids[k].as_ref().expect("built above");
        let before = k.checked_sub(1).map(|b| {
            (
                grids[b].as_ref().expect("built above"),
                (n - frames[b].number) as f64,
            )
        });
        links.clear();
        for (l, &s) in starting.iter().enumerate() {
            let search = backward_search(&paths[s], n, p.max_acceleration);
            // Free particles, and the last points of other trajectories
            // ending here.
            let holder = &holder[k];
            let accept = |e: usize| {
                let h = holder[grid.order[e] as usize];
                h == FREE
                    || (h as usize != s
                        && paths[h as usize].points.back().map(|b| b.frame) == Some(n))
            };
            candidate_links(
                p,
                grid,
                before,
                &search,
                l,
                accept,
                &mut scratch,
                &mut links,
            );
        }
        links.sort_unstable();
        let mut taken_path = vec![false; starting.len()];
        let mut taken = vec![false; frame.particles.len()];
        for link in &links {
            if taken_path[link.live] || taken[link.particle] {
                continue;
            }
            let s = starting[link.live];
            let particle = &frame.particles[link.particle];
            let point = Sample {
                frame: n,
                position: particle.position.coords,
                sigma: particle.sigma,
            };
            let h = holder[k][link.particle];
            let other = (h != FREE).then(|| &paths[h as usize]);
            if !accepts_start(point, &paths[s], other, p) {
                continue;
            }
            taken_path[link.live] = true;
            taken[link.particle] = true;
            if h == FREE {
                let path = &mut paths[s];
                if !path.lengthened {
                    path.lengthened = true;
                    summary.lengthened += 1;
                }
                path.points.push_front(TrackPoint {
                    trajectory: path.id,
                    frame: n,
                    particle: link.particle,
                    position: particle.position,
                    derivatives: unfitted(),
                });
                path.sigma.push_front(particle.sigma);
                path.fresh.push_front(true);
                holder[k][link.particle] = s as u32;
                summary.points += 1;
            } else {
                join(&mut paths, (s, h as usize), &mut holder, &index_of);
                summary.joined += 1;
                if paths[s].lengthened {
                    paths[s].lengthened = false;
                    summary.lengthened -= 1;
                }
            }
        }
    }
    (paths, summary)
}

/// The trajectories that may gain a point at frame `n`: of two points or
/// more, starting after `n` by at most the bridged gap.
fn starting_at(paths: &[Path], n: i64, max_gap: usize) -> Vec<usize> {
    paths
        .iter()
        .enumerate()
        .filter(|(_, path)| {
            !path.gone
                && path.points.len() >= 2
                && path.points[0].frame > n
                && path.points[0].frame <= n + 1 + max_gap as i64
        })
        .map(|(s, _)| s)
        .collect()
}

/// Where `path`'s point at frame `n` is looked for: its first point moved
/// back by its first velocity, within the acceleration bound over the
/// frames between (and its position's noise).
fn backward_search(path: &Path, n: i64, max_acceleration: f64) -> Search {
    let (first, second) = (&path.points[0], &path.points[1]);
    let dt = (first.frame - n) as f64;
    // Its velocity backwards in time (mm per frame).
    let velocity = (first.position - second.position) / (second.frame - first.frame) as f64;
    let floor = noise_floor(&path.sigma[0]);
    Search {
        predicted: first.position + velocity * dt,
        radius: max_acceleration * dt * dt + floor,
        from: first.position,
        dt,
        velocity: Some(velocity),
        floor,
        source: 0,
    }
}

/// Whether `point` may start `path`: the first window with it is one
/// smooth path, the point no gross error at the start (the test the
/// forward pass gives a trajectory's first point), and the window its
/// velocity will be fitted from consistent at the fits' own level (module
/// docs: the links that pass only the gross-error tests are where the
/// added points' error was); and where the point is the last of `other`,
/// the two join smoothly.
fn accepts_start(point: Sample, path: &Path, other: Option<&Path>, p: &TrackingParameters) -> bool {
    let w = p.fit_half_window;
    let mut window = [point; MAX_SAMPLES];
    let len = (2 * w + 1).min(path.points.len() + 1).min(MAX_SAMPLES);
    for (i, slot) in window.iter_mut().enumerate().take(len).skip(1) {
        *slot = path.sample(i - 1);
    }
    if !is_smooth(&window[..len], 3)
        || end_is_intruder(&window[..len], true, w, p.fit_order)
        || !is_consistent(&window[..len], p.fit_order)
    {
        return false;
    }
    other.map_or(true, |other| joins_smoothly(point, other, path, w))
}

/// Path `s` joins path `h` (which ends at `s`'s new first point): `h`
/// takes `s`'s points after its own, their particles' holder becomes `h`,
/// and `s` is gone.
fn join(
    paths: &mut [Path],
    (s, h): (usize, usize),
    holder: &mut [Vec<u32>],
    index_of: &impl Fn(i64) -> Option<usize>,
) {
    let moved = std::mem::take(&mut paths[s].points);
    let moved_sigma = std::mem::take(&mut paths[s].sigma);
    let moved_fresh = std::mem::take(&mut paths[s].fresh);
    paths[s].gone = true;
    for q in &moved {
        let f = index_of(q.frame).expect("a point of a frame linked");
        holder[f][q.particle] = h as u32;
    }
    let other = &mut paths[h];
    if let Some(last) = other.fresh.back_mut() {
        *last = true;
    }
    other.points.extend(moved);
    other.sigma.extend(moved_sigma);
    other.fresh.extend(moved_fresh);
}

/// Whether `path`, starting with `point`, may join `other` (which ends
/// at the point's particle): the window across the junction, `w` points
/// on each side of the other's last point, is smooth, and the path does
/// not break there.
fn joins_smoothly(point: Sample, other: &Path, path: &Path, w: usize) -> bool {
    let mut window = [point; MAX_SAMPLES];
    let (m, _) = across(other, path, (w, w), &mut window);
    if !is_smooth(&window[..m], 3) {
        return false;
    }
    // Nor does the path break there (the test that cuts a trajectory
    // forward: a join must not undo a cut), with up to 4 points on each
    // side.
    let (m, k) = across(other, path, (3, 4), &mut window);
    !breaks_before(&window[..m], k)
}

/// Up to `before` points of `other` before its last, its last, and up to
/// `after` of `path`'s first, into `window`: how many, and where `path`'s
/// start.
fn across(
    other: &Path,
    path: &Path,
    (before, after): (usize, usize),
    window: &mut [Sample],
) -> (usize, usize) {
    let last = other.points.len() - 1;
    let mut m = 0;
    for i in last - before.min(last)..=last {
        window[m] = other.sample(i);
        m += 1;
    }
    let k = m;
    for i in 0..after.min(path.points.len()) {
        window[m] = path.sample(i);
        m += 1;
    }
    (m, k)
}

/// The forward pass's trajectories as paths, and per frame and particle
/// the path (slot) holding it.
fn paths_of(frames: &[Stored], gathered: Gathered) -> (Vec<Path>, Vec<Vec<u32>>) {
    let index_of = |number: i64| frames.binary_search_by_key(&number, |f| f.number).ok();
    // Per frame and particle, the trajectory (slot) holding it.
    let mut holder: Vec<Vec<u32>> = frames
        .iter()
        .map(|f| vec![FREE; f.particles.len()])
        .collect();
    let mut paths: Vec<Path> = Vec::new();
    for t in gathered.finish() {
        let slot = paths.len() as u32;
        let mut sigma = VecDeque::with_capacity(t.points.len());
        for p in &t.points {
            let f = index_of(p.frame).expect("a point of a frame linked");
            holder[f][p.particle] = slot;
            sigma.push_back(frames[f].particles[p.particle].sigma);
        }
        paths.push(Path {
            id: t.id,
            points: t.points.into(),
            fresh: vec![false; sigma.len()].into(),
            sigma,
            gone: false,
            lengthened: false,
        });
    }
    (paths, holder)
}

/// The paths kept, each with its number (those joined onto another are
/// gone: their numbers are no more); the derivatives of the points whose
/// windows reach a new point or a junction fitted again as the forward
/// pass fits them.
fn refitted(paths: Vec<Path>, w: usize, order: usize) -> Vec<TrackPoint> {
    let mut out = Vec::new();
    for path in paths.into_iter().filter(|path| !path.gone) {
        let id = path.id;
        let len = path.points.len();
        if !path.fresh.contains(&true) {
            for mut point in path.points {
                point.trajectory = id;
                out.push(point);
            }
            continue;
        }
        let samples: Vec<Sample> = (0..len).map(|k| path.sample(k)).collect();
        for (k, mut point) in path.points.into_iter().enumerate() {
            // Its fit reads points within 2 w of it.
            let reach = k.saturating_sub(2 * w)..(k + 2 * w + 1).min(len);
            if path.fresh.range(reach).any(|&f| f) {
                let first = k.saturating_sub(2 * w);
                let last = (k + 2 * w + 1).min(len);
                let fit = derivatives_at(&samples[first..last], k - first, w, order);
                point.derivatives = fit.derivatives.unwrap_or_else(unfitted);
            }
            point.trajectory = id;
            out.push(point);
        }
    }
    out
}

/// Derivatives of a point not fitted (yet, or at all: too few points).
fn unfitted() -> Derivatives {
    Derivatives {
        velocity: Vector3::repeat(f64::NAN),
        velocity_sigma: Vector3::repeat(f64::NAN),
        acceleration: None,
        acceleration_sigma: None,
    }
}
