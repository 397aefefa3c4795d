//! Tracking: the particles of consecutive frames linked into trajectories
//! in object space, after Malik, Dracos and Papantoniou (1993), *Particle
//! tracking velocimetry in three-dimensional flows, Part II: Particle
//! tracking* (Exp. Fluids 15), section 3, with velocities and
//! accelerations from local polynomial fits ([`kinematics`]).
//!
//! **Linking, frame `t` to `t+1`** (decided once frame `t+2` is in: the
//! look-ahead):
//!
//! 1. Every trajectory predicts its next position: with two or more points
//!    `x̂ = x_t + v Δ` (`v` its last velocity, `Δ` the frames since its last
//!    point), searched within `max_acceleration Δ²` plus a noise floor; a
//!    trajectory of one point (just started) searches within
//!    `max_velocity Δ` around itself. Every link also keeps `|x_{t+1} -
//!    x_t| ≤ max_velocity Δ`.
//! 2. Each candidate `c` in `t+1` is judged by the look-ahead: from `c`
//!    with the velocity the link implies, the particles of `t+2` near the
//!    next prediction; the link's cost is the least change of acceleration
//!    over the four positions `x_{t-1}, x_t, c, d` (Malik et al.'s
//!    smoothest trajectory), or for a trajectory of one point the least
//!    acceleration over `x_t, c, d`. Links without any `d` rank after all
//!    links with one, by their own acceleration; a new trajectory's first
//!    link needs a `d` (one unconfirmed step between two random particles
//!    is no evidence), except at the sequence's last frame.
//! 3. **Conflicts are resolved globally**: every candidate link of the
//!    frame, of every trajectory, is ranked by cost, and taken best first
//!    where neither its trajectory nor its particle is taken. No
//!    trajectory is served first because of where it stands in a list.
//!    **Ghosts** (a group of the correspondences whose rays meet by
//!    chance; it moves with the particles whose images it borrows, so it
//!    makes a smooth track too): the fewer cameras see a point, the likelier
//!    it is one. A link to a candidate missed by `m` of the rig's cameras
//!    (the most any particle so far was seen by), or from a trajectory of
//!    one such point, pays `m` x [`WEAK_PENALTY`] times the RMS the noise
//!    gives its cost (`sqrt(20) |sigma|`): among candidates of similar
//!    cost the one seen by all cameras wins.
//! 4. A trajectory with no link keeps predicting for up to `max_gap`
//!    frames (gaps of one or two frames, where the correspondences missed
//!    the particle), then ends. Particles of `t+1` no trajectory took start
//!    new ones.
//!
//! **The test for ghosts' trajectories.** A real particle misses a
//! camera at random, independently from frame to frame, so it is seen by
//! all cameras in about the share `f` of the frame's particles that are;
//! a ghost rarely is. A trajectory whose points are mostly not seen by
//! all, with fewer such points than a real particle would show with
//! probability [`GHOST_TEST_LEVEL`] (binomial with the frames' `f`), is
//! never reported, and ends (a real particle's next point would start a
//! new trajectory, losing only the points rejected). It is decided after enough points for the test to have
//! power (`(1 - f)^n` under the level; at least `min_length`, at most
//! [`MAX_DECISION_LENGTH`]) or at its end. Relative to the rig: where
//! every particle is seen by all cameras (2 cameras, or counts unknown)
//! nothing is rejected. On the simulated flow of `examples/track_report`
//! it changes little: the matcher's ghosts there are 0.01-0.1% of the
//! 3- and 4-camera particles (3-11% of the 2-camera ones).
//!
//! **Search.** Each frame's particles are filed in a sorted cell index
//! (counting sort by cell over the frame's bounding box, cells of the
//! larger of the two limits, a flat array of cell starts, and what a
//! link's cost reads of a particle in cell order): a search reads one
//! contiguous run of cells per column of its box. The trajectories search
//! in the order of their predictions' cells (another counting sort), so
//! that consecutive searches read neighbouring memory. The instructions
//! per particle and frame are constant from 2,500 to 40,000 particles
//! (`benches/track.rs`: 6.5 ms a frame at 10,000 on one core; the time
//! per particle still grows as the data outgrow the caches).
//!
//! **Paths that break.** A trajectory that lost its particle (its images
//! missed, or it left the volume) may go on through a free particle near
//! its prediction, and from there through another each frame; each link
//! is within the limits, which the flow's own accelerations set, and each
//! point is a real particle, so neither the linking nor the test for
//! ghosts stops it. Before a point is handed out, the path is tested on
//! each side of it ([`kinematics`]' `breaks_before`): the point off the
//! cubic through the 4 points before it, and the point before off the
//! cubic through the 4 from it on, both at the gross-error level. A single
//! wrong point whose neighbours are one path without it leaves the
//! trajectory; otherwise the trajectory is cut there: it keeps what it
//! handed out and ends, and the rest goes on as a new trajectory on
//! probation, reported only once a window of `2 w + 3` of its first points
//! is one smooth path (so a chain of others' points, which rarely is,
//! is never reported). Every new trajectory also loses leading points
//! until its first window of `2 w + 1` is smooth. On `examples/track_report`
//! at 0.44 of the spacing per frame this took the wrong links from 0.93%
//! to 0.24% and the velocity's RMS error from 7.6% to 4.7%, for 0.5% of
//! the links (recall 0.9863 to 0.9813); at 0.32, 8,000 particles, wrong
//! links 0.16% to 0.10%, velocity 1.56% to 1.33%. The test runs only
//! where the window centred on the point is not consistent (it holds the
//! point and the one before, so a break would show there): 10% more
//! instructions (`benches/track.rs` under callgrind, `PTV_TRACK_ONCE=10000`:
//! 957 to 1,049 million; testing every point cost 42%). It needs `w` of at
//! least 2 (4 points on each side are kept); trajectories of fewer than
//! `2 w + 1` points cannot be tested and are reported as before.
//!
//! **Output, streamed.** A trajectory is reported once it has
//! `min_length` points and passed the test for ghosts; from then on each point is handed out as soon as
//! its fit window is complete (or the trajectory ended), with velocity and
//! acceleration from the fit. The tracker keeps only the frames of the
//! look-ahead and, per live trajectory, the points not yet handed out and
//! the window behind them: memory is bounded by the live particles and the
//! window, not by the sequence's length.
//!
//! Pure and deterministic: the same frames give the same trajectories
//! (equal costs, which continuous positions make rare, are ranked by
//! trajectory and then particle index).

