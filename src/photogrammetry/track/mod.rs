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
pub mod kinematics;
pub mod recovery;

use std::collections::{HashMap, VecDeque};

use nalgebra::{Point3, Vector3};

pub use backward::BackwardSummary;
pub use kinematics::Derivatives;
use kinematics::{
    breaks_before, derivatives_at, end_is_intruder, is_outlier, is_smooth, is_smooth_scaled,
    NoiseScale, Sample, MAX_SAMPLES,
};
pub use recovery::{FrameTargets, ImageSpaceRecovery};

use super::correspond::{readable, Particle};
use super::volume::Volume;

/// How to track.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackingParameters {
    /// The largest displacement of a particle between two frames (mm per
    /// frame): the search radius of a trajectory's first link.
    pub max_velocity: f64,
    /// The largest change of velocity between two frames (mm per frame²):
    /// the search radius around a prediction.
    pub max_acceleration: f64,
    /// Frames a trajectory may miss and still continue (0..=2).
    pub max_gap: usize,
    /// The fewest points of a trajectory that is reported.
    pub min_length: usize,
    /// Points on each side of a point in its polynomial fit (1..=5).
    pub fit_half_window: usize,
    /// The order of the fit (1..=3; lower where the window has fewer
    /// points).
    pub fit_order: usize,
}

impl TrackingParameters {
    /// Parameters for particles moving at most `max_velocity` mm per
    /// frame: velocity changes up to half of that per frame, gaps of one
    /// frame bridged, trajectories of 3 points or more, a 5-point
    /// quadratic fit.
    pub fn new(max_velocity: f64) -> Self {
        TrackingParameters {
            max_velocity,
            max_acceleration: max_velocity / 2.0,
            max_gap: 1,
            min_length: 3,
            fit_half_window: 2,
            fit_order: 2,
        }
    }

    /// How many frames behind the newest frame given a point may still be
    /// handed out: a trajectory waits for up to
    /// `max(min_length, MAX_DECISION_LENGTH)` points (the test for ghosts)
    /// spread over gaps, then for its fit window, plus the look-ahead. A
    /// caller holding per-frame data for the points (the command line's
    /// target indices) needs this many frames.
    pub fn report_delay(&self) -> usize {
        self.min_length
            .max(MAX_DECISION_LENGTH)
            .max(2 * self.fit_half_window + 1)
            * (self.max_gap + 1)
            + 2 * self.fit_half_window
            + 4
    }

    /// Checks every field; the error names it, its value and its range.
    ///
    /// Without a volume to compare with, the limits are bounded by
    /// [`MAX_DISPLACEMENT`]; where the observation volume is known,
    /// [`TrackingParameters::check_volume`] bounds them by its size.
    pub fn validate(&self) -> Result<(), TrackError> {
        let invalid = |what: String| Err(TrackError::InvalidParameter(what));
        if !(self.max_velocity.is_finite() && self.max_velocity > 0.0) {
            return invalid(format!(
                "max_velocity must be a positive number of mm per frame, got {}",
                self.max_velocity
            ));
        }
        if self.max_velocity > MAX_DISPLACEMENT {
            return invalid(format!(
                "max_velocity {} mm per frame is above the bound of {MAX_DISPLACEMENT} mm (1 km, \
                 MAX_DISPLACEMENT): no particle tracking volume is that large, and a larger \
                 limit only makes every particle a candidate for every trajectory; give the \
                 largest displacement per frame of the flow",
                readable(self.max_velocity)
            ));
        }
        if !(self.max_acceleration.is_finite() && self.max_acceleration > 0.0) {
            return invalid(format!(
                "max_acceleration must be a positive number of mm per frame², got {}",
                self.max_acceleration
            ));
        }
        if self.max_acceleration > 2.0 * MAX_DISPLACEMENT {
            return invalid(format!(
                "max_acceleration {} mm per frame² is above the bound of {} mm (twice \
                 MAX_DISPLACEMENT, 1 km): a change of velocity between two frames is at most \
                 twice the largest displacement; give the largest change of velocity per frame \
                 of the flow",
                readable(self.max_acceleration),
                2.0 * MAX_DISPLACEMENT
            ));
        }
        if self.max_gap > MAX_GAP {
            return invalid(format!(
                "max_gap must be 0..={MAX_GAP} frames (a prediction over a longer gap is a guess), got {}",
                self.max_gap
            ));
        }
        if self.min_length == 0 {
            return invalid("min_length must be at least 1 point".into());
        }
        if self.min_length > MAX_MIN_LENGTH {
            return invalid(format!(
                "min_length {} is above the bound of {MAX_MIN_LENGTH} points (MAX_MIN_LENGTH): \
                 every new trajectory is held in memory until it has min_length points; \
                 track with a shorter one and keep the long trajectories when reading them \
                 (the service's `?min_length=`, or filter `ptv track`'s output)",
                self.min_length
            ));
        }
        if !(1..=5).contains(&self.fit_half_window) {
            return invalid(format!(
                "fit_half_window must be 1..=5 points, got {}",
                self.fit_half_window
            ));
        }
        if !(1..=3).contains(&self.fit_order) {
            return invalid(format!(
                "fit_order must be 1, 2 or 3, got {}",
                self.fit_order
            ));
        }
        Ok(())
    }

