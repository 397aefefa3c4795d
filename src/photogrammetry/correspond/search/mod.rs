//! The search of one frame (steps 2 to 6 of the [module
//! doc](super)): the state shared by its steps (which targets are used,
//! the groups accepted so far, the acceptance threshold) and the
//! geometric queries they all make: a target's epipolar band in another
//! camera, the targets near a predicted image, and how a group's rays
//! meet. The steps are in their own files: seed pairs and their
//! completion ([`completion`]), best-first selection with the noise
//! estimate ([`selection`]), the exchange of near-coincident targets
//! ([`exchange`]), unambiguous pairs ([`pairs`]); the least-squares points
//! (Eq. 21-23) are here.

mod completion;
mod exchange;
mod pairs;
mod selection;

use nalgebra::{Point2, Point3};

use self::completion::CandidateGroups;
use super::epipolar::{clip, EpipolarCurve};
use super::grid::CameraFrame;
use super::matcher::Matcher;
use super::pencil::PencilGrid;
use super::Particle;
use crate::photogrammetry::camera::Ray;
use crate::photogrammetry::cancel::{Cancel, Cancelled};
use crate::photogrammetry::intersect::{intersect_from, ray_midpoint, Observation};
use crate::photogrammetry::target::Target;

/// A marker for "no target" in the flat group arrays.
const NONE: u32 = u32::MAX;

/// How many cameras a group's members hold a target in. A count, not a
/// byte: a rig may have 256 cameras or more.
fn size(members: &[u32]) -> usize {
    members.iter().filter(|&&m| m != NONE).count()
}

/// How the rays of a group meet (pixels).
#[derive(Clone, Copy, Debug)]
struct GroupFit {
    /// RMS miss of the rays from their nearest point.
    spread: f64,
    /// The largest miss.
    largest: f64,
    /// The camera whose ray misses most, among those that may be dropped.
    worst: Option<usize>,
}

/// The state of one frame's search.
pub(super) struct Search<'m, 'f> {
    matcher: &'m Matcher,
    frames: &'f [CameraFrame],
    used: Vec<Vec<bool>>,
    /// Per ordered camera pair `(i, j)` at `i * count + j`: camera j's
    /// targets filed along the epipolar curves from camera i, built when a
    /// band first needs it, of the targets unused then (bands look for
    /// unused targets only; a target freed again, in [`Self::improve`],
    /// drops every grid).
    pencil_grids: Vec<Option<PencilGrid>>,
    /// Per camera: the current target's epipolar curve in it.
    curves: Vec<EpipolarCurve>,
    /// The epipolar band's half-width (px): the tolerance, or less once the
    /// first seed pair's probe has shown the frame's noise needs less
    /// ([`Search::first_stage`]).
    band_px: f64,
    /// The largest miss (px) a group member may have, and the largest
    /// residual of a particle's intersection: the tolerance, or less once
    /// the frame's image noise is known (see [`Search::estimate_noise`]).
    acceptance: f64,
    /// The groups accepted so far: members per camera (NONE for none),
    /// group after group, a stride of the camera count.
    accepted: Vec<u32>,
    /// Per camera and target, the accepted group that holds it, or NONE.
    owner: Vec<Vec<u32>>,
    /// Checked in the outer loops; once it fires, the steps end early and
    /// [`Search::run`] gives the reason.
    cancel: Option<Cancel>,
    /// Why the search stopped early, once it did.
    stopped: Option<Cancelled>,
}

/// Outer-loop iterations between two checks of the cancel token (each
/// iteration is a band search, microseconds).
const CHECK_EVERY: usize = 64;

/// [`Search::should_stop`] on the two fields, for loops that hold other
/// borrows of the search.
fn stop_at(cancel: Option<&Cancel>, stopped: &mut Option<Cancelled>, step: usize) -> bool {
    if stopped.is_some() {
        return true;
    }
    if step % CHECK_EVERY != 0 {
        return false;
    }
    match cancel.map(Cancel::check) {
        Some(Err(reason)) => {
            *stopped = Some(reason);
            true
        }
        _ => false,
    }
}