pub mod backward;
mod grid;
pub mod kinematics;
mod links;
mod live;
mod parameters;
pub mod recovery;

use std::collections::{HashMap, VecDeque};

use nalgebra::{Point3, Vector3};

pub use backward::BackwardSummary;
pub use kinematics::Derivatives;
use kinematics::{
    breaks_before, derivatives_at, end_is_intruder, is_outlier, is_smooth, NoiseScale, Sample,
    MAX_SAMPLES,
};
pub use recovery::{FrameTargets, ImageSpaceRecovery};

use grid::Grid;
pub use links::WEAK_PENALTY;
use links::{candidate_links, floor_sigmas, noise_floor, short_path_is_smooth, Scratch, Search};
use live::{Live, Node};
pub use live::{GHOST_TEST_LEVEL, MAX_DECISION_LENGTH};
pub use parameters::{
    TrackingParameters, MAX_CANDIDATES, MAX_DISPLACEMENT, MAX_GAP, MAX_MIN_LENGTH,
};

use super::correspond::{readable, Particle};
use super::volume::Volume;

/// One particle of a frame, as tracking takes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParticlePosition {
    /// Position (mm).
    pub position: Point3<f64>,
    /// Standard deviations of X, Y, Z (mm), each above zero: the
    /// intersection's, or the lab's estimate where a file has none.
    pub sigma: Vector3<f64>,
    /// How many cameras saw it (the correspondences' group size); 0 where
    /// that is unknown (particle files without target columns), which
    /// counts as seen by all.
    pub cameras: usize,
}

impl ParticlePosition {
    /// A particle whose camera count is unknown (counted as seen by all).
    pub fn new(position: Point3<f64>, sigma: Vector3<f64>) -> Self {
        ParticlePosition {
            position,
            sigma,
            cameras: 0,
        }
    }

    /// A particle seen by `cameras` cameras.
    pub fn seen_by(position: Point3<f64>, sigma: Vector3<f64>, cameras: usize) -> Self {
        ParticlePosition {
            position,
            sigma,
            cameras,
        }
    }
}

/// A point of a trajectory.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackPoint {
    /// The trajectory (numbered from 0 in the order trajectories reach
    /// `min_length`).
    pub trajectory: u64,
    /// The frame number.
    pub frame: i64,
    /// The particle's index in that frame's input.
    pub particle: usize,
    /// Position (mm).
    pub position: Point3<f64>,
    /// Velocity and acceleration from the fit.
    pub derivatives: Derivatives,
}

