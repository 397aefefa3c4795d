//! Comparing two target lists of one image (ours against another tool's, or
//! against a renderer's truth), shared by the detection tests and by
//! `examples/detection_report.rs`.
//!
//! **Both ways.** A target of one list is *found* by the other when the
//! other has a target within the radius (nearest neighbour, not one to
//! one: this asks "is there a target there", as OpenPTV's own versions are
//! compared with each other).
//!
//! **Border targets aside.** OpenPTV keeps targets that touch the image
//! border; ours drops them (their centroid is cut off). A target touches the
//! border only if its bounding box reaches column or row 0 or the last one;
//! its centroid lies inside the box, so it is then no farther than its
//! extent (`nx`, `ny`) plus one pixel from that border. Targets (of either
//! list) that close to the border are left out of both shares; everything
//! else is scored.

use std::collections::HashMap;

use ptv::photogrammetry::Target;

/// How two target lists of one image agree.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Agreement {
    /// Our targets, all of them.
    pub ours: usize,
    /// Their targets, all of them.
    pub theirs: usize,
    /// Our targets away from the border.
    pub ours_scored: usize,
    /// Their targets away from the border.
    pub theirs_scored: usize,
    /// Of `ours_scored`, those with one of theirs within the radius.
    pub ours_found: usize,
    /// Of `theirs_scored`, those with one of ours within the radius.
    pub theirs_found: usize,
    /// Mean of (ours - theirs) over nearest pairs within the radius, x.
    pub mean_dx: f64,
    /// The same, y.
    pub mean_dy: f64,
}

impl Agreement {
    /// Share of their (scored) targets we find.
    pub fn theirs_share(&self) -> f64 {
        self.theirs_found as f64 / self.theirs_scored.max(1) as f64
    }

    /// Share of our (scored) targets they have.
    pub fn ours_share(&self) -> f64 {
        self.ours_found as f64 / self.ours_scored.max(1) as f64
    }

    /// Our count over theirs.
    pub fn count_ratio(&self) -> f64 {
        self.ours as f64 / self.theirs.max(1) as f64
    }
}

/// Whether a target is too close to the border to score (see the module
/// documentation).
pub fn near_border(t: &Target, width: u32, height: u32) -> bool {
    let (mx, my) = (f64::from(t.nx) + 1.0, f64::from(t.ny) + 1.0);
    t.x < mx || t.y < my || t.x > f64::from(width) - mx || t.y > f64::from(height) - my
}

/// Targets near points, by a grid of `radius`-sized cells.
struct Grid<'a> {
    targets: &'a [(f64, f64)],
    cells: HashMap<(i64, i64), Vec<usize>>,
    radius: f64,
}

impl<'a> Grid<'a> {
    fn new(targets: &'a [(f64, f64)], radius: f64) -> Grid<'a> {
        let mut cells: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (k, &(x, y)) in targets.iter().enumerate() {
            cells
                .entry(((x / radius).floor() as i64, (y / radius).floor() as i64))
                .or_default()
                .push(k);
        }
        Grid {
            targets,
            cells,
            radius,
        }
    }

    /// The nearest target within the radius of (x, y), as (index, dx, dy)
    /// with d = target - point.
    fn nearest(&self, x: f64, y: f64) -> Option<(usize, f64, f64)> {
        let (cx, cy) = (
            (x / self.radius).floor() as i64,
            (y / self.radius).floor() as i64,
        );
        let mut best: Option<(f64, usize)> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for &k in self.cells.get(&(cx + dx, cy + dy)).into_iter().flatten() {
                    let (tx, ty) = self.targets[k];
                    let d = (tx - x).hypot(ty - y);
                    if d <= self.radius && best.map_or(true, |(bd, _)| d < bd) {
                        best = Some((d, k));
                    }
                }
            }
        }
        best.map(|(_, k)| (k, self.targets[k].0 - x, self.targets[k].1 - y))
    }
}

