//! Epipolar pencils: an index of one camera's targets that lies along the
//! epipolar curves of another camera.
//!
//! Without walls, the epipolar lines in camera j of all points of camera i
//! pass through one point, the epipole (the image of camera i's projective
//! centre; design paper, section 6.2): a pencil of lines. Through
//! refracting walls the curves bend and no longer meet exactly, but their
//! chords still nearly do. [`Pencil::fit`] finds that point by least
//! squares over sampled chords; a [`PencilGrid`] then files camera j's
//! targets by their angle around it and their distance from it. Its cells
//! are thin sectors running along the curves, so an epipolar band a
//! tolerance wide touches a few cells and few targets outside the band,
//! where a square grid with as many cells touches several times as many.
//! Where the chords run parallel (the epipole at infinity) the angle
//! becomes the distance across them and the sectors become strips.
//!
//! The index only chooses which targets to test: a band's exact test is
//! the distance to its curve. The cells a piece of the curve visits are
//! bounded conservatively (see [`PencilGrid::visit_piece`]), so no target
//! within the tolerance is ever missed, however poorly the chords meet.

use std::f64::consts::PI;

use nalgebra::{Matrix2, Point2, Vector2};

/// Cells per target: memory stays linear in the targets.
const CELLS_PER_TARGET: f64 = 1.0;

/// A sector's width across the curves, in tolerances: the band's own width,
/// so that a band lies in one to three sectors, while the sectors run as
/// long as the density allows. Chosen by the matching benchmark's
/// instruction counts (1.5, 2, 3 and 5 were tried; 2 to 3 within 1%).
const ACROSS_TOLERANCES: f64 = 2.0;

/// The epipole of camera i in camera j (or the common direction of the
/// epipolar chords) and a reference direction for angles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Pencil {
    /// The point the chords meet, or `None` where they run parallel.
    centre: Option<Point2<f64>>,
    /// Unit vector: angle zero (from the centre towards the chords), or
    /// the chords' direction.
    direction: Vector2<f64>,
}

/// `a x b`, the z component.
#[inline]
fn cross(a: &Vector2<f64>, b: &Vector2<f64>) -> f64 {
    a.x * b.y - a.y * b.x
}

/// An angle difference wrapped into (-pi, pi].
#[inline]
fn wrap(angle: f64) -> f64 {
    if angle > PI {
        angle - 2.0 * PI
    } else if angle <= -PI {
        angle + 2.0 * PI
    } else {
        angle
    }
}

impl Pencil {
    /// The point nearest (least squares, perpendicular distances) to the
    /// lines through the chords; `None` with fewer than two chords of
    /// positive length.
    pub(super) fn fit(chords: &[(Point2<f64>, Point2<f64>)]) -> Option<Pencil> {
        let mut normal_matrix = Matrix2::zeros();
        let mut right = Vector2::zeros();
        let mut scatter = Matrix2::zeros();
        let mut centroid = Vector2::zeros();
        let mut count = 0.0;
        for (p, q) in chords {
            let along = q - p;
            let length = along.norm();
            if length <= 1e-9 || length.is_nan() {
                continue;
            }
            let t = along / length;
            let n = Vector2::new(-t.y, t.x);
            normal_matrix += n * n.transpose();
            right += n * n.dot(&p.coords);
            scatter += t * t.transpose();
            centroid += nalgebra::center(p, q).coords;
            count += 1.0;
        }
        if count < 2.0 {
            return None;
        }
        centroid /= count;
        let eigen = normal_matrix.symmetric_eigen();
        let (small, large) = (eigen.eigenvalues.min(), eigen.eigenvalues.max());
        // Parallel chords, or a meeting point so far off that the sectors
        // are strips anyway (1e7 px: angles keep 1e-9 of precision).
        let centre = (small > 1e-10 * large)
            .then(|| normal_matrix.try_inverse().map(|inverse| inverse * right))
            .flatten()
            .map(Point2::from)
            .filter(|e| (e.coords - centroid).norm() < 1e7);
        let direction = match centre {
            Some(e) => {
                let towards = centroid - e.coords;
                let norm = towards.norm();
                if norm > 1e-9 {
                    towards / norm
                } else {
                    Vector2::x()
                }
            }
            None => {
                let eigen = scatter.symmetric_eigen();
                let index = eigen.eigenvalues.imax();
                eigen.eigenvectors.column(index).into_owned()
            }
        };
        Some(Pencil { centre, direction })
    }