/// A whole trajectory: its points in frame order.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    /// Its number.
    pub id: u64,
    /// Its points.
    pub points: Vec<TrackPoint>,
}

/// Why tracking cannot go on.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TrackError {
    /// A parameter out of range.
    #[error("invalid tracking parameter: {0}")]
    InvalidParameter(String),
    /// Frames must come in increasing order.
    #[error("frame {frame} came after frame {last}; give the frames in increasing order")]
    FrameOrder {
        /// The frame given.
        frame: i64,
        /// The frame before it.
        last: i64,
    },
    /// A frame's targets for the image-space recovery that do not fit
    /// the recovery's cameras.
    #[error("frame {frame}: targets of {given} cameras, the recovery's calibration has {cameras}")]
    TargetCameras {
        /// The frame.
        frame: i64,
        /// Cameras with targets given.
        given: usize,
        /// Cameras of the recovery.
        cameras: usize,
    },
    /// A particle that is not a position.
    #[error("frame {frame}, particle {index}: {reason}")]
    InvalidParticle {
        /// The frame.
        frame: i64,
        /// The particle's index in it.
        index: usize,
        /// What is wrong.
        reason: String,
    },
}

/// A frame in the look-ahead.
struct Frame {
    number: i64,
    particles: Vec<ParticlePosition>,
    /// Per particle, the cameras short of the rig's count that missed it
    /// (0 where it was seen by all or the count is unknown).
    missing: Vec<usize>,
    /// The share of the frame's particles seen by all cameras.
    full_share: f64,
    grid: Grid,
    /// The frame's targets, where the image-space recovery runs.
    targets: Option<FrameTargets>,
    /// The particles given; those after them are recovered.
    given: usize,
    /// The particles found in the images, in `particles` after `given`.
    recovered: Vec<Particle>,
    /// The median of the given particles' sigmas (per axis), the floor of
    /// a recovered particle's ([`floor_sigmas`]).
    median_sigma: Vector3<f64>,
}

/// The particles a frame gained from the image-space recovery
/// ([`Tracker::take_recovered`]).
#[derive(Clone, Debug, PartialEq)]
pub struct RecoveredParticles {
    /// The frame.
    pub frame: i64,
    /// The index in the frame of the first of them: the number of
    /// particles given ([`TrackPoint::particle`] counts on from there).
    pub first: usize,
    /// The particles, in index order.
    pub particles: Vec<Particle>,
}

/// Links particles of consecutive frames into trajectories, frame by frame
/// ([`Tracker::push`], then [`Tracker::finish`]).
pub struct Tracker {
    parameters: TrackingParameters,
    /// The image-space recovery, where frames come with their targets.
    recovery: Option<ImageSpaceRecovery>,
    /// Frames that left the look-ahead with recovered particles, not yet
    /// taken.
    recovered: Vec<RecoveredParticles>,
    /// Frames given but not yet linked to: at most two.
    ahead: VecDeque<Frame>,
    live: Vec<Live>,
    next_id: u64,
    last_frame: Option<i64>,
    /// The most cameras any particle so far was seen by: the rig's count.
    rig_cameras: usize,
    /// How the fits' residuals compare with the points' sigmas, for the
    /// test of short trajectories ([`short_path_is_smooth`]).
    noise_scale: NoiseScale,
    /// With backward tracking ([`Tracker::extending_backward`]): every
    /// frame linked and every point, until the end.
    backward: Option<(Vec<backward::Stored>, Vec<TrackPoint>)>,
}

/// The end of a sequence ([`Tracker::finish_all`]).
#[derive(Debug)]
pub struct Finished {
    /// The last points (all of them, with backward tracking).
    pub points: Vec<TrackPoint>,
    /// The particles recovered in the frames linked last
    /// ([`Tracker::take_recovered`]).
    pub recovered: Vec<RecoveredParticles>,
    /// What backward tracking added, where it ran.
    pub backward: Option<BackwardSummary>,
}

impl Tracker {
    /// A tracker; the parameters are checked.
    pub fn new(parameters: TrackingParameters) -> Result<Self, TrackError> {
        parameters.validate()?;
        Ok(Tracker {
            parameters,
            recovery: None,
            recovered: Vec::new(),
            ahead: VecDeque::new(),
            live: Vec::new(),
            next_id: 0,
            last_frame: None,
            rig_cameras: 0,
            noise_scale: NoiseScale::new(),
            backward: None,
        })
    }