/// Compares `ours` with `theirs` on a `width` x `height` image, their
/// coordinates first moved by `shift` (to our pixel convention), with
/// matches within `radius` px.
pub fn compare(
    ours: &[Target],
    theirs: &[Target],
    shift: (f64, f64),
    radius: f64,
    width: u32,
    height: u32,
) -> Agreement {
    let scored = |targets: &[Target], shift: (f64, f64)| -> Vec<(f64, f64)> {
        targets
            .iter()
            .filter(|t| !near_border(t, width, height))
            .map(|t| (t.x + shift.0, t.y + shift.1))
            .collect()
    };
    let our_points = scored(ours, (0.0, 0.0));
    let their_points = scored(theirs, shift);
    // Lookups go against all targets of the other list, border ones
    // included: a scored target next to a border target is still found.
    let all = |targets: &[Target], shift: (f64, f64)| -> Vec<(f64, f64)> {
        targets
            .iter()
            .map(|t| (t.x + shift.0, t.y + shift.1))
            .collect()
    };
    let (all_ours, all_theirs) = (all(ours, (0.0, 0.0)), all(theirs, shift));
    let (our_grid, their_grid) = (Grid::new(&all_ours, radius), Grid::new(&all_theirs, radius));
    let mut agreement = Agreement {
        ours: ours.len(),
        theirs: theirs.len(),
        ours_scored: our_points.len(),
        theirs_scored: their_points.len(),
        ..Agreement::default()
    };
    let (mut sx, mut sy) = (0.0, 0.0);
    for &(x, y) in &their_points {
        if let Some((_, dx, dy)) = our_grid.nearest(x, y) {
            agreement.theirs_found += 1;
            sx += dx;
            sy += dy;
        }
    }
    if agreement.theirs_found > 0 {
        agreement.mean_dx = sx / agreement.theirs_found as f64;
        agreement.mean_dy = sy / agreement.theirs_found as f64;
    }
    agreement.ours_found = our_points
        .iter()
        .filter(|&&(x, y)| their_grid.nearest(x, y).is_some())
        .count();
    agreement
}

/// How detected targets reproduce rendered particles: one-to-one matching
/// within `radius`, nearest pairs first (as `detect_accuracy.rs`).
/// Particles and targets within `margin` px of the border are not scored
/// (the detector drops border-touching targets by design).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TruthScore {
    /// Scored particles.
    pub particles: usize,
    /// Of them, those matched by a target.
    pub found: usize,
    /// Scored targets.
    pub targets: usize,
    /// Of them, those matched to no particle.
    pub false_targets: usize,
    /// Root mean square of the 2D centroid error of matched pairs (px).
    pub rms: f64,
}

impl TruthScore {
    /// Share of the particles found.
    pub fn recall(&self) -> f64 {
        self.found as f64 / self.particles.max(1) as f64
    }

    /// Share of the targets that are false.
    pub fn false_share(&self) -> f64 {
        self.false_targets as f64 / self.targets.max(1) as f64
    }
}

/// Scores `targets` against the exact particle positions `truth`.
pub fn score_truth(
    truth: &[(f64, f64)],
    targets: &[Target],
    radius: f64,
    margin: f64,
    width: u32,
    height: u32,
) -> TruthScore {
    let inside = |x: f64, y: f64| {
        x >= margin
            && y >= margin
            && x <= f64::from(width) - margin
            && y <= f64::from(height) - margin
    };
    let points: Vec<(f64, f64)> = targets.iter().map(|t| (t.x, t.y)).collect();
    let grid = Grid::new(&points, radius);
    let mut pairs = Vec::new();
    let (cell, reach) = (radius, 1i64);
    for (i, &(x, y)) in truth.iter().enumerate() {
        let (cx, cy) = ((x / cell).floor() as i64, (y / cell).floor() as i64);
        for dx in -reach..=reach {
            for dy in -reach..=reach {
                for &k in grid.cells.get(&(cx + dx, cy + dy)).into_iter().flatten() {
                    let d = (points[k].0 - x).hypot(points[k].1 - y);
                    if d <= radius {
                        pairs.push((d, i, k));
                    }
                }
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut of_truth = vec![None; truth.len()];
    let mut taken = vec![false; targets.len()];
    for (d, i, k) in pairs {
        if of_truth[i].is_none() && !taken[k] {
            of_truth[i] = Some(d);
            taken[k] = true;
        }
    }
    let mut score = TruthScore::default();
    let mut sum2 = 0.0;
    for (&(x, y), matched) in truth.iter().zip(&of_truth) {
        if inside(x, y) {
            score.particles += 1;
            if let Some(d) = matched {
                score.found += 1;
                sum2 += d * d;
            }
        }
    }
    for (&(x, y), &taken) in points.iter().zip(&taken) {
        if inside(x, y) {
            score.targets += 1;
            if !taken {
                score.false_targets += 1;
            }
        }
    }
    score.rms = (sum2 / score.found.max(1) as f64).sqrt();
    score
}
