//! A trajectory being tracked ([`Live`]): its points not yet handed out and
//! the window behind them, the test for ghosts' trajectories and the
//! tests of its path (module docs of [`super`]).

use std::collections::VecDeque;

use nalgebra::{Point3, Vector3};

use super::kinematics::Sample;

/// A trajectory being tracked.
pub(super) struct Live {
    /// Its number, once it has `min_length` points and passed the test
    /// for ghosts ([`Live::decide`]).
    pub(super) id: Option<u64>,
    /// Failed the test for ghosts: never reported.
    pub(super) rejected: bool,
    /// The rest of a trajectory cut where its path broke ([`Live::cut`]):
    /// reported only once a window of `2 w + 3` of its first points (at
    /// most [`MAX_SAMPLES`]) is one smooth path.
    pub(super) probation: bool,
    /// Its points seen by all cameras.
    pub(super) full: usize,
    /// The sum, over its points, of their frames' share of particles seen
    /// by all cameras: the `full` expected of a real particle.
    pub(super) expected_full: f64,
    /// Its recent points: those not yet handed out, and up to a fit
    /// window of those before them.
    pub(super) nodes: VecDeque<Node>,
    /// Points ever added.
    pub(super) length: usize,
    /// Points handed out (the first `emitted` of the trajectory).
    pub(super) emitted: usize,
}

#[derive(Clone, Copy)]
pub(super) struct Node {
    pub(super) frame: i64,
    pub(super) particle: usize,
    pub(super) position: Point3<f64>,
    pub(super) sigma: Vector3<f64>,
    /// Cameras short of the rig's that missed it.
    pub(super) missing: usize,
    /// Its frame's share of particles seen by all cameras (the test for
    /// ghosts' expectation).
    pub(super) share: f64,
}

impl Node {
    /// The point for a fit.
    pub(super) fn sample(&self) -> Sample {
        Sample {
            frame: self.frame,
            position: self.position.coords,
            sigma: self.sigma,
        }
    }
}

impl Live {
    pub(super) fn last(&self) -> &Node {
        self.nodes.back().expect("a trajectory has a point")
    }

    /// Velocity (mm per frame) from the last two points, if it has two.
    pub(super) fn velocity(&self) -> Option<Vector3<f64>> {
        let n = self.nodes.len();
        (n >= 2).then(|| {
            let (a, b) = (&self.nodes[n - 2], &self.nodes[n - 1]);
            (b.position - a.position) / (b.frame - a.frame) as f64
        })
    }

    /// The index in `nodes` of the trajectory's point `k`.
    pub(super) fn local(&self, k: usize) -> usize {
        k - (self.length - self.nodes.len())
    }

    pub(super) fn add(&mut self, node: Node) {
        self.full += usize::from(node.missing == 0);
        self.expected_full += node.share;
        self.nodes.push_back(node);
        self.length += 1;
    }

    /// Drops its first point (not handed out yet).
    pub(super) fn drop_first(&mut self) {
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
    pub(super) fn cut(&mut self, k: usize) -> Live {
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
    pub(super) fn decide(&self, min_length: usize, ended: bool) -> Option<bool> {
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
pub(super) fn decision_length(share: f64, min_length: usize) -> usize {
    let mut n = min_length;
    while n < MAX_DECISION_LENGTH && (1.0 - share).powi(n as i32) >= GHOST_TEST_LEVEL {
        n += 1;
    }
    n
}

/// `P(X <= k)` for `X` binomial `(n, p)`.
pub(super) fn binomial_cdf(k: usize, n: usize, p: f64) -> f64 {
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
