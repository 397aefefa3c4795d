//! Wide bands: candidates and the disparity peak (Wieneke 2008, section 3).
//!
//! With a calibration a few pixels off and a dense frame, the best-fitting
//! groups in a band wide enough for the true correspondences are mostly
//! ghosts: a true group fits at the calibration's error, while random
//! targets fit the (wrong) epipolar geometry just as well or better. The
//! matcher, which keeps one best group per target, then finds almost only
//! ghosts (simulated: 1 true of 1,700 at 8 px with 2,000 particles). So
//! wide rounds do not match; they vote:
//!
//! 1. Every target of the first camera with every target of each other
//!    camera within the band of its epipolar curve (the object ray sampled
//!    across the volume and projected), completed by the nearest target
//!    within the band in the remaining cameras: all candidate groups, ghosts
//!    included, each intersected with the current rig.
//! 2. Per sub-volume and camera, the 2D histogram of the groups' disparity
//!    vectors (observed minus reprojected): the true groups share the
//!    calibration's error, a smooth field, and pile up in one peak; ghosts
//!    spread over the band.
//! 3. Groups whose disparities lie within `radius` of their sub-volume's
//!    peak in every camera are kept, each target in at most one (the
//!    closest to the peaks first).

use nalgebra::{Point2, Point3, Vector2};
use rayon::prelude::*;

use super::bundle::Track;
use super::report::{cell_of, flat};
use crate::photogrammetry::camera::Camera;
use crate::photogrammetry::intersect::{intersect, Observation};
use crate::photogrammetry::target::Target;
use crate::photogrammetry::volume::Volume;

/// Samples of a ray across the volume for its epipolar curve.
const SAMPLES: usize = 24;

/// A candidate group and its disparities.
struct Group {
    frame: usize,
    /// Per camera its target, if any.
    targets: Vec<Option<usize>>,
    point: Point3<f64>,
    /// Per observation (in camera order of `targets`), the disparity.
    disparities: Vec<Vector2<f64>>,
}

/// One camera's targets of a frame in a square grid.
struct Grid {
    cell: f64,
    columns: usize,
    rows: usize,
    cells: Vec<Vec<usize>>,
}

impl Grid {
    fn new(targets: &[Target], width: u32, height: u32, cell: f64) -> Grid {
        let columns = ((f64::from(width) / cell).ceil() as usize).max(1);
        let rows = ((f64::from(height) / cell).ceil() as usize).max(1);
        let mut cells = vec![Vec::new(); columns * rows];
        for (i, t) in targets.iter().enumerate() {
            if let Some(k) = Self::index(cell, columns, rows, t.x, t.y) {
                cells[k].push(i);
            }
        }
        Grid {
            cell,
            columns,
            rows,
            cells,
        }
    }

    fn index(cell: f64, columns: usize, rows: usize, x: f64, y: f64) -> Option<usize> {
        let (i, j) = ((x / cell).floor(), (y / cell).floor());
        (i >= 0.0 && j >= 0.0 && (i as usize) < columns && (j as usize) < rows)
            .then(|| j as usize * columns + i as usize)
    }

    /// Targets within `band` of the segment `a`-`b`, appended to `out`.
    fn near_segment(
        &self,
        targets: &[Target],
        a: Point2<f64>,
        b: Point2<f64>,
        band: f64,
        out: &mut Vec<usize>,
    ) {
        let (x0, x1) = (a.x.min(b.x) - band, a.x.max(b.x) + band);
        let (y0, y1) = (a.y.min(b.y) - band, a.y.max(b.y) + band);
        let clampc = |v: f64, n: usize| ((v / self.cell).floor().max(0.0) as usize).min(n - 1);
        if x1 < 0.0 || y1 < 0.0 {
            return;
        }
        let (i0, i1) = (clampc(x0, self.columns), clampc(x1, self.columns));
        let (j0, j1) = (clampc(y0, self.rows), clampc(y1, self.rows));
        let d = b - a;
        let len2 = d.norm_squared();
        for j in j0..=j1 {
            for i in i0..=i1 {
                for &t in &self.cells[j * self.columns + i] {
                    let p = Point2::new(targets[t].x, targets[t].y);
                    let s = if len2 > 0.0 {
                        ((p - a).dot(&d) / len2).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    if (p - (a + d * s)).norm() <= band {
                        out.push(t);
                    }
                }
            }
        }
    }

    /// The nearest target within `band` of `p`.
    fn nearest(&self, targets: &[Target], p: Point2<f64>, band: f64) -> Option<usize> {
        let mut best: Option<(f64, usize)> = None;
        let mut found = Vec::new();
        self.near_segment(targets, p, p, band, &mut found);
        for t in found {
            let d = (Point2::new(targets[t].x, targets[t].y) - p).norm();
            if best.map_or(true, |(b, _)| d < b) {
                best = Some((d, t));
            }
        }
        best.map(|(_, t)| t)
    }
}

/// The part of a ray inside the volume, as its parameter range.
fn clip(
    origin: &Point3<f64>,
    direction: &nalgebra::Vector3<f64>,
    v: &Volume,
) -> Option<(f64, f64)> {
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        if direction[a].abs() < 1e-15 {
            if origin[a] < v.min[a] || origin[a] > v.max[a] {
                return None;
            }
            continue;
        }
        let (ta, tb) = (
            (v.min[a] - origin[a]) / direction[a],
            (v.max[a] - origin[a]) / direction[a],
        );
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t0 < t1 && t1.is_finite()).then_some((t0, t1))
}