impl<'m, 'f> Search<'m, 'f> {
    pub(super) fn new(matcher: &'m Matcher, frames: &'f [CameraFrame]) -> Self {
        Search {
            matcher,
            frames,
            used: frames
                .iter()
                .map(|f| vec![false; f.targets.len()])
                .collect(),
            pencil_grids: frames
                .iter()
                .flat_map(|_| frames.iter().map(|_| None))
                .collect(),
            curves: frames.iter().map(|_| EpipolarCurve::default()).collect(),
            band_px: matcher.tolerance,
            acceptance: matcher.tolerance,
            accepted: Vec::new(),
            owner: frames.iter().map(|f| vec![NONE; f.targets.len()]).collect(),
            cancel: None,
            stopped: None,
        }
    }

    /// The search, stopping early once `cancel` fires.
    pub(super) fn until(mut self, cancel: &Cancel) -> Self {
        self.cancel = Some(cancel.clone());
        self
    }

    /// Whether to stop: checks the token at every `CHECK_EVERY`th `step`
    /// of an outer loop and remembers why it fired.
    fn should_stop(&mut self, step: usize) -> bool {
        stop_at(self.cancel.as_ref(), &mut self.stopped, step)
    }

    /// Traces target `a` of camera `i` into camera `j` (`self.curves[j]`);
    /// false if its ray misses the volume or does not image there.
    fn trace(&mut self, i: usize, a: usize, j: usize) -> bool {
        let Some(ray) = self.frames[i].ray(a) else {
            return false;
        };
        let Some(span) = clip(&ray, &self.matcher.volume) else {
            return false;
        };
        let parts = self.matcher.epipolar[i * self.frames.len() + j].parts;
        self.curves[j].trace(&self.matcher.cameras[j], &ray, span, parts)
    }

    /// The epipolar band of target `a` of camera `i` in camera `j`: calls
    /// `found` once for each unused target of camera j within the band's
    /// half-width (`band_px`) of the curve.
    pub(super) fn band(&mut self, i: usize, a: usize, j: usize, mut found: impl FnMut(usize)) {
        if !self.trace(i, a, j) {
            return;
        }
        let tolerance = self.band_px;
        let frame = &self.frames[j];
        let pair = i * self.frames.len() + j;
        let used = &self.used[j];
        let grid = self.pencil_grids[pair].get_or_insert_with(|| {
            PencilGrid::new(
                self.matcher.epipolar[pair].pencil,
                (0..frame.targets.len())
                    .filter(|&b| !used[b])
                    .map(|b| (b, frame.position(b))),
                tolerance,
            )
        });
        grid.begin_band();
        let curve = &self.curves[j];
        let reference = &self.frames[i].targets[a];
        let tolerance_sq = tolerance * tolerance;
        // Each part is walked in spans about two cells long (one to eight
        // were tried on the benchmark: shorter spans cost more visits,
        // longer ones boxes that stray from the curve), each widened by how
        // far the parabola strays from the span's chord.
        for part in curve.parts() {
            let spans = (part.chord_length() / (2.0 * grid.cell_diameter()))
                .ceil()
                .clamp(1.0, 256.0) as usize;
            let du = 1.0 / spans as f64;
            let margin = tolerance + part.deviation(du);
            let mut start = part.at(0.0);
            let mut start_coordinates = grid.coordinates(&start);
            for span in 1..=spans {
                let end = part.at(span as f64 * du);
                let end_coordinates = grid.coordinates(&end);
                grid.visit_piece(
                    (&start, &end),
                    (start_coordinates, end_coordinates),
                    margin,
                    |grid, cell| {
                        for &b in grid.cell(cell) {
                            let b = b as usize;
                            if !used[b]
                                && curve.within(&frame.position(b), tolerance_sq)
                                && self.matcher.similar(reference, &frame.targets[b])
                            {
                                found(b);
                            }
                        }
                    },
                );
                (start, start_coordinates) = (end, end_coordinates);
            }
        }
    }