    /// The same tracker, extending every trajectory backwards in time
    /// once the sequence ends ([`backward`]): its points are all handed
    /// out by [`Tracker::finish_all`] (every push returns none), and it
    /// holds the whole sequence until then.
    pub fn extending_backward(mut self) -> Self {
        self.backward = Some((Vec::new(), Vec::new()));
        self
    }

    /// Whether it extends the trajectories backwards at the end
    /// ([`Tracker::extending_backward`]).
    pub fn is_extending_backward(&self) -> bool {
        self.backward.is_some()
    }

    /// A tracker that also looks in the images for the particles the
    /// correspondences missed ([`recovery`]), in the frames given with
    /// their targets ([`Tracker::push_with_targets`]).
    pub fn with_recovery(
        parameters: TrackingParameters,
        recovery: ImageSpaceRecovery,
    ) -> Result<Self, TrackError> {
        let mut tracker = Tracker::new(parameters)?;
        tracker.recovery = Some(recovery);
        Ok(tracker)
    }

    /// Takes the particles of frame `number` (numbers increasing; a number
    /// skipped is a frame with no particles) and returns the trajectory
    /// points that became final.
    pub fn push(
        &mut self,
        number: i64,
        particles: Vec<ParticlePosition>,
    ) -> Result<Vec<TrackPoint>, TrackError> {
        self.push_frame(number, particles, None)
    }

    /// [`Tracker::push`] with the frame's targets ([`FrameTargets`]: per
    /// camera, and which of them the particles use), for the image-space
    /// recovery of a tracker made [`Tracker::with_recovery`] (without one
    /// the targets are not needed, and ignored). Particles recovered in
    /// this frame are numbered after the ones given; which they are comes
    /// from [`Tracker::take_recovered`], before or with their points.
    pub fn push_with_targets(
        &mut self,
        number: i64,
        particles: Vec<ParticlePosition>,
        targets: FrameTargets,
    ) -> Result<Vec<TrackPoint>, TrackError> {
        if let Some(recovery) = &self.recovery {
            if targets.cameras() != recovery.cameras().len() {
                return Err(TrackError::TargetCameras {
                    frame: number,
                    given: targets.cameras(),
                    cameras: recovery.cameras().len(),
                });
            }
        }
        self.push_frame(number, particles, Some(targets))
    }

    /// The particles recovered in the frames that have left the
    /// look-ahead since the last call (no more are recovered in them), in
    /// frame order. Call it after each push: a point of a recovered
    /// particle is handed out no earlier than the push that makes its
    /// frame's entry available here.
    pub fn take_recovered(&mut self) -> Vec<RecoveredParticles> {
        std::mem::take(&mut self.recovered)
    }

    fn push_frame(
        &mut self,
        number: i64,
        particles: Vec<ParticlePosition>,
        targets: Option<FrameTargets>,
    ) -> Result<Vec<TrackPoint>, TrackError> {
        if let Some(last) = self.last_frame {
            if number <= last {
                return Err(TrackError::FrameOrder {
                    frame: number,
                    last,
                });
            }
        }
        for (index, p) in particles.iter().enumerate() {
            let reason = if !p.position.iter().all(|v| v.is_finite()) {
                "its position is not finite"
            } else if !p.sigma.iter().all(|s| s.is_finite() && *s > 0.0) {
                "its standard deviations must be finite and above zero"
            } else {
                continue;
            };
            return Err(TrackError::InvalidParticle {
                frame: number,
                index,
                reason: reason.into(),
            });
        }
        let mut out = Vec::new();
        // Skipped frame numbers are empty frames, as far as they matter:
        // beyond the longest gap every trajectory has ended anyway.
        if let Some(last) = self.last_frame {
            let skipped = (number - last - 1).min(MAX_GAP as i64 + 2);
            for k in 0..skipped {
                self.take(number - skipped + k, Vec::new(), None, &mut out);
            }
        }
        let targets = targets.filter(|_| self.recovery.is_some());
        self.take(number, particles, targets, &mut out);
        self.last_frame = Some(number);
        if let Some((_, held)) = &mut self.backward {
            held.append(&mut out);
        }
        Ok(out)
    }

    /// Ends the sequence: links what is left and returns the last points.
    pub fn finish(self) -> Vec<TrackPoint> {
        self.finish_with_recovered().0
    }

    /// [`Tracker::finish`], with the particles recovered in the frames
    /// linked last ([`Tracker::take_recovered`]).
    pub fn finish_with_recovered(self) -> (Vec<TrackPoint>, Vec<RecoveredParticles>) {
        let finished = self.finish_all();
        (finished.points, finished.recovered)
    }