    /// Strips along the x axis: the index for a camera pair whose chords
    /// could not be sampled (every band is still searched exactly, only
    /// less quickly).
    pub(super) fn strips() -> Pencil {
        Pencil {
            centre: None,
            direction: Vector2::x(),
        }
    }

    /// (across, along): the angle around the centre from the reference
    /// direction and the distance from it, or, for parallel chords, the
    /// distances across and along them.
    #[inline]
    pub(super) fn coordinates(&self, p: &Point2<f64>) -> (f64, f64) {
        match self.centre {
            Some(e) => {
                let v = p - e;
                (
                    cross(&self.direction, &v).atan2(self.direction.dot(&v)),
                    v.norm(),
                )
            }
            None => (
                cross(&self.direction, &p.coords),
                self.direction.dot(&p.coords),
            ),
        }
    }
}

/// One camera's targets filed by pencil coordinates: sectors (columns
/// across, rows along), targets stored in cell order.
#[derive(Debug)]
pub(super) struct PencilGrid {
    pencil: Pencil,
    across_min: f64,
    across_scale: f64,
    along_min: f64,
    along_scale: f64,
    cols: usize,
    rows: usize,
    /// Whether the columns cover the full circle (angles), so that ranges
    /// wrap around.
    circular: bool,
    /// Cell `c` holds `entries[starts[c]..starts[c + 1]]`.
    starts: Vec<u32>,
    /// Target indices (into the positions the grid was built from).
    entries: Vec<u32>,
    /// The largest distance between two points of one cell (px).
    cell_diameter: f64,
    /// Per cell, the number of the last band that visited it.
    stamps: Vec<u32>,
    stamp: u32,
}

