//! A frame's particles filed by cell of a uniform grid ([`Grid`]): the
//! search of module docs of [`super`], section **Search**.

use nalgebra::{Point3, Vector3};

use super::ParticlePosition;

/// The particles of a frame filed by cell of a uniform grid over their
/// bounding box: their indices sorted by cell (x, then y, then z fastest)
/// with what a link's cost reads of them alongside (position, sigmas,
/// cameras missed), and per cell where its run starts. A search visits,
/// per (x, y) column of its box, one contiguous run of cells, and gives
/// entries: neighbours in space are neighbours in memory.
pub(super) struct Grid {
    pub(super) cell: f64,
    pub(super) origin: Point3<f64>,
    pub(super) dims: [usize; 3],
    /// Per cell, the first entry of its run in `order` (and one past the
    /// end).
    pub(super) starts: Vec<u32>,
    /// Particle indices by cell: entry `e` is particle `order[e]`.
    pub(super) order: Vec<u32>,
    /// Their positions, in the same order.
    pub(super) points: Vec<Point3<f64>>,
    /// Their standard deviations, in the same order.
    pub(super) sigma: Vec<Vector3<f64>>,
    /// The cameras that missed them ([`Frame::missing`]), in the same
    /// order.
    pub(super) missing: Vec<usize>,
}

impl Grid {
    /// Cells of side `cell`, or larger where the particles spread so far
    /// that cells of that side would outnumber them eightfold (outliers):
    /// a search's answer is the same, only slower.
    pub(super) fn new(particles: &[ParticlePosition], missing: &[usize], cell: f64) -> Grid {
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
    pub(super) fn counting_sort(
        &self,
        points: impl Iterator<Item = Point3<f64>>,
    ) -> (Vec<u32>, Vec<u32>) {
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
    pub(super) fn cell_order(&self, points: impl Iterator<Item = Point3<f64>>) -> Vec<u32> {
        self.counting_sort(points).1
    }

    /// The cell of a point, clamped into the grid. (The cast truncates,
    /// saturating below at 0: the floor for the offsets at or above zero,
    /// and 0, as the clamp needs, for those below. `floor` itself is a
    /// library call on x86-64 without SSE 4.1.)
    pub(super) fn cell_of(&self, point: &Point3<f64>) -> [usize; 3] {
        std::array::from_fn(|i| {
            (((point[i] - self.origin[i]) / self.cell) as usize).min(self.dims[i] - 1)
        })
    }

    pub(super) fn key(&self, c: &[usize; 3]) -> usize {
        (c[0] * self.dims[1] + c[1]) * self.dims[2] + c[2]
    }

    /// The entries of the particles within `radius` of `centre`, appended
    /// to `out` (in no particular order).
    pub(super) fn within(&self, centre: &Point3<f64>, radius: f64, out: &mut Vec<usize>) {
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
    pub(super) fn is_small(&self, radius: f64) -> bool {
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
    pub(super) fn nearest(
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