    /// Checks the limits against the observation volume the particles
    /// are found in (the matcher's, [`crate::photogrammetry::correspond::Matcher::volume`]):
    /// `max_velocity` at most the volume's diagonal and `max_acceleration`
    /// at most twice that. No particle of the volume moves farther than its
    /// diagonal between two frames, and no velocity changes by more than
    /// twice that, so a larger limit describes no motion the volume can
    /// hold: it only widens every search to the whole volume. The bound is
    /// the diagonal, not the volume's smallest side, so that a flow
    /// through a thin light sheet or along a long channel keeps whatever
    /// limit its geometry allows. A volume with an unbounded axis (as
    /// OpenPTV's depth-only bounds) bounds nothing here: [`MAX_DISPLACEMENT`]
    /// still holds.
    pub fn check_volume(&self, volume: &Volume) -> Result<(), TrackError> {
        let diagonal = (volume.max - volume.min).norm();
        if !diagonal.is_finite() {
            return Ok(());
        }
        let describe = || {
            format!(
                "x {}..{}, y {}..{}, z {}..{} mm",
                volume.min.x, volume.max.x, volume.min.y, volume.max.y, volume.min.z, volume.max.z
            )
        };
        if self.max_velocity > diagonal {
            return Err(TrackError::InvalidParameter(format!(
                "max_velocity {} mm per frame is above the bound of {} mm, the diagonal of the \
                 observation volume ({}): no particle moves farther than that between two \
                 frames, and a larger limit only makes every particle a candidate for every \
                 trajectory; give the largest displacement per frame of the flow",
                readable(self.max_velocity),
                readable(diagonal),
                describe()
            )));
        }
        if self.max_acceleration > 2.0 * diagonal {
            return Err(TrackError::InvalidParameter(format!(
                "max_acceleration {} mm per frame² is above the bound of {} mm, twice the \
                 diagonal of the observation volume ({}): a velocity within the volume changes \
                 by at most that between two frames; give the largest change of velocity per \
                 frame of the flow",
                readable(self.max_acceleration),
                readable(2.0 * diagonal),
                describe()
            )));
        }
        Ok(())
    }
}

/// The largest `max_velocity` any tracking takes (mm per frame), whatever
/// its volume: 10^6 mm, a kilometre per frame. The largest volumes
/// tracked (helium bubbles or snowflakes in the atmospheric surface
/// layer) are tens of metres across; where the volume is known
/// ([`TrackingParameters::check_volume`]) its diagonal bounds the limit
/// far more tightly. `max_acceleration` is bounded by twice this.
pub const MAX_DISPLACEMENT: f64 = 1e6;