    /// Ends the sequence: links what is left and, with backward tracking,
    /// extends the trajectories backwards; returns the points not yet
    /// handed out, the particles recovered in the frames linked last, and
    /// what backward tracking added.
    pub fn finish_all(mut self) -> Finished {
        let mut out = Vec::new();
        while let Some(mut next) = self.ahead.pop_front() {
            let ahead = self.ahead.pop_front();
            self.step(&mut next, ahead.as_ref(), &mut out);
            self.keep_recovered(next);
            self.ahead.extend(ahead);
        }
        for live in std::mem::take(&mut self.live) {
            self.end(live, &mut out);
        }
        let mut summary = None;
        if let Some((frames, mut held)) = self.backward.take() {
            held.append(&mut out);
            let (points, added) = backward::extend(&frames, held, &self.parameters, self.cell());
            out = points;
            summary = Some(added);
        }
        Finished {
            points: out,
            recovered: self.recovered,
            backward: summary,
        }
    }

    /// Points held (not yet handed out, or kept for their neighbours'
    /// fits): for a test of the memory bound.
    pub fn held_points(&self) -> usize {
        self.live.iter().map(|l| l.nodes.len()).sum::<usize>()
            + self.ahead.iter().map(|f| f.particles.len()).sum::<usize>()
    }

    fn take(
        &mut self,
        number: i64,
        mut particles: Vec<ParticlePosition>,
        targets: Option<FrameTargets>,
        out: &mut Vec<TrackPoint>,
    ) {
        let median_sigma = floor_sigmas(&mut particles);
        self.rig_cameras = particles
            .iter()
            .map(|p| p.cameras)
            .fold(self.rig_cameras, usize::max);
        let missing: Vec<usize> = particles
            .iter()
            .map(|p| match p.cameras {
                0 => 0,
                c => self.rig_cameras - c,
            })
            .collect();
        let full_share = if particles.is_empty() {
            1.0
        } else {
            missing.iter().filter(|&&m| m == 0).count() as f64 / particles.len() as f64
        };
        self.ahead.push_back(Frame {
            number,
            grid: Grid::new(&particles, &missing, self.cell()),
            given: particles.len(),
            particles,
            targets,
            recovered: Vec::new(),
            median_sigma,
            missing,
            full_share,
        });
        if self.ahead.len() == 2 {
            let mut next = self.ahead.pop_front().expect("two frames");
            let ahead = self.ahead.pop_front();
            self.step(&mut next, ahead.as_ref(), out);
            self.keep_recovered(next);
            self.ahead.extend(ahead);
        }
    }

    /// The side of the particle grid's cells (mm): the larger of the
    /// velocity and acceleration limits (fewer, fuller cells: fewer runs
    /// per search).
    fn cell(&self) -> f64 {
        self.parameters
            .max_velocity
            .max(self.parameters.max_acceleration)
    }

    /// Keeps what `frame` recovered for [`Tracker::take_recovered`].
    fn keep_recovered(&mut self, frame: Frame) {
        if let Some((frames, _)) = &mut self.backward {
            frames.push(backward::Stored {
                number: frame.number,
                particles: frame.particles,
                missing: frame.missing,
            });
        }
        if !frame.recovered.is_empty() {
            self.recovered.push(RecoveredParticles {
                frame: frame.number,
                first: frame.given,
                particles: frame.recovered,
            });
        }
    }

    /// The image-space recovery ([`recovery`]) in `next`: for every
    /// trajectory with a velocity whose prediction has no particle of
    /// `next` within its search radius, a particle intersected from the
    /// unused targets there, added to `next`.
    fn recover(&self, next: &mut Frame) {
        let (Some(recovery), Some(targets)) = (&self.recovery, next.targets.as_mut()) else {
            return;
        };
        let mut near = Vec::new();
        let mut nearest = Vec::new();
        let before = next.particles.len();
        for live in &self.live {
            if live.velocity().is_none() {
                continue;
            }
            let (predicted, radius) = self.prediction(live, next.number);
            if next.grid.is_small(radius) {
                near.clear();
                next.grid.within(&predicted, radius, &mut near);
                if !near.is_empty() {
                    continue;
                }
            } else {
                next.grid
                    .nearest(&predicted, radius, 1, |_| true, &mut nearest);
                if !nearest.is_empty() {
                    continue;
                }
            }
            if let Some(found) = recovery.recover(targets, &predicted, radius) {
                // Floored as the given particles are, and never below the
                // trajectory's last point (a frame may have no others).
                let cameras = found.camera_count();
                next.particles.push(ParticlePosition::seen_by(
                    found.position,
                    found.sigma.sup(&next.median_sigma).sup(&live.last().sigma),
                    cameras,
                ));
                next.missing.push(self.rig_cameras.saturating_sub(cameras));
                next.recovered.push(found);
            }
        }
        if next.particles.len() > before {
            next.grid = Grid::new(&next.particles, &next.missing, self.cell());
        }
    }