/// All candidate groups of one frame seen by at least `min_cameras`.
fn frame_groups(
    f: usize,
    frame: &[Vec<Target>],
    cameras: &[Camera],
    volume: &Volume,
    band: f64,
    min_cameras: usize,
) -> Vec<Group> {
    let n = cameras.len();
    let grids: Vec<Grid> = frame
        .iter()
        .zip(cameras)
        .map(|(t, c)| Grid::new(t, c.sensor().width, c.sensor().height, band.max(4.0)))
        .collect();
    let first = &frame[0];
    first
        .par_iter()
        .enumerate()
        .flat_map_iter(|(a, ta)| {
            let mut out = Vec::new();
            let Ok(ray) = cameras[0].ray(Point2::new(ta.x, ta.y)) else {
                return out.into_iter();
            };
            let Some((t0, t1)) = clip(&ray.origin, &ray.direction, volume) else {
                return out.into_iter();
            };
            let samples: Vec<Point3<f64>> = (0..SAMPLES)
                .map(|k| ray.at(t0 + (t1 - t0) * k as f64 / (SAMPLES - 1) as f64))
                .collect();
            // The second camera of the pair: the first that has a curve.
            for second in 1..n {
                let curve: Vec<Point2<f64>> = samples
                    .iter()
                    .filter_map(|p| cameras[second].project(p).ok())
                    .collect();
                if curve.len() < 2 {
                    continue;
                }
                let mut near = Vec::new();
                for w in curve.windows(2) {
                    grids[second].near_segment(&frame[second], w[0], w[1], band, &mut near);
                }
                near.sort_unstable();
                near.dedup();
                for b in near {
                    let tb = &frame[second][b];
                    let pair = [
                        Observation {
                            camera: 0,
                            pixel: Point2::new(ta.x, ta.y),
                        },
                        Observation {
                            camera: second,
                            pixel: Point2::new(tb.x, tb.y),
                        },
                    ];
                    let Ok(x) = intersect(cameras, &pair) else {
                        continue;
                    };
                    let mut targets = vec![None; n];
                    targets[0] = Some(a);
                    targets[second] = Some(b);
                    for other in (1..n).filter(|&o| o != second) {
                        if let Ok(p) = cameras[other].project(&x.point) {
                            targets[other] = grids[other].nearest(&frame[other], p, band);
                        }
                    }
                    let observations: Vec<Observation> = targets
                        .iter()
                        .enumerate()
                        .filter_map(|(c, t)| {
                            t.map(|t| Observation {
                                camera: c,
                                pixel: Point2::new(frame[c][t].x, frame[c][t].y),
                            })
                        })
                        .collect();
                    if observations.len() < min_cameras {
                        continue;
                    }
                    let Ok(x) = intersect(cameras, &observations) else {
                        continue;
                    };
                    if x.residuals_px.iter().any(|r| r.norm() > band) {
                        continue;
                    }
                    out.push(Group {
                        frame: f,
                        targets,
                        point: x.point,
                        disparities: x.residuals_px,
                    });
                }
                // Pairs of the first camera with every other: a group
                // found from two pairs is kept once (each target once).
            }
            out.into_iter()
        })
        .collect()
}

/// The peak of 2D vectors within `band`: the densest bin of a histogram of
/// `bin` px (summed over 3x3 bins), refined by the mean within `radius`.
fn peak(vectors: &[Vector2<f64>], band: f64, radius: f64) -> Option<Vector2<f64>> {
    if vectors.is_empty() {
        return None;
    }
    // Small bins: the true groups' peak is narrow (the noise and the
    // field's change over a sub-volume), the ghosts' background broad.
    let bin = 0.25;
    let half = (band / bin).ceil() as i64 + 1;
    let side = (2 * half + 1) as usize;
    let mut counts = vec![0u32; side * side];
    let index = |v: &Vector2<f64>| {
        let i = (v.x / bin).round() as i64 + half;
        let j = (v.y / bin).round() as i64 + half;
        (i >= 0 && j >= 0 && (i as usize) < side && (j as usize) < side)
            .then(|| j as usize * side + i as usize)
    };
    for v in vectors {
        if let Some(k) = index(v) {
            counts[k] += 1;
        }
    }
    let mut best = (0u32, 0usize, 0usize);
    for j in 1..side - 1 {
        for i in 1..side - 1 {
            let mut s = 0;
            for dj in 0..3 {
                for di in 0..3 {
                    s += counts[(j + dj - 1) * side + i + di - 1];
                }
            }
            if s > best.0 {
                best = (s, i, j);
            }
        }
    }
    let mut centre = Vector2::new(
        (best.1 as f64 - half as f64) * bin,
        (best.2 as f64 - half as f64) * bin,
    );
    for _ in 0..3 {
        let near: Vec<&Vector2<f64>> = vectors
            .iter()
            .filter(|v| (*v - centre).norm() <= radius)
            .collect();
        if near.is_empty() {
            break;
        }
        centre = near.iter().copied().sum::<Vector2<f64>>() / near.len() as f64;
    }
    Some(centre)
}

