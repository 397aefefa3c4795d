//! One camera's targets of a frame, prepared for the search: each
//! target's ray into the object medium traced once (Eq. 13-17) and kept in
//! the same cache line as its position ([`Sighting`]), and the targets
//! filed in a uniform grid ([`TargetGrid`]) for searches around a point
//! (completion and exchanges; bands use the pencil grids).

use nalgebra::{Point2, Point3, Vector3};

use super::pencil::index_range;
use crate::photogrammetry::camera::{Camera, Ray};
use crate::photogrammetry::target::Target;

/// Cells per target of the square grid that serves searches around a point
/// (completion, exchanges); bands use the pencil grids.
const CELLS_PER_TARGET: f64 = 1.0;

/// A uniform grid over target positions (pixels).
#[derive(Debug)]
pub(super) struct TargetGrid {
    min: Point2<f64>,
    cell: f64,
    inv_cell: f64,
    cols: usize,
    rows: usize,
    /// Cell `c` holds the targets `starts[c]..starts[c + 1]`: targets are
    /// stored in cell order, so that a band's targets lie close in memory.
    starts: Vec<u32>,
}

impl TargetGrid {
    /// [`CELLS_PER_TARGET`] cells per target (never smaller than the
    /// tolerance): memory linear in the targets, and cells small enough that
    /// a search around a point touches few targets. Returns the grid and the
    /// cell order of the targets (the indices of `positions`, cell by cell).
    fn new(positions: &[Point2<f64>], tolerance: f64) -> (TargetGrid, Vec<u32>) {
        let (mut min, mut max) = (
            Point2::new(f64::INFINITY, f64::INFINITY),
            Point2::new(f64::NEG_INFINITY, f64::NEG_INFINITY),
        );
        for p in positions {
            min = min.inf(p);
            max = max.sup(p);
        }
        if positions.is_empty() {
            min = Point2::origin();
            max = Point2::origin();
        }
        let n = positions.len().max(1) as f64;
        let extent = (max - min).map(|v| v.max(1e-9));
        let cell = (extent.x * extent.y / (CELLS_PER_TARGET * n))
            .sqrt()
            .max(tolerance)
            .max(1e-6);
        let cols = ((extent.x / cell) as usize + 1).max(1);
        let rows = ((extent.y / cell) as usize + 1).max(1);
        let inv_cell = 1.0 / cell;
        let cell_of = |p: &Point2<f64>| {
            let c = (((p.x - min.x) * inv_cell) as usize).min(cols - 1);
            let r = (((p.y - min.y) * inv_cell) as usize).min(rows - 1);
            r * cols + c
        };
        let mut starts = vec![0u32; cols * rows + 1];
        for p in positions {
            starts[cell_of(p) + 1] += 1;
        }
        for c in 0..cols * rows {
            starts[c + 1] += starts[c];
        }
        let mut fill = starts.clone();
        let mut entries = vec![0u32; positions.len()];
        for (i, p) in positions.iter().enumerate() {
            let c = cell_of(p);
            entries[fill[c] as usize] = i as u32;
            fill[c] += 1;
        }
        let grid = TargetGrid {
            min,
            cell,
            inv_cell,
            cols,
            rows,
            starts,
        };
        (grid, entries)
    }

    /// Targets per pixel squared over the grid's extent.
    pub(super) fn density(&self) -> f64 {
        let area = (self.cols * self.rows) as f64 * self.cell * self.cell;
        f64::from(self.starts[self.cols * self.rows]) / area
    }

    /// The cell columns and rows that overlap a box, if any.
    #[inline]
    fn cell_range(&self, lo: Point2<f64>, hi: Point2<f64>) -> Option<(usize, usize, usize, usize)> {
        let index = |v: f64, origin: f64| (v - origin) * self.inv_cell;
        let (c0, c1) = index_range(index(lo.x, self.min.x), index(hi.x, self.min.x), self.cols)?;
        let (r0, r1) = index_range(index(lo.y, self.min.y), index(hi.y, self.min.y), self.rows)?;
        Some((c0, c1, r0, r1))
    }

    /// Calls `visit` for every target in the cells that overlap the box.
    #[inline]
    pub(super) fn visit(&self, lo: Point2<f64>, hi: Point2<f64>, mut visit: impl FnMut(usize)) {
        let Some((c0, c1, r0, r1)) = self.cell_range(lo, hi) else {
            return;
        };
        for r in r0..=r1 {
            let row = r * self.cols;
            (self.starts[row + c0] as usize..self.starts[row + c1 + 1] as usize)
                .for_each(&mut visit);
        }
    }
}

/// A target's position and its ray side by side, a cache line each: the
/// search reads the position of a target near a band or a predicted image
/// and then, if it is close, its ray, and with several megabytes of rays
/// per frame a second line would be a second trip to memory.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Sighting {
    position: Point2<f64>,
    /// The ray's origin; NaN where the pixel has no ray.
    origin: Point3<f64>,
    direction: Vector3<f64>,
}

impl Sighting {
    fn new(position: Point2<f64>, ray: Option<Ray>) -> Sighting {
        let ray = ray.unwrap_or(Ray {
            origin: Point3::new(f64::NAN, f64::NAN, f64::NAN),
            direction: Vector3::zeros(),
        });
        Sighting {
            position,
            origin: ray.origin,
            direction: ray.direction,
        }
    }

    /// The target's ray in the object medium, if it has one.
    #[inline]
    fn ray(&self) -> Option<Ray> {
        (!self.origin.x.is_nan()).then_some(Ray {
            origin: self.origin,
            direction: self.direction,
        })
    }
}

/// One camera's targets prepared for the search, in the grid's cell order.
pub(super) struct CameraFrame {
    /// The targets, in cell order.
    pub(super) targets: Vec<Target>,
    /// Per target, its index in the caller's list.
    pub(super) original: Vec<u32>,
    sightings: Vec<Sighting>,
    pub(super) grid: TargetGrid,
}

impl CameraFrame {
    pub(super) fn new(camera: &Camera, targets: &[Target], tolerance: f64) -> CameraFrame {
        let positions: Vec<Point2<f64>> = targets.iter().map(|t| Point2::new(t.x, t.y)).collect();
        let (grid, original) = TargetGrid::new(&positions, tolerance);
        CameraFrame {
            targets: original.iter().map(|&o| targets[o as usize]).collect(),
            sightings: original
                .iter()
                .map(|&o| {
                    let position = positions[o as usize];
                    Sighting::new(position, camera.ray(position).ok())
                })
                .collect(),
            original,
            grid,
        }
    }

    #[inline]
    pub(super) fn position(&self, target: usize) -> Point2<f64> {
        self.sightings[target].position
    }

    #[inline]
    pub(super) fn ray(&self, target: usize) -> Option<Ray> {
        self.sightings[target].ray()
    }
}