impl PencilGrid {
    /// Files `positions` (pixels, each with its index), for bands of
    /// half-width `tolerance`.
    pub(super) fn new(
        pencil: Pencil,
        positions: impl Iterator<Item = (usize, Point2<f64>)>,
        tolerance: f64,
    ) -> PencilGrid {
        let (mut across_min, mut across_max) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut along_min, mut along_max) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut lo, mut hi) = (
            Point2::new(f64::INFINITY, f64::INFINITY),
            Point2::new(f64::NEG_INFINITY, f64::NEG_INFINITY),
        );
        let mut along_sum = 0.0;
        let (indices, coordinates): (Vec<u32>, Vec<(f64, f64)>) = positions
            .map(|(index, p)| {
                let (a, r) = pencil.coordinates(&p);
                across_min = across_min.min(a);
                across_max = across_max.max(a);
                along_min = along_min.min(r);
                along_max = along_max.max(r);
                along_sum += r;
                lo = lo.inf(&p);
                hi = hi.sup(&p);
                (index as u32, (a, r))
            })
            .unzip();
        let n = indices.len();
        if n == 0 {
            (across_min, across_max, along_min, along_max) = (0.0, 0.0, 0.0, 0.0);
            (lo, hi) = (Point2::origin(), Point2::origin());
        }
        let area = ((hi.x - lo.x).max(1.0)) * ((hi.y - lo.y).max(1.0));
        let cell_area = area / (CELLS_PER_TARGET * n.max(1) as f64);
        // Sector width across (px) and length along: as thin as the band
        // allows, as long as the cell area then gives, never longer than
        // wide would be pointless.
        let width = (ACROSS_TOLERANCES * tolerance)
            .min(cell_area.sqrt())
            .max(1e-6);
        let length = (cell_area / width).max(width);
        // Across: radians for a pencil (the width at the mean distance),
        // pixels for parallel chords.
        let (across_bin, circular) = match pencil.centre {
            Some(_) => {
                let mean = (along_sum / n.max(1) as f64).max(width);
                (width / mean, true)
            }
            None => (width, false),
        };
        let span = |min: f64, max: f64, bin: f64| ((max - min) / bin).floor() as usize + 1;
        let mut cols = span(across_min, across_max, across_bin);
        let mut rows = span(along_min, along_max, length);
        let (mut across_bin, mut length) = (across_bin, length);
        // Clustered targets can leave most of the box empty: keep the cell
        // count linear in the targets by coarsening both ways.
        let limit = 4 * n + 64;
        while cols * rows > limit {
            across_bin *= 2.0;
            length *= 2.0;
            cols = span(across_min, across_max, across_bin);
            rows = span(along_min, along_max, length);
        }
        let circular = circular && across_max - across_min > PI;
        let cell_of = |&(a, r): &(f64, f64)| {
            let c = (((a - across_min) / across_bin) as usize).min(cols - 1);
            let row = (((r - along_min) / length) as usize).min(rows - 1);
            row * cols + c
        };
        let mut starts = vec![0u32; cols * rows + 1];
        for c in &coordinates {
            starts[cell_of(c) + 1] += 1;
        }
        for c in 0..cols * rows {
            starts[c + 1] += starts[c];
        }
        let mut fill = starts.clone();
        let mut entries = vec![0u32; n];
        for (&index, c) in indices.iter().zip(&coordinates) {
            let cell = cell_of(c);
            entries[fill[cell] as usize] = index;
            fill[cell] += 1;
        }
        let widest = match pencil.centre {
            Some(_) => across_bin * along_max.abs().max(along_min.abs()),
            None => across_bin,
        };
        PencilGrid {
            pencil,
            across_min,
            across_scale: 1.0 / across_bin,
            along_min,
            along_scale: 1.0 / length,
            cols,
            rows,
            circular,
            starts,
            entries,
            cell_diameter: widest.hypot(length),
            stamps: vec![0; cols * rows],
            stamp: 0,
        }
    }

    /// The largest distance between two points of one cell (px).
    pub(super) fn cell_diameter(&self) -> f64 {
        self.cell_diameter
    }

    /// The pencil coordinates of a point.
    #[inline]
    pub(super) fn coordinates(&self, p: &Point2<f64>) -> (f64, f64) {
        self.pencil.coordinates(p)
    }

    /// Starts a new band: cells are visited once per band.
    pub(super) fn begin_band(&mut self) {
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.stamps.fill(0);
            self.stamp = 1;
        }
    }

    /// The target indices filed in cell `cell`.
    #[inline]
    pub(super) fn cell(&self, cell: usize) -> &[u32] {
        &self.entries[self.starts[cell] as usize..self.starts[cell + 1] as usize]
    }

    /// Calls `visit` for each cell, not yet visited in this band, that may
    /// hold a point within `tolerance` of the segment `p0`-`p1`, whose
    /// pencil coordinates are `c0` and `c1`.
    ///
    /// Along: distances from the centre change by at most the tolerance
    /// (triangle inequality). Across, for a pencil: the angle over a
    /// straight segment changes monotonically between its ends, and a
    /// point within `tolerance` of a segment point at distance `d` from the
    /// centre lies within `asin(tolerance / d)` of its angle, `d` being at
    /// least the segment's distance from the centre; a segment closer to
    /// the centre than the tolerance takes every angle.
    #[inline]
    pub(super) fn visit_piece(
        &mut self,
        (p0, p1): (&Point2<f64>, &Point2<f64>),
        ((a0, r0), (a1, r1)): ((f64, f64), (f64, f64)),
        tolerance: f64,
        mut visit: impl FnMut(&Self, usize),
    ) {
        let rows = self.rows_of(r0.min(r1) - tolerance, r0.max(r1) + tolerance);
        let Some((row0, row1)) = rows else {
            return;
        };
        let mut ranges = [(0.0, 0.0); 2];
        let count = match self.pencil.centre {
            None => {
                ranges[0] = (a0.min(a1) - tolerance, a0.max(a1) + tolerance);
                1
            }
            Some(e) => {
                let distance = segment_distance(&e, p0, p1);
                if distance <= tolerance {
                    ranges[0] = (-PI, PI);
                    1
                } else {
                    // asin(x) <= x / sqrt(1 - x^2) = tan(asin(x)): a
                    // margin as safe and cheaper to compute.
                    let x = tolerance / distance;
                    let margin = x / (1.0 - x * x).sqrt();
                    let turn = wrap(a1 - a0);
                    let (lo, hi) = (a0 + turn.min(0.0) - margin, a0 + turn.max(0.0) + margin);
                    if lo < -PI {
                        ranges[0] = (lo + 2.0 * PI, PI);
                        ranges[1] = (-PI, hi);
                        2
                    } else if hi > PI {
                        ranges[0] = (lo, PI);
                        ranges[1] = (-PI, hi - 2.0 * PI);
                        2
                    } else {
                        ranges[0] = (lo, hi);
                        1
                    }
                }
            }
        };
        let stamp = self.stamp;
        for &(lo, hi) in &ranges[..count] {
            let Some((col0, col1)) = self.cols_of(lo, hi) else {
                continue;
            };
            for row in row0..=row1 {
                for col in col0..=col1 {
                    let cell = row * self.cols + col;
                    if self.stamps[cell] != stamp {
                        self.stamps[cell] = stamp;
                        visit(self, cell);
                    }
                }
            }
        }
    }

    /// The rows overlapping [lo, hi] along, if any.
    #[inline]
    fn rows_of(&self, lo: f64, hi: f64) -> Option<(usize, usize)> {
        index_range(
            (lo - self.along_min) * self.along_scale,
            (hi - self.along_min) * self.along_scale,
            self.rows,
        )
    }

    /// The columns overlapping [lo, hi] across, if any.
    #[inline]
    fn cols_of(&self, lo: f64, hi: f64) -> Option<(usize, usize)> {
        if self.circular && hi - lo >= 2.0 * PI {
            return Some((0, self.cols - 1));
        }
        index_range(
            (lo - self.across_min) * self.across_scale,
            (hi - self.across_min) * self.across_scale,
            self.cols,
        )
    }
}