    /// Where `live` predicts its particle in frame `number`, and the
    /// search radius around it (mm): with a velocity, `x_t + v Δ` within
    /// `max_acceleration Δ²`; else its last position within `max_velocity
    /// Δ`; each plus the noise floor.
    fn prediction(&self, live: &Live, number: i64) -> (Point3<f64>, f64) {
        let p = &self.parameters;
        let last = live.last();
        let dt = (number - last.frame) as f64;
        let floor = noise_floor(&last.sigma);
        match live.velocity() {
            Some(v) => (last.position + v * dt, p.max_acceleration * dt * dt + floor),
            None => (last.position, p.max_velocity * dt + floor),
        }
    }

    /// Links the live trajectories to `next`, judged with `ahead`; starts
    /// trajectories from what is left; hands out final points.
    fn step(&mut self, next: &mut Frame, ahead: Option<&Frame>, out: &mut Vec<TrackPoint>) {
        self.recover(next);
        let next = &*next;
        let p = &self.parameters;
        let mut links = Vec::new();
        // What each trajectory's search needs, in one pass over them in
        // memory order. The searches then run in the order of their
        // predictions' cells in `next`'s grid, so that one search reads
        // cells of both frames next to the ones the search before read (in
        // the trajectories' own order, random in space, nearly every search
        // missed the cache at 10,000+ particles). The links are the same:
        // each names its trajectory by its index.
        let searches: Vec<Search> = self
            .live
            .iter()
            .map(|live| {
                let last = live.last();
                let (predicted, radius) = self.prediction(live, next.number);
                Search {
                    predicted,
                    radius,
                    from: last.position,
                    dt: (next.number - last.frame) as f64,
                    velocity: live.velocity(),
                    floor: noise_floor(&last.sigma),
                    source: if live.length == 1 { last.missing } else { 0 },
                }
            })
            .collect();
        let visits = next.grid.cell_order(searches.iter().map(|s| s.predicted));
        let mut scratch = Scratch::default();
        let ahead = ahead.map(|a| (&a.grid, (a.number - next.number) as f64));
        for l in visits {
            let l = l as usize;
            candidate_links(
                p,
                &next.grid,
                ahead,
                &searches[l],
                l,
                |_| true,
                &mut scratch,
                &mut links,
            );
        }
        // Global resolution: best first over the whole frame.
        // (Unstable is enough: no two links share a trajectory and a
        // particle, so the order is total.)
        links.sort_unstable();
        let mut taken_live = vec![false; self.live.len()];
        let mut taken = vec![false; next.particles.len()];
        for link in links {
            if taken_live[link.live] || taken[link.particle] {
                continue;
            }
            taken_live[link.live] = true;
            taken[link.particle] = true;
            let particle = &next.particles[link.particle];
            self.live[link.live].add(Node {
                frame: next.number,
                particle: link.particle,
                position: particle.position,
                sigma: particle.sigma,
                missing: next.missing[link.particle],
                share: next.full_share,
            });
        }
        // Trajectories that missed this frame: continue within the gap
        // (only those with a velocity to predict with), or end.
        let mut live = std::mem::take(&mut self.live);
        let mut kept = Vec::with_capacity(live.len() + next.particles.len());
        for (l, trajectory) in live.drain(..).enumerate() {
            let missed = (next.number - trajectory.last().frame) as usize;
            let continues =
                taken_live[l] || (trajectory.length >= 2 && missed <= self.parameters.max_gap);
            if continues {
                kept.push(trajectory);
            } else {
                self.end(trajectory, out);
            }
        }
        for (c, particle) in next.particles.iter().enumerate() {
            if !taken[c] {
                let mut live = Live {
                    id: None,
                    rejected: false,
                    probation: false,
                    full: 0,
                    expected_full: 0.0,
                    nodes: VecDeque::new(),
                    length: 0,
                    emitted: 0,
                };
                live.add(Node {
                    frame: next.number,
                    particle: c,
                    position: particle.position,
                    sigma: particle.sigma,
                    missing: next.missing[c],
                    share: next.full_share,
                });
                kept.push(live);
            }
        }
        self.live = kept;
        let mut live = std::mem::take(&mut self.live);
        for trajectory in &mut live {
            while let Some(rest) = self.hand_out(trajectory, false, out) {
                *trajectory = rest;
            }
        }
        // A rejected trajectory ends: if it was a real particle's after all
        // (a 1% chance), its next point starts a new one, which loses only
        // the points already rejected.
        live.retain(|l| !l.rejected);
        self.live = live;
    }