/// The longest `min_length` (points): 100. A new trajectory is held in
/// memory, about 80 bytes a point, until it has `min_length` points (or
/// the test for ghosts decided, at [`MAX_DECISION_LENGTH`] points for
/// the default), so this bounds what each live particle holds at 8 KB
/// (80 MB at 10,000 particles a frame); longer trajectories are chosen
/// when reading the result.
pub const MAX_MIN_LENGTH: usize = 100;

/// The most candidates a trajectory's search keeps in the next frame: the
/// 32 nearest its prediction (all of them where there are fewer, as at
/// any sane limit: a limit of the particle spacing puts 4 on average in
/// the search). With limits as large as the volume every particle is in
/// every search; this keeps a frame's links at `32 N` and its work at
/// about `N` searches of a few cells each (each look-ahead is a search for
/// the single best partner), instead of `N³` (5,000 particles a frame at
/// 10^308 mm per frame: 85 s a frame before this bound).
pub const MAX_CANDIDATES: usize = 32;

/// The longest gap bridged.
pub const MAX_GAP: usize = 2;

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

/// A trajectory being tracked.
struct Live {
    /// Its number, once it has `min_length` points and passed the test
    /// for ghosts ([`Live::decide`]).
    id: Option<u64>,
    /// Failed the test for ghosts: never reported.
    rejected: bool,
    /// The rest of a trajectory cut where its path broke ([`Live::cut`]):
    /// reported only once a window of `2 w + 3` of its first points (at
    /// most [`MAX_SAMPLES`]) is one smooth path.
    probation: bool,
    /// Its points seen by all cameras.
    full: usize,
    /// The sum, over its points, of their frames' share of particles seen
    /// by all cameras: the `full` expected of a real particle.
    expected_full: f64,
    /// Its recent points: those not yet handed out, and up to a fit
    /// window of those before them.
    nodes: VecDeque<Node>,
    /// Points ever added.
    length: usize,
    /// Points handed out (the first `emitted` of the trajectory).
    emitted: usize,
}

#[derive(Clone, Copy)]
struct Node {
    frame: i64,
    particle: usize,
    position: Point3<f64>,
    sigma: Vector3<f64>,
    /// Cameras short of the rig's that missed it.
    missing: usize,
    /// Its frame's share of particles seen by all cameras (the test for
    /// ghosts' expectation).
    share: f64,
}

impl Node {
    /// The point for a fit.
    fn sample(&self) -> Sample {
        Sample {
            frame: self.frame,
            position: self.position.coords,
            sigma: self.sigma,
        }
    }
}

impl Live {
    fn last(&self) -> &Node {
        self.nodes.back().expect("a trajectory has a point")
    }

    /// Velocity (mm per frame) from the last two points, if it has two.
    fn velocity(&self) -> Option<Vector3<f64>> {
        let n = self.nodes.len();
        (n >= 2).then(|| {
            let (a, b) = (&self.nodes[n - 2], &self.nodes[n - 1]);
            (b.position - a.position) / (b.frame - a.frame) as f64
        })
    }

    /// The index in `nodes` of the trajectory's point `k`.
    fn local(&self, k: usize) -> usize {
        k - (self.length - self.nodes.len())
    }

    fn add(&mut self, node: Node) {
        self.full += usize::from(node.missing == 0);
        self.expected_full += node.share;
        self.nodes.push_back(node);
        self.length += 1;
    }

    /// Drops its first point (not handed out yet).
    fn drop_first(&mut self) {
        if let Some(node) = self.nodes.pop_front() {
            self.length -= 1;
            self.full -= usize::from(node.missing == 0);
            self.expected_full -= node.share;
        }
    }

    /// Cuts the trajectory before its point `k` (its path breaks there:
    /// `kinematics::breaks_before`), all of whose points before are
    /// handed out: it keeps those and ends; the points from `k` on are
    /// returned as a trajectory of their own, new and undecided (reported,
    /// under a number of its own, once it passes [`Live::decide`] as any
    /// new one).
    fn cut(&mut self, k: usize) -> Live {
        let local = self.local(k);
        let nodes: VecDeque<Node> = self.nodes.drain(local..).collect();
        self.length = k;
        Live {
            id: None,
            rejected: false,
            probation: true,
            full: nodes.iter().filter(|n| n.missing == 0).count(),
            expected_full: nodes.iter().map(|n| n.share).sum(),
            length: nodes.len(),
            emitted: 0,
            nodes,
        }
    }