/// What a vote found.
pub(super) struct Vote {
    /// The groups kept, as tracks.
    pub tracks: Vec<Track>,
    /// Candidate groups in all.
    pub candidates: usize,
    /// Candidate groups by the number of cameras (index = count).
    pub by_cameras: Vec<usize>,
}

/// Wide-band candidates over `frames`, kept where their disparities lie
/// within `radius` of their sub-volume's peak in every camera.
#[allow(clippy::too_many_arguments)]
pub(super) fn vote(
    frames: &[Vec<Vec<Target>>],
    cameras: &[Camera],
    volume: &Volume,
    grid: [usize; 3],
    band: f64,
    radius: f64,
    min_cameras: usize,
    max_particles: usize,
    cancel: &crate::photogrammetry::cancel::Cancel,
) -> Result<Vote, crate::photogrammetry::cancel::Cancelled> {
    let n = cameras.len();
    let mut groups = Vec::new();
    for (f, frame) in frames.iter().enumerate() {
        cancel.check()?;
        groups.extend(frame_groups(f, frame, cameras, volume, band, min_cameras));
    }
    let mut by_cameras = vec![0; n + 1];
    for g in &groups {
        by_cameras[g.disparities.len()] += 1;
    }
    let cells = grid[0] * grid[1] * grid[2];
    // Per cell and camera, the peak.
    let mut per_cell: Vec<Vec<Vec<Vector2<f64>>>> = vec![vec![Vec::new(); n]; cells];
    let cell_of_group: Vec<usize> = groups
        .iter()
        .map(|g| flat(grid, cell_of(volume, grid, &g.point)))
        .collect();
    for (g, &cell) in groups.iter().zip(&cell_of_group) {
        let cams = g.targets.iter().enumerate().filter(|(_, t)| t.is_some());
        for ((c, _), d) in cams.zip(&g.disparities) {
            per_cell[cell][c].push(*d);
        }
    }
    let peaks: Vec<Vec<Option<Vector2<f64>>>> = per_cell
        .par_iter()
        .map(|cams| cams.iter().map(|v| peak(v, band, radius)).collect())
        .collect();
    // Groups near the peaks in every camera, the closest first, each
    // target once.
    let mut scored: Vec<(f64, usize)> = groups
        .iter()
        .zip(&cell_of_group)
        .enumerate()
        .filter_map(|(i, (g, &cell))| {
            let cams = g.targets.iter().enumerate().filter(|(_, t)| t.is_some());
            let mut worst = 0.0f64;
            for ((c, _), d) in cams.zip(&g.disparities) {
                let p = peaks[cell][c]?;
                worst = worst.max((d - p).norm());
            }
            (worst <= radius).then_some((worst, i))
        })
        .collect();
    scored.sort_by(|a, b| {
        groups[b.1]
            .disparities
            .len()
            .cmp(&groups[a.1].disparities.len())
            .then(a.0.total_cmp(&b.0))
    });
    let mut used: Vec<Vec<Vec<bool>>> = frames
        .iter()
        .map(|f| f.iter().map(|t| vec![false; t.len()]).collect())
        .collect();
    let cap = max_particles.div_ceil(cells).max(1);
    let mut filled = vec![0usize; cells];
    let mut tracks = Vec::new();
    for (_, i) in scored {
        let g = &groups[i];
        let cell = cell_of_group[i];
        if filled[cell] >= cap || tracks.len() >= max_particles {
            continue;
        }
        if g.targets
            .iter()
            .enumerate()
            .any(|(c, t)| t.is_some_and(|t| used[g.frame][c][t]))
        {
            continue;
        }
        for (c, t) in g.targets.iter().enumerate() {
            if let Some(t) = t {
                used[g.frame][c][*t] = true;
            }
        }
        filled[cell] += 1;
        tracks.push(Track {
            observations: g
                .targets
                .iter()
                .enumerate()
                .filter_map(|(c, t)| {
                    t.map(|t| {
                        let target = &frames[g.frame][c][t];
                        (c, Point2::new(target.x, target.y), 1.0)
                    })
                })
                .collect(),
            point: g.point,
        });
    }
    Ok(Vote {
        tracks,
        candidates: groups.len(),
        by_cameras,
    })
}