    /// The targets of camera `k` within `radius` of `pixel`.
    fn near(
        &self,
        k: usize,
        pixel: Point2<f64>,
        radius: f64,
        reference: &Target,
        out: &mut Vec<u32>,
    ) {
        out.clear();
        let margin = nalgebra::Vector2::repeat(radius);
        let radius_sq = radius * radius;
        let frame = &self.frames[k];
        let used = &self.used[k];
        frame.grid.visit(pixel - margin, pixel + margin, |c| {
            if !used[c]
                && (frame.position(c) - pixel).norm_squared() <= radius_sq
                && self.matcher.similar(reference, &frame.targets[c])
            {
                out.push(c as u32);
            }
        });
    }

    /// The square of how far a ray of camera `k` passes from `point`, in
    /// that camera's pixels (distance times the camera's scale at the
    /// point's range).
    #[inline]
    fn miss_px_sq(&self, k: usize, ray: &Ray, point: &Point3<f64>) -> f64 {
        let rel = point - ray.origin;
        let along = rel.dot(&ray.direction);
        let miss_sq = (rel.norm_squared() - along * along).max(0.0);
        let range_sq = (point - self.matcher.cameras[k].position()).norm_squared();
        let scale = self.matcher.pixels_per_unit_angle[k];
        miss_sq * scale * scale / range_sq
    }

    /// How a group's rays meet, with the worst camera among those for which
    /// `droppable` holds.
    fn fit(&self, members: &[u32], droppable: impl Fn(usize) -> bool) -> Option<GroupFit> {
        let ray = |k: usize| match members[k] {
            NONE => None,
            m => self.frames[k].ray(m as usize),
        };
        let point = ray_midpoint((0..members.len()).filter_map(ray))?;
        let (mut sum, mut count, mut largest) = (0.0, 0u32, 0f64);
        let mut worst = (None, f64::NEG_INFINITY);
        for k in 0..members.len() {
            let Some(ray) = ray(k) else {
                continue;
            };
            let px_sq = self.miss_px_sq(k, &ray, &point);
            sum += px_sq;
            count += 1;
            largest = largest.max(px_sq);
            if droppable(k) && px_sq > worst.1 {
                worst = (Some(k), px_sq);
            }
        }
        Some(GroupFit {
            spread: (sum / f64::from(count)).sqrt(),
            largest: largest.sqrt(),
            worst: worst.0,
        })
    }

    /// Drops the worst member of a group until every ray meets the others
    /// within `limit`; how they then meet, or `None` if that leaves fewer
    /// than three cameras (or only `keep` ones).
    fn trim(
        &self,
        group: &mut [u32],
        limit: f64,
        keep: impl Fn(usize) -> bool,
    ) -> Option<GroupFit> {
        loop {
            let size = size(group);
            if size < 3 {
                return None;
            }
            let fit = self.fit(group, |k| !keep(k))?;
            if fit.largest <= limit {
                return Some(fit);
            }
            if size == 3 {
                return None;
            }
            group[fit.worst?] = NONE;
        }
    }

    /// Steps 2 to 6: the particles of the frame, or why the search was
    /// stopped before its end.
    pub(super) fn run(mut self) -> Result<Vec<Particle>, Cancelled> {
        self.seed_stages(Self::select);
        if !self.should_stop(0) {
            self.improve();
        }
        if self.matcher.min_cameras == 2 && !self.should_stop(0) {
            self.pairs();
        }
        self.particles()
    }