/// The bins `[floor(lo), floor(hi)]` clamped to `0..count`, if they
/// overlap it (`None` for NaN).
#[inline]
pub(super) fn index_range(lo: f64, hi: f64, count: usize) -> Option<(usize, usize)> {
    let last = count as f64;
    if !(hi >= 0.0 && lo < last) {
        return None;
    }
    let first = if lo > 0.0 { lo as usize } else { 0 };
    let end = if hi < last { hi as usize } else { count - 1 };
    Some((first, end.min(count - 1)))
}

/// The distance from `e` to the segment `p0`-`p1`.
#[inline]
fn segment_distance(e: &Point2<f64>, p0: &Point2<f64>, p1: &Point2<f64>) -> f64 {
    let along = p1 - p0;
    let length_sq = along.norm_squared();
    let rel = e - p0;
    let t = if length_sq > 0.0 {
        (rel.dot(&along) / length_sq).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (rel - along * t).norm()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chords_through(centre: Point2<f64>) -> Vec<(Point2<f64>, Point2<f64>)> {
        (0..10)
            .map(|k| {
                let angle = 0.1 * k as f64;
                let d = Vector2::new(angle.cos(), angle.sin());
                (centre + d * 500.0, centre + d * 1500.0)
            })
            .collect()
    }

    #[test]
    fn the_centre_of_a_pencil_of_lines_is_found() {
        let centre = Point2::new(-300.0, 200.0);
        let pencil = Pencil::fit(&chords_through(centre)).unwrap();
        assert!((pencil.centre.unwrap() - centre).norm() < 1e-6);
    }

    #[test]
    fn parallel_chords_give_strips() {
        let chords: Vec<_> = (0..10)
            .map(|k| {
                let start = Point2::new(10.0 * k as f64, 0.0);
                (start, start + Vector2::new(1.0, 2.0))
            })
            .collect();
        let pencil = Pencil::fit(&chords).unwrap();
        assert!(pencil.centre.is_none());
        assert!((pencil.direction.y / pencil.direction.x - 2.0).abs() < 1e-9);
    }

    /// Every target within the tolerance of a segment is in a visited cell,
    /// for pencils centred outside, inside and near the targets, and for
    /// segments in every direction (brute force over random targets).
    #[test]
    fn no_target_near_a_segment_is_missed() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let positions: Vec<Point2<f64>> = (0..4000)
            .map(|_| Point2::new(rng.random_range(0.0..1000.0), rng.random_range(0.0..800.0)))
            .collect();
        let tolerance = 2.0;
        for centre in [
            Point2::new(-2000.0, 400.0),
            Point2::new(500.0, 400.0),
            Point2::new(500.0, 1000.0),
        ] {
            let pencil = Pencil::fit(&chords_through(centre)).unwrap();
            let mut grid =
                PencilGrid::new(pencil, positions.iter().copied().enumerate(), tolerance);
            for _ in 0..300 {
                let p0 = Point2::new(rng.random_range(0.0..1000.0), rng.random_range(0.0..800.0));
                let p1 =
                    p0 + Vector2::new(rng.random_range(-60.0..60.0), rng.random_range(-60.0..60.0));
                let mut seen = vec![false; positions.len()];
                grid.begin_band();
                let (c0, c1) = (grid.coordinates(&p0), grid.coordinates(&p1));
                grid.visit_piece((&p0, &p1), (c0, c1), tolerance, |grid, cell| {
                    for &t in grid.cell(cell) {
                        seen[t as usize] = true;
                    }
                });
                for (t, p) in positions.iter().enumerate() {
                    if segment_distance(p, &p0, &p1) <= tolerance {
                        assert!(
                            seen[t],
                            "target {t} at {p} missed, segment {p0}-{p1}, centre {centre}"
                        );
                    }
                }
            }
        }
    }
}