    /// The test for ghosts, once it has `decision_length(share)` points or
    /// ended: `Some(true)` for a particle's trajectory, `Some(false)` for a
    /// ghost's, `None` while undecided.
    ///
    /// A real particle is seen by all cameras in a frame with about the
    /// probability `f` that the frame's particles are (its images are
    /// lost at random, independently from frame to frame), so its count
    /// of full points over `n` is about binomial `(n, f)`. A ghost borrows
    /// its images from other particles, and the more cameras, the less
    /// likely their rays meet by chance: it is rarely seen by all. A
    /// trajectory is a ghost's where most of its points are not full and
    /// so few are that a real particle would show as few with probability
    /// under [`GHOST_TEST_LEVEL`]. The frames' shares include the ghosts,
    /// so `f` is underestimated: the test errs towards keeping. Where
    /// every particle is seen by all cameras (a 2-camera rig, or counts
    /// unknown) nothing is rejected.
    fn decide(&self, min_length: usize, ended: bool) -> Option<bool> {
        let n = self.length;
        let share = self.expected_full / n as f64;
        if n < min_length {
            return ended.then_some(false);
        }
        if !ended && n < decision_length(share, min_length) {
            return None;
        }
        let weak_majority = 2 * self.full < n;
        Some(!(weak_majority && binomial_cdf(self.full, n, share) < GHOST_TEST_LEVEL))
    }
}

/// The test for ghosts rejects a real particle's trajectory with at most
/// this probability.
pub const GHOST_TEST_LEVEL: f64 = 0.01;

/// The most points a trajectory waits for before the test for ghosts
/// decides (where few particles are seen by all cameras, the test needs
/// more points; beyond this it decides on what it has).
pub const MAX_DECISION_LENGTH: usize = 10;

/// The points the test for ghosts waits for: enough that a trajectory of
/// none seen by all cameras is improbable for a real particle (`(1 -
/// share)^n < GHOST_TEST_LEVEL`), at least `min_length`, at most
/// [`MAX_DECISION_LENGTH`].
fn decision_length(share: f64, min_length: usize) -> usize {
    let mut n = min_length;
    while n < MAX_DECISION_LENGTH && (1.0 - share).powi(n as i32) >= GHOST_TEST_LEVEL {
        n += 1;
    }
    n
}

/// `P(X <= k)` for `X` binomial `(n, p)`.
fn binomial_cdf(k: usize, n: usize, p: f64) -> f64 {
    let p = p.clamp(0.0, 1.0);
    let mut term = (1.0 - p).powi(n as i32); // P(X = 0)
    let mut sum = term;
    for i in 0..k.min(n) {
        // P(X = i + 1) from P(X = i).
        term *= (n - i) as f64 / (i + 1) as f64 * p / (1.0 - p).max(f64::MIN_POSITIVE);
        sum += term;
    }
    sum.min(1.0)
}

/// A candidate link, ordered by its rank (without a look-ahead partner
/// after all with one, then by cost), then its trajectory and particle.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Link {
    /// [`Link::rank`].
    rank: u64,
    live: usize,
    particle: usize,
}

impl Link {
    /// The rank as one integer: a cost's bits (for a cost of zero or
    /// above, its IEEE 754 bits order as the cost does), with the top (the
    /// sign) bit set for a link without a look-ahead partner. Sorting
    /// integers is cheaper than comparing floats, and an infinite or NaN
    /// cost (which finite positions never give) ranks last instead of
    /// stopping the sort.
    fn rank(unconfirmed: bool, cost: f64) -> u64 {
        debug_assert!(cost >= 0.0, "a cost is a norm plus a penalty");
        // `+ 0.0` turns a -0.0 into 0.0.
        (cost + 0.0).to_bits() | u64::from(unconfirmed) << 63
    }
}