    fn end(&mut self, mut live: Live, out: &mut Vec<TrackPoint>) {
        while let Some(rest) = self.hand_out(&mut live, true, out) {
            live = rest;
        }
    }

    /// Hands out the points of `live` whose fit windows are complete (all
    /// of them if it `ended`), once it is long enough; drops what no fit
    /// needs any more. Where its path breaks (it is not one particle's
    /// there) it is cut: `live` keeps what it handed out and ends, and the
    /// rest is returned, to go on in its place.
    fn hand_out(
        &mut self,
        live: &mut Live,
        ended: bool,
        out: &mut Vec<TrackPoint>,
    ) -> Option<Live> {
        let p = &self.parameters;
        let w = p.fit_half_window;
        let span = 2 * w + 1;
        if live.id.is_none() && !live.rejected {
            // Its start: leading points that are not on one smooth path
            // with the points after them leave it (a trajectory starts where
            // its particle's path does; after a cut, where the next
            // particle's path does).
            // The rest of a cut trajectory shows a longer window (more
            // redundancy against a chain of others' points that is smooth
            // by chance).
            let start = if live.probation {
                (span + 2).min(MAX_SAMPLES)
            } else {
                span
            };
            while live.nodes.len() >= start && live.nodes.len() == live.length {
                let mut window = [live.nodes[0].sample(); MAX_SAMPLES];
                for (slot, node) in window.iter_mut().zip(live.nodes.iter().take(start)) {
                    *slot = node.sample();
                }
                if is_smooth(&window[..start], 3) {
                    live.probation = false;
                    break;
                }
                live.drop_first();
            }
            if live.length < start {
                if !ended {
                    return None;
                }
                if live.probation || !short_path_is_smooth(live, self.noise_scale.median()) {
                    live.rejected = true;
                    return None;
                }
            }
            match live.decide(p.min_length, ended) {
                Some(true) => {
                    live.id = Some(self.next_id);
                    self.next_id += 1;
                }
                Some(false) => live.rejected = true,
                None => return None,
            }
        }
        let Some(id) = live.id else {
            // Rejected: it ends after this frame, and nothing is handed out.
            return None;
        };
        while live.emitted < live.length {
            let k = live.emitted;
            let node = live.nodes[live.local(k)];
            // Its fit takes a window of 2 w + 1 points from those within
            // 2 w of it on each side (centred where that is consistent,
            // `kinematics::derivatives_at`): final once those after it are
            // there, or none will come.
            if !ended && live.length < k + 2 * w + 1 {
                break;
            }
            let first = k.saturating_sub(2 * w);
            let last = (k + 2 * w + 1).min(live.length);
            // At most 4 w + 1 (w <= 5) points, on the stack.
            let mut samples = [Sample {
                frame: 0,
                position: Vector3::zeros(),
                sigma: Vector3::zeros(),
            }; 2 * MAX_SAMPLES - 1];
            for (slot, i) in samples.iter_mut().zip(first..last) {
                let n = &live.nodes[live.local(i)];
                *slot = Sample {
                    frame: n.frame,
                    position: n.position.coords,
                    sigma: n.sigma,
                };
            }
            let track = &samples[..last - first];
            // An intruder at an end (another particle's point, taken by
            // the unconfirmed first or last link) leaves the trajectory,
            // which keeps its reported length.
            let at_start = k == 0;
            if (at_start || (ended && k + 1 == live.length))
                && live.length > p.min_length
                && end_is_intruder(track, at_start, w, p.fit_order)
            {
                let local = live.local(k);
                live.nodes.remove(local);
                live.length -= 1;
                continue;
            }
            // A wrong point inside leaves the trajectory; where the path
            // is not one particle's, the trajectory is cut. (Tested only
            // where the centred window, which holds the point and the one
            // before, is not consistent: a break there would show.)
            let fit = derivatives_at(track, k - first, w, p.fit_order);
            if let Some(ratio) = fit.centred_chi2_ratio {
                self.noise_scale.add(ratio);
            }
            if !fit.centred_consistent && breaks_before(track, k - first) {
                if is_outlier(track, k - first) {
                    let local = live.local(k);
                    live.nodes.remove(local);
                    live.length -= 1;
                    continue;
                }
                return Some(live.cut(k));
            }
            let derivatives = fit.derivatives.unwrap_or(Derivatives {
                velocity: Vector3::repeat(f64::NAN),
                velocity_sigma: Vector3::repeat(f64::NAN),
                acceleration: None,
                acceleration_sigma: None,
            });
            out.push(TrackPoint {
                trajectory: id,
                frame: node.frame,
                particle: node.particle,
                position: node.position,
                derivatives,
            });
            live.emitted += 1;
        }
        // Keep what is not handed out, the 2 w points before the first of
        // it (the reach of its window), and the last two points (for the
        // prediction).
        while live.nodes.len() > 2 && live.length - live.nodes.len() + 2 * w < live.emitted {
            live.nodes.pop_front();
        }
        None
    }
}
/// Tracks a whole sequence and returns its trajectories, by number.
pub fn track(
    frames: impl IntoIterator<Item = (i64, Vec<ParticlePosition>)>,
    parameters: TrackingParameters,
) -> Result<Vec<Trajectory>, TrackError> {
    let mut tracker = Tracker::new(parameters)?;
    let mut gathered = Gathered::default();
    for (number, particles) in frames {
        gathered.extend(tracker.push(number, particles)?);
    }
    gathered.extend(tracker.finish());
    Ok(gathered.finish())
}