    /// Every candidate group of the frame (see [`Matcher::candidates`]):
    /// the seed stages as in [`Search::run`], each group trimmed to the
    /// acceptance threshold and kept once, none marking its targets used.
    pub(super) fn candidates(mut self) -> Result<Vec<Particle>, Cancelled> {
        let mut kept = std::collections::HashSet::new();
        self.seed_stages(|search, groups| search.keep_all(groups, &mut kept));
        self.particles()
    }

    /// Steps 2 and 3 for every seed pair (three cameras or more), the first
    /// with the frame's noise estimate, each stage's groups handed to
    /// `take` before the next stage's search.
    fn seed_stages(&mut self, mut take: impl FnMut(&mut Self, CandidateGroups)) {
        if self.frames.len() < 3 {
            return;
        }
        let matcher = self.matcher;
        for (stage, &seed) in matcher.seeds.iter().enumerate() {
            let groups = if stage == 0 {
                let groups = self.first_stage(seed);
                self.estimate_noise(&groups);
                groups
            } else {
                self.candidate_groups(seed)
            };
            take(self, groups);
        }
    }

    /// Step 6 over the accepted groups, or why the search stopped early.
    fn particles(mut self) -> Result<Vec<Particle>, Cancelled> {
        let particles = self.finish();
        match self.stopped {
            Some(reason) => Err(reason),
            None => Ok(particles),
        }
    }

    /// Least-squares intersection of a group, with its targets numbered as
    /// in the caller's lists; `None` unless every residual is within the
    /// acceptance threshold. `observations` is scratch space.
    fn intersect(&self, members: &[u32], observations: &mut Vec<Observation>) -> Option<Particle> {
        observations.clear();
        observations.extend(members.iter().enumerate().filter(|(_, &m)| m != NONE).map(
            |(k, &m)| Observation {
                camera: k,
                pixel: self.frames[k].position(m as usize),
            },
        ));
        if observations.len() < self.matcher.min_cameras {
            return None;
        }
        let rays = observations
            .iter()
            .filter_map(|o| self.frames[o.camera].ray(members[o.camera] as usize));
        let start = ray_midpoint(rays)?;
        let result = intersect_from(&self.matcher.cameras, observations, start).ok()?;
        let worst = result
            .residuals_px
            .iter()
            .map(|r| r.norm())
            .fold(0.0, f64::max);
        (worst <= self.acceptance).then(|| Particle {
            position: result.point,
            sigma: result.sigma,
            rms_px: result.rms_px,
            targets: members
                .iter()
                .enumerate()
                .map(|(k, &m)| (m != NONE).then(|| self.frames[k].original[m as usize] as usize))
                .collect(),
        })
    }

    /// Accepts a group: its targets are used from now on.
    fn keep(&mut self, members: &[u32]) {
        let index = (self.accepted.len() / self.frames.len()) as u32;
        for (k, &m) in members.iter().enumerate() {
            if m != NONE {
                self.used[k][m as usize] = true;
                self.owner[k][m as usize] = index;
            }
        }
        self.accepted.extend_from_slice(members);
    }

    /// Accepted group `p`'s members.
    fn group(&self, p: usize) -> &[u32] {
        let count = self.frames.len();
        &self.accepted[p * count..(p + 1) * count]
    }

    /// The particles: every accepted group's least-squares intersection.
    fn finish(&mut self) -> Vec<Particle> {
        let mut observations = Vec::with_capacity(self.frames.len());
        let mut particles = Vec::new();
        let mut stopped = self.stopped;
        for (step, members) in self.accepted.chunks_exact(self.frames.len()).enumerate() {
            if stop_at(self.cancel.as_ref(), &mut stopped, step) {
                break;
            }
            particles.extend(self.intersect(members, &mut observations));
        }
        self.stopped = stopped;
        particles
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn group_sizes_count_past_255_cameras() {
        // The candidate groups' sizes once were bytes: 256 cameras wrapped
        // to 0 and ranked a full group last.
        let mut members = vec![0; 300];
        members[7] = NONE;
        assert_eq!(size(&members), 299);
    }
}