/// A trajectory's search in the next frame ([`Tracker::prediction`]).
#[derive(Clone, Copy)]
struct Search {
    predicted: Point3<f64>,
    radius: f64,
    /// Its last position.
    from: Point3<f64>,
    /// Frames from its last point to the next frame.
    dt: f64,
    /// Its last velocity, with two points or more.
    velocity: Option<Vector3<f64>>,
    /// The noise floor of its last point ([`noise_floor`]).
    floor: f64,
    /// Cameras missed by its point, for a trajectory of one point (else 0):
    /// the ghost penalty's share from the source.
    source: usize,
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
fn short_path_is_smooth(live: &Live, scale: Option<f64>) -> bool {
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
struct Scratch {
    near: Vec<usize>,
    candidates: Vec<(f64, usize)>,
    near_ahead: Vec<usize>,
    partner: Vec<(f64, usize)>,
}

/// The candidate links of one trajectory's `search` (trajectory `live`)
/// in the frame of grid `next`, judged with the frame after it (`ahead`:
/// its grid and the frames from `next` to it), appended to `links`: the
/// linking's steps 1 and 2 (module docs), the same whichever way in time
/// the trajectory is extended (forward, or backward from its first points:
/// [`backward`]). `accept` says which entries of `next` may be taken at
/// all (the backward pass takes only particles no trajectory holds).
#[allow(clippy::too_many_arguments)]
fn candidate_links(
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
fn floor_sigmas(particles: &mut [ParticlePosition]) -> Vector3<f64> {
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
fn cost_noise(sigma: &Vector3<f64>) -> f64 {
    20f64.sqrt() * sigma.norm()
}

/// A search radius's allowance for the positions' noise: the prediction
/// from two points and the candidate carry about `sqrt(6)` times a
/// position's sigma per axis; 3 of those over the three axes.
fn noise_floor(sigma: &Vector3<f64>) -> f64 {
    3.0 * 6f64.sqrt() * sigma.norm()
}

/// The particles of a frame filed by cell of a uniform grid over their
/// bounding box: their indices sorted by cell (x, then y, then z fastest)
/// with what a link's cost reads of them alongside (position, sigmas,
/// cameras missed), and per cell where its run starts. A search visits,
/// per (x, y) column of its box, one contiguous run of cells, and gives
/// entries: neighbours in space are neighbours in memory.
struct Grid {
    cell: f64,
    origin: Point3<f64>,
    dims: [usize; 3],
    /// Per cell, the first entry of its run in `order` (and one past the
    /// end).
    starts: Vec<u32>,
    /// Particle indices by cell: entry `e` is particle `order[e]`.
    order: Vec<u32>,
    /// Their positions, in the same order.
    points: Vec<Point3<f64>>,
    /// Their standard deviations, in the same order.
    sigma: Vec<Vector3<f64>>,
    /// The cameras that missed them ([`Frame::missing`]), in the same
    /// order.
    missing: Vec<usize>,
}

impl Grid {
    /// Cells of side `cell`, or larger where the particles spread so far
    /// that cells of that side would outnumber them eightfold (outliers):
    /// a search's answer is the same, only slower.
    fn new(particles: &[ParticlePosition], missing: &[usize], cell: f64) -> Grid {
        let mut low = Point3::origin();
        let mut high = Point3::origin();
        if let Some(first) = particles.first() {
            (low, high) = (first.position, first.position);
            for p in particles {
                low = low.inf(&p.position);
                high = high.sup(&p.position);
            }
        }
        let extent = high - low;
        let limit = (8 * particles.len()).max(64) as f64;
        // Cells no larger than about 8 particles' share of the box (over
        // its axes of non-zero extent): a search limit far above the
        // particle spacing would otherwise make one cell of the whole
        // frame, and every search ([`Grid::nearest`]) read all of it.
        let spread: Vec<f64> = extent.iter().copied().filter(|&e| e > 0.0).collect();
        let mut cell = cell;
        if !spread.is_empty() {
            let share = (spread.iter().product::<f64>() / particles.len() as f64)
                .powf(1.0 / spread.len() as f64);
            if share.is_finite() && share > 0.0 {
                cell = cell.min(2.0 * share);
            }
        }
        let dims = if extent.iter().all(|e| e.is_finite()) && cell.is_finite() {
            loop {
                let dims: [f64; 3] = std::array::from_fn(|i| (extent[i] / cell).floor() + 1.0);
                let cells = dims[0] * dims[1] * dims[2];
                if cells <= limit {
                    break dims.map(|d| d as usize);
                }
                cell *= (cells / limit).cbrt().max(1.01);
            }
        } else {
            // Positions so far apart that their differences overflow: one
            // cell (the searches' distance tests still hold).
            cell = f64::INFINITY;
            [1, 1, 1]
        };
        let mut grid = Grid {
            cell,
            origin: low,
            dims,
            starts: Vec::new(),
            order: Vec::new(),
            points: Vec::new(),
            sigma: Vec::new(),
            missing: Vec::new(),
        };
        (grid.starts, grid.order) = grid.counting_sort(particles.iter().map(|p| p.position));
        grid.points = grid
            .order
            .iter()
            .map(|&i| particles[i as usize].position)
            .collect();
        grid.sigma = grid
            .order
            .iter()
            .map(|&i| particles[i as usize].sigma)
            .collect();
        grid.missing = grid.order.iter().map(|&i| missing[i as usize]).collect();
        grid
    }

    /// Points sorted by their cells (clamped into the grid), in linear
    /// time (a counting sort): per cell where its run starts (and one past
    /// the end), and the points' indices by cell (in the order given
    /// within a cell).
    fn counting_sort(&self, points: impl Iterator<Item = Point3<f64>>) -> (Vec<u32>, Vec<u32>) {
        let keys: Vec<usize> = points.map(|p| self.key(&self.cell_of(&p))).collect();
        let mut starts = vec![0u32; self.dims.iter().product::<usize>() + 1];
        for &k in &keys {
            starts[k + 1] += 1;
        }
        for k in 1..starts.len() {
            starts[k] += starts[k - 1];
        }
        let mut next: Vec<u32> = starts[..starts.len() - 1].to_vec();
        let mut order = vec![0; keys.len()];
        for (i, &k) in keys.iter().enumerate() {
            order[next[k] as usize] = i as u32;
            next[k] += 1;
        }
        (starts, order)
    }

    /// The indices of `points` in the order of their cells.
    fn cell_order(&self, points: impl Iterator<Item = Point3<f64>>) -> Vec<u32> {
        self.counting_sort(points).1
    }

    /// The cell of a point, clamped into the grid. (The cast truncates,
    /// saturating below at 0: the floor for the offsets at or above zero,
    /// and 0, as the clamp needs, for those below. `floor` itself is a
    /// library call on x86-64 without SSE 4.1.)
    fn cell_of(&self, point: &Point3<f64>) -> [usize; 3] {
        std::array::from_fn(|i| {
            (((point[i] - self.origin[i]) / self.cell) as usize).min(self.dims[i] - 1)
        })
    }

    fn key(&self, c: &[usize; 3]) -> usize {
        (c[0] * self.dims[1] + c[1]) * self.dims[2] + c[2]
    }

    /// The entries of the particles within `radius` of `centre`, appended
    /// to `out` (in no particular order).
    fn within(&self, centre: &Point3<f64>, radius: f64, out: &mut Vec<usize>) {
        // Cells are clamped into the grid: a box beyond it reaches its
        // border cells, whose particles the distance test then rejects.
        let low = self.cell_of(&(centre - Vector3::repeat(radius)));
        let high = self.cell_of(&(centre + Vector3::repeat(radius)));
        let r2 = radius * radius;
        for i in low[0]..=high[0] {
            for j in low[1]..=high[1] {
                let from = self.starts[self.key(&[i, j, low[2]])] as usize;
                let to = self.starts[self.key(&[i, j, high[2]]) + 1] as usize;
                for e in from..to {
                    if (self.points[e] - centre).norm_squared() <= r2 {
                        out.push(e);
                    }
                }
            }
        }
    }

    /// Whether a search of `radius` around a point reads few enough cells
    /// to read them all ([`Grid::within`]): a box of at most 5 cells a
    /// side. Larger ones (a limit far above the particle spacing, or a
    /// search across a gap) go ring by ring ([`Grid::nearest`]).
    fn is_small(&self, radius: f64) -> bool {
        radius <= 2.0 * self.cell
    }

    /// The `k` entries nearest to `centre` among those within `reach` of
    /// it that `accept` takes, as (squared distance, entry) nearest first
    /// (ties by entry), replacing `out`'s contents. The cells are read in
    /// rings of growing Chebyshev distance around `centre`'s cell (clamped
    /// into the grid, and to the box of `reach`); a point in ring `r` is
    /// more than `(r - 1) cell` away, so the search stops once that
    /// exceeds the `k`-th distance found, or `reach`. Its work is the
    /// cells out to the `k`-th nearest, not the particles within `reach`.
    fn nearest(
        &self,
        centre: &Point3<f64>,
        reach: f64,
        k: usize,
        mut accept: impl FnMut(usize) -> bool,
        out: &mut Vec<(f64, usize)>,
    ) {
        out.clear();
        if k == 0 {
            return;
        }
        let c = self.cell_of(centre).map(|v| v as isize);
        let low = self
            .cell_of(&(centre - Vector3::repeat(reach)))
            .map(|v| v as isize);
        let high = self
            .cell_of(&(centre + Vector3::repeat(reach)))
            .map(|v| v as isize);
        let rings = (0..3)
            .map(|i| (c[i] - low[i]).max(high[i] - c[i]))
            .max()
            .unwrap_or(0);
        let r2 = reach * reach;
        let mut take = |e: usize, out: &mut Vec<(f64, usize)>| {
            let d2 = (self.points[e] - centre).norm_squared();
            if d2 > r2 || (out.len() == k && (d2, e) >= out[k - 1]) || !accept(e) {
                return;
            }
            if out.len() == k {
                out.pop();
            }
            let at = out.partition_point(|&x| x < (d2, e));
            out.insert(at, (d2, e));
        };
        for ring in 0..=rings {
            let bound = if ring <= 1 {
                0.0
            } else {
                (ring - 1) as f64 * self.cell
            };
            if bound > reach || (out.len() == k && bound * bound > out[k - 1].0) {
                break;
            }
            let span = |i: usize| ((c[i] - ring).max(low[i]), (c[i] + ring).min(high[i]));
            let ((x0, x1), (y0, y1), (z0, z1)) = (span(0), span(1), span(2));
            for i in x0..=x1 {
                for j in y0..=y1 {
                    let edge = (i - c[0]).abs() == ring || (j - c[1]).abs() == ring;
                    // A column on the ring's side: its whole run; inside
                    // the ring: its two end cells, where they are on it.
                    let runs: [(isize, isize); 2] = if edge {
                        [(z0, z1), (1, 0)]
                    } else {
                        [
                            if c[2] - ring >= z0 {
                                (c[2] - ring, c[2] - ring)
                            } else {
                                (1, 0)
                            },
                            if ring > 0 && c[2] + ring <= z1 {
                                (c[2] + ring, c[2] + ring)
                            } else {
                                (1, 0)
                            },
                        ]
                    };
                    for (from, to) in runs {
                        if from > to {
                            continue;
                        }
                        let (i, j) = (i as usize, j as usize);
                        let first = self.starts[self.key(&[i, j, from as usize])] as usize;
                        let last = self.starts[self.key(&[i, j, to as usize]) + 1] as usize;
                        for e in first..last {
                            take(e, out);
                        }
                    }
                }
            }
        }
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