/// [`track`] with backward tracking ([`backward`]): the trajectories,
/// and what the pass back added.
pub fn track_both_ways(
    frames: impl IntoIterator<Item = (i64, Vec<ParticlePosition>)>,
    parameters: TrackingParameters,
) -> Result<(Vec<Trajectory>, BackwardSummary), TrackError> {
    let mut tracker = Tracker::new(parameters)?.extending_backward();
    for (number, particles) in frames {
        tracker.push(number, particles)?;
    }
    let finished = tracker.finish_all();
    Ok((
        trajectories(finished.points),
        finished.backward.unwrap_or_default(),
    ))
}

/// Trajectory points, in any order, gathered into trajectories by number,
/// each in frame order.
pub fn trajectories(points: impl IntoIterator<Item = TrackPoint>) -> Vec<Trajectory> {
    let mut gathered = Gathered::default();
    gathered.extend(points);
    gathered.finish()
}

/// Points gathered by trajectory in linear time: kept in one list as they
/// come, counted per trajectory, then each moved once into its
/// trajectory's list of exactly its size (not sorted as one list: at
/// 20,000 particles over 16 frames that list is 50 MB of 160-byte points,
/// beyond the cache, and its sort was a fifth of `track`'s instructions).
/// Pushing into a growing list per trajectory instead costs about as much
/// (its reallocations' copies were a sixth of the simulated cache misses,
/// about what the move from one list costs), but leaves up to half of
/// each list unused.
#[derive(Default)]
struct Gathered {
    points: Vec<TrackPoint>,
    /// Per point, its trajectory's slot.
    slots: Vec<u32>,
    /// Per trajectory number, its slot.
    slot_of: HashMap<u64, u32>,
    /// Per slot, its number and points.
    ids: Vec<u64>,
    counts: Vec<usize>,
}

impl Gathered {
    fn extend(&mut self, points: impl IntoIterator<Item = TrackPoint>) {
        for point in points {
            let slot = *self.slot_of.entry(point.trajectory).or_insert_with(|| {
                self.ids.push(point.trajectory);
                self.counts.push(0);
                (self.ids.len() - 1) as u32
            });
            self.counts[slot as usize] += 1;
            self.slots.push(slot);
            self.points.push(point);
        }
    }

    /// The trajectories by number, each in frame order (points of one
    /// frame in the order given). A tracker hands out each trajectory's
    /// points in frame order, so only the trajectories are sorted.
    fn finish(self) -> Vec<Trajectory> {
        let mut trajectories: Vec<Trajectory> = self
            .ids
            .iter()
            .zip(&self.counts)
            .map(|(&id, &count)| Trajectory {
                id,
                points: Vec::with_capacity(count),
            })
            .collect();
        for (point, slot) in self.points.into_iter().zip(self.slots) {
            trajectories[slot as usize].points.push(point);
        }
        trajectories.sort_unstable_by_key(|t| t.id);
        for t in &mut trajectories {
            if !t.points.windows(2).all(|w| w[0].frame <= w[1].frame) {
                t.points.sort_by_key(|p| p.frame);
            }
        }
        trajectories
    }
}

#[cfg(test)]
mod tests;
