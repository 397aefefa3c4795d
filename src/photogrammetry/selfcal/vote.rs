//! Wide bands: pairwise epipolar disparity peaks, then groups consistent
//! with every pair's peak (after Wieneke 2008, section 3).
//!
//! With a calibration a few pixels off and a dense frame, the best-fitting
//! groups in a band wide enough for the true correspondences are mostly
//! ghosts: a true group fits at the calibration's error, while random
//! targets fit the (wrong) epipolar geometry just as well or better. The
//! matcher, which keeps one best group per target, then finds almost only
//! ghosts (simulated: 1 true of 1,700 at 8 px with 2,000 particles). A
//! first attempt intersected every camera-0 candidate pair, completed it
//! by the nearest target in the other cameras, and voted on 2D disparity
//! peaks: the completion mixed ghosts into every group's disparities, and
//! it kept ~54 groups or converged to a self-consistent wrong rig. So wide
//! rounds vote pair by pair, each pair on its own:
//!
//! 1. **Signed epipolar distances per camera pair.** For each pair
//!    (i, j), i < j, and each target of camera i (all frames given), the
//!    object ray is sampled across the volume and projected into camera j
//!    (the epipolar curve, refraction included); every target of j within
//!    the band of that curve gives its *signed* distance to it. They are
//!    binned by region: a cell of camera i's image (up to 3 x 3) and the
//!    depth along the ray (up to 3 slices, the position along the curve),
//!    fewer cells where there are few targets. A calibration error is a
//!    smooth field, so in each cell the true pairs pile up at one offset;
//!    ghosts spread evenly over the band.
//! 2. **The peak per pair and cell**: the densest 1 px window of a
//!    0.25 px histogram, refined by the mean within the acceptance radius.
//!    Its contrast (window count over the ghost floor, the median bin's
//!    count times the window's bins) must reach [`MIN_CONTRAST`], or the
//!    cell gives no pair candidates. Measured on the simulated 4-camera
//!    rig (10 frames x 2,000 particles, 0.1 px noise, 27 cells a pair;
//!    [`tests::peak_contrast_on_the_simulated_rig`]): the contrast is far
//!    lower than one might hope, median 1.1-1.9 per pair (0.7 mm / 1 mrad
//!    at 8 px and 2 mm / 3 mrad at 20 px alike): each target of i has
//!    about one true partner but 10-40 ghosts in the band, about as many
//!    per 1 px as the true ones. Only the cells above 2 vote, and that is
//!    enough: the group test below does the rest.
//! 3. **Groups consistent with every pair's peak.** A pair is a candidate
//!    when its signed distance lies within the radius of its cell's peak.
//!    Groups are the maximal sets of targets, one per camera, at least
//!    `min_cameras` of them, whose every pair is a candidate (a small
//!    clique search from each target of the lowest camera of the group;
//!    groups without camera 0 too). A ghost passing 3..6 pairwise tests,
//!    each about `2 radius / 2 band` likely by chance, is rare. Only
//!    unambiguous groups are kept: each of their targets in no other
//!    maximal group. Measured: 2,373 maximal groups, 863 kept, 862 of
//!    them true (0.7 mm / 1 mrad, 8 px); 2,214, 777 and 773 (2 mm /
//!    3 mrad, 20 px). All are 3-camera groups: a 4-camera group needs all
//!    6 pairs in voting cells.
//!
//! The groups go to the robust bundle adjustment (`bundle.rs`, `mod.rs`);
//! its residuals set the next band, and once that is at most 1 px the
//! rounds match as usual.

use nalgebra::{Point2, Point3};
use rayon::prelude::*;

use super::bundle::Track;
use super::report::{cell_of, flat};
use crate::photogrammetry::camera::Camera;
use crate::photogrammetry::cancel::{Cancel, Cancelled};
use crate::photogrammetry::intersect::{intersect, Observation};
use crate::photogrammetry::target::Target;
use crate::photogrammetry::volume::Volume;

/// Samples of a ray across the volume for its epipolar curve (the curve
/// bends little: refraction at a plane wall, a few hundred pixels long).
const SAMPLES: usize = 16;

/// Histogram bin of the signed distances (px).
const BIN: f64 = 0.25;

/// The peak window (px): about the true pairs' spread (0.14 px of noise
/// across the curve, plus the field's change over a cell).
const WINDOW: f64 = 1.0;

/// A peak below this contrast over the ghost floor is not trusted.
pub(super) const MIN_CONTRAST: f64 = 2.0;

/// Targets wanted per cell of a pair's histogram.
const PER_CELL: usize = 150;

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

/// The signed distance of `p` to the polyline `curve` (positive to the
/// left of its direction) and the position along it (0..1), if `p` lies
/// within `band` of it, beside one of its segments.
fn signed_distance(curve: &[Point2<f64>], p: Point2<f64>, band: f64) -> Option<(f64, f64)> {
    let mut best: Option<(f64, f64)> = None;
    let segments = (curve.len() - 1) as f64;
    for (k, w) in curve.windows(2).enumerate() {
        let d = w[1] - w[0];
        let len2 = d.norm_squared();
        if len2 <= 0.0 {
            continue;
        }
        let s = (p - w[0]).dot(&d) / len2;
        if !(-1e-9..=1.0 + 1e-9).contains(&s) {
            continue;
        }
        let signed = (d.x * (p.y - w[0].y) - d.y * (p.x - w[0].x)) / len2.sqrt();
        if signed.abs() <= band && best.map_or(true, |(b, _)| signed.abs() < b.abs()) {
            best = Some((signed, (k as f64 + s.clamp(0.0, 1.0)) / segments));
        }
    }
    best
}

/// Cells of a pair's histogram: `regions` x `regions` of camera i's image
/// times `depths` slices along the ray, as many as `targets` fill with
/// about [`PER_CELL`] each.
fn layout(targets: usize) -> (usize, usize) {
    [(3, 3), (2, 3), (2, 2), (1, 2), (1, 1)]
        .into_iter()
        .find(|&(r, z)| targets >= PER_CELL * r * r * z)
        .unwrap_or((1, 1))
}

/// One pair candidate: the target of camera j, its signed distance and
/// its cell.
#[derive(Clone, Copy)]
struct PairCandidate {
    b: u32,
    d: f32,
    cell: u16,
}

/// The peak of signed distances in `[-band, band]`: the centre of the
/// densest [`WINDOW`], refined by the mean within `radius`, and the
/// contrast over the floor.
fn peak(values: &[f64], band: f64, radius: f64) -> Option<(f64, f64)> {
    if values.is_empty() {
        return None;
    }
    let half = (band / BIN).ceil() as i64;
    let side = (2 * half + 1) as usize;
    let mut counts = vec![0u32; side];
    for v in values {
        let i = (v / BIN).round() as i64 + half;
        if (0..side as i64).contains(&i) {
            counts[i as usize] += 1;
        }
    }
    let w = ((WINDOW / BIN).round() as usize).max(1);
    if side < w {
        return None;
    }
    let mut best = (0u32, 0usize);
    let mut sum: u32 = counts[..w].iter().sum();
    for i in 0..=side - w {
        if i > 0 {
            sum = sum + counts[i + w - 1] - counts[i - 1];
        }
        if sum > best.0 {
            best = (sum, i);
        }
    }
    let mut sorted = counts.clone();
    sorted.sort_unstable();
    let floor = f64::from(sorted[side / 2]).max(0.5) * w as f64;
    let contrast = f64::from(best.0) / floor;
    let mut centre = ((best.1 as f64 + (w - 1) as f64 / 2.0) - half as f64) * BIN;
    for _ in 0..4 {
        let (s, k) = values
            .iter()
            .filter(|v| (*v - centre).abs() <= radius)
            .fold((0.0, 0usize), |(s, k), v| (s + v, k + 1));
        if k == 0 {
            break;
        }
        centre = s / k as f64;
    }
    Some((centre, contrast))
}

/// What a vote found.
pub(super) struct Vote {
    /// The groups kept, as tracks.
    pub tracks: Vec<Track>,
    /// Maximal consistent groups in all (ambiguous ones included).
    pub candidates: usize,
    /// Groups kept by the number of cameras (index = count).
    pub by_cameras: Vec<usize>,
    /// Per pair (i, j), i < j, in order, its cells' peak contrasts (read
    /// by the tests).
    #[cfg_attr(not(test), allow(dead_code))]
    pub contrasts: Vec<((usize, usize), Vec<f64>)>,
}

/// One target's candidates, per other camera j (filled for j > i).
type PairLists = Vec<Vec<PairCandidate>>;

/// Wide-band pair votes and consistent groups over `frames`: see the
/// module's documentation.
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
    cancel: &Cancel,
) -> Result<Vote, Cancelled> {
    let n = cameras.len();
    let pairs: Vec<(usize, usize)> = (0..n)
        .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
        .collect();
    // Per camera i, the histogram layout from its targets over all frames.
    let layouts: Vec<(usize, usize)> = (0..n)
        .map(|i| layout(frames.iter().map(|f| f[i].len()).sum()))
        .collect();
    // 1. Per frame and pair, each target's candidates.
    let mut lists: Vec<Vec<Vec<PairLists>>> = Vec::with_capacity(frames.len());
    for frame in frames {
        cancel.check()?;
        lists.push(pair_candidates(frame, cameras, volume, &layouts, band));
    }
    // 2. Per pair and cell, the peak.
    let (peaks, contrasts) = pair_peaks(&lists, &pairs, &layouts, n, band, radius);
    // 3-4. Per frame, the maximal groups consistent with the peaks.
    let mut groups: Vec<(usize, Vec<Option<usize>>)> = Vec::new();
    for (f, frame) in lists.iter().enumerate() {
        cancel.check()?;
        let adj = consistent_pairs(frame, &frames[f], &pairs, &peaks, radius);
        let found: Vec<Vec<Option<usize>>> = (0..n)
            .flat_map(|s| (0..frames[f][s].len()).map(move |a| (s, a)))
            .collect::<Vec<_>>()
            .par_iter()
            .flat_map_iter(|&(s, a)| {
                let mut out = Vec::new();
                let mut members = vec![None; n];
                members[s] = Some(a);
                extend(&adj, n, s + 1, &mut members, min_cameras, &mut out);
                out.into_iter()
            })
            .collect();
        groups.extend(found.into_iter().map(|g| (f, g)));
    }
    // 5. Unambiguous groups, the most cameras first, capped per sub-volume.
    let candidates = groups.len();
    let kept = unambiguous(groups, frames, cameras);
    let (tracks, by_cameras) = capped(kept, frames, volume, grid, max_particles, n);
    Ok(Vote {
        tracks,
        candidates,
        by_cameras,
        contrasts,
    })
}

/// Step 1 on one frame: per camera i, per target, its pair candidates in
/// each camera j > i (signed distance to its epipolar curve, and cell).
fn pair_candidates(
    frame: &[Vec<Target>],
    cameras: &[Camera],
    volume: &Volume,
    layouts: &[(usize, usize)],
    band: f64,
) -> Vec<Vec<PairLists>> {
    let n = cameras.len();
    let grids: Vec<Grid> = frame
        .iter()
        .zip(cameras)
        .map(|(t, c)| Grid::new(t, c.sensor().width, c.sensor().height, band.max(4.0)))
        .collect();
    (0..n)
        .map(|i| {
            let (regions, depths) = layouts[i];
            let sensor = cameras[i].sensor();
            frame[i]
                .par_iter()
                .map(|ta| {
                    let mut out = vec![Vec::new(); n];
                    if i + 1 >= n {
                        return out;
                    }
                    let Ok(ray) = cameras[i].ray(Point2::new(ta.x, ta.y)) else {
                        return out;
                    };
                    let Some((t0, t1)) = clip(&ray.origin, &ray.direction, volume) else {
                        return out;
                    };
                    let samples: Vec<Point3<f64>> = (0..SAMPLES)
                        .map(|k| ray.at(t0 + (t1 - t0) * k as f64 / (SAMPLES - 1) as f64))
                        .collect();
                    let rx = ((ta.x / f64::from(sensor.width) * regions as f64).floor() as usize)
                        .min(regions - 1);
                    let ry = ((ta.y / f64::from(sensor.height) * regions as f64).floor() as usize)
                        .min(regions - 1);
                    let region = ry * regions + rx;
                    for j in i + 1..n {
                        let curve: Option<Vec<Point2<f64>>> =
                            samples.iter().map(|p| cameras[j].project(p).ok()).collect();
                        let Some(curve) = curve else {
                            continue;
                        };
                        let mut near = Vec::new();
                        for w in curve.windows(2) {
                            grids[j].near_segment(&frame[j], w[0], w[1], band, &mut near);
                        }
                        near.sort_unstable();
                        near.dedup();
                        for b in near {
                            let tb = &frame[j][b];
                            if let Some((d, along)) =
                                signed_distance(&curve, Point2::new(tb.x, tb.y), band)
                            {
                                let z = ((along * depths as f64).floor() as usize).min(depths - 1);
                                out[j].push(PairCandidate {
                                    b: b as u32,
                                    d: d as f32,
                                    cell: (region * depths + z) as u16,
                                });
                            }
                        }
                    }
                    out
                })
                .collect()
        })
        .collect()
}

/// Per pair (i, j) and cell, its peak.
type Peaks = Vec<Vec<Vec<Option<f64>>>>;

/// Per pair (i, j) and cell, its contrasts.
type Contrasts = Vec<((usize, usize), Vec<f64>)>;

/// Step 2: per pair and cell over all frames, the peak of the signed
/// distances where its contrast reaches [`MIN_CONTRAST`], and every cell's
/// contrast.
fn pair_peaks(
    lists: &[Vec<Vec<PairLists>>],
    pairs: &[(usize, usize)],
    layouts: &[(usize, usize)],
    n: usize,
    band: f64,
    radius: f64,
) -> (Peaks, Contrasts) {
    let mut contrasts = Vec::new();
    let mut peaks: Peaks = vec![vec![Vec::new(); n]; n];
    for &(i, j) in pairs {
        let (regions, depths) = layouts[i];
        let cells = regions * regions * depths;
        let mut values = vec![Vec::new(); cells];
        for frame in lists {
            for candidates in &frame[i] {
                for c in &candidates[j] {
                    values[usize::from(c.cell)].push(f64::from(c.d));
                }
            }
        }
        let found: Vec<Option<(f64, f64)>> =
            values.par_iter().map(|v| peak(v, band, radius)).collect();
        contrasts.push((
            (i, j),
            found.iter().map(|p| p.map_or(0.0, |(_, c)| c)).collect(),
        ));
        peaks[i][j] = found
            .into_iter()
            .map(|p| p.and_then(|(centre, c)| (c >= MIN_CONTRAST).then_some(centre)))
            .collect();
    }
    (peaks, contrasts)
}

/// Step 3 on one frame: the pair candidates within `radius` of their
/// cell's peak, both ways: per camera i, camera j and target of i, the
/// targets of j (sorted, each once).
fn consistent_pairs(
    frame: &[Vec<PairLists>],
    targets: &[Vec<Target>],
    pairs: &[(usize, usize)],
    peaks: &Peaks,
    radius: f64,
) -> Vec<Vec<Vec<Vec<u32>>>> {
    let n = targets.len();
    let mut adj: Vec<Vec<Vec<Vec<u32>>>> = (0..n)
        .map(|i| vec![vec![Vec::new(); targets[i].len()]; n])
        .collect();
    for &(i, j) in pairs {
        for (a, candidates) in frame[i].iter().enumerate() {
            for c in &candidates[j] {
                let Some(p) = peaks[i][j][usize::from(c.cell)] else {
                    continue;
                };
                if (f64::from(c.d) - p).abs() <= radius {
                    adj[i][j][a].push(c.b);
                    adj[j][i][c.b as usize].push(a as u32);
                }
            }
        }
    }
    for by_j in adj.iter_mut() {
        for by_a in by_j.iter_mut() {
            for list in by_a.iter_mut() {
                list.sort_unstable();
                list.dedup();
            }
        }
    }
    adj
}

/// A kept group: its frame, its target per camera, its intersection.
type Group = (usize, Vec<Option<usize>>, Point3<f64>);

/// Step 5's first half: the groups each of whose targets is in no other
/// (per frame), intersected, the most cameras first.
fn unambiguous(
    groups: Vec<(usize, Vec<Option<usize>>)>,
    frames: &[Vec<Vec<Target>>],
    cameras: &[Camera],
) -> Vec<Group> {
    let mut uses: Vec<Vec<Vec<u8>>> = frames
        .iter()
        .map(|f| f.iter().map(|t| vec![0u8; t.len()]).collect())
        .collect();
    for (f, g) in &groups {
        for (c, t) in g.iter().enumerate() {
            if let Some(t) = t {
                let u = &mut uses[*f][c][*t];
                *u = u.saturating_add(1);
            }
        }
    }
    let mut kept: Vec<Group> = groups
        .into_par_iter()
        .filter(|(f, g)| {
            g.iter()
                .enumerate()
                .all(|(c, t)| t.map_or(true, |t| uses[*f][c][t] == 1))
        })
        .filter_map(|(f, g)| {
            let observations: Vec<Observation> = observations(&frames[f], &g);
            let x = intersect(cameras, &observations).ok()?;
            Some((f, g, x.point))
        })
        .collect();
    kept.sort_by_key(|(f, g, _)| (std::cmp::Reverse(g.iter().flatten().count()), *f));
    kept
}

/// Step 5's second half: the groups in order, at most `max_particles` and
/// an even share per sub-volume of `grid`, as tracks; the count kept by
/// the number of cameras.
fn capped(
    kept: Vec<Group>,
    frames: &[Vec<Vec<Target>>],
    volume: &Volume,
    grid: [usize; 3],
    max_particles: usize,
    n: usize,
) -> (Vec<Track>, Vec<usize>) {
    let cells = grid[0] * grid[1] * grid[2];
    let cap = max_particles.div_ceil(cells).max(1);
    let mut filled = vec![0usize; cells];
    let mut by_cameras = vec![0; n + 1];
    let mut tracks = Vec::new();
    for (f, g, point) in kept {
        let cell = flat(grid, cell_of(volume, grid, &point));
        if filled[cell] >= cap || tracks.len() >= max_particles {
            continue;
        }
        filled[cell] += 1;
        by_cameras[g.iter().flatten().count()] += 1;
        tracks.push(Track {
            observations: observations(&frames[f], &g)
                .into_iter()
                .map(|o| (o.camera, o.pixel, 1.0))
                .collect(),
            point,
        });
    }
    (tracks, by_cameras)
}

fn observations(frame: &[Vec<Target>], group: &[Option<usize>]) -> Vec<Observation> {
    group
        .iter()
        .enumerate()
        .filter_map(|(camera, t)| {
            t.map(|t| Observation {
                camera,
                pixel: Point2::new(frame[camera][t].x, frame[camera][t].y),
            })
        })
        .collect()
}

/// The targets of camera `k` consistent with every member of the group.
fn consistent(adj: &[Vec<Vec<Vec<u32>>>], members: &[Option<usize>], k: usize) -> Vec<u32> {
    let mut common: Option<Vec<u32>> = None;
    for (m, t) in members.iter().enumerate() {
        let Some(t) = t else { continue };
        let list = &adj[m][k][*t];
        common = Some(match common {
            None => list.clone(),
            Some(c) => c
                .into_iter()
                .filter(|x| list.binary_search(x).is_ok())
                .collect(),
        });
        if common.as_ref().is_some_and(Vec::is_empty) {
            break;
        }
    }
    common.unwrap_or_default()
}

/// Extends the group from camera `next` on (each camera: a consistent
/// target, or none); pushes the maximal groups of at least `min_cameras`.
fn extend(
    adj: &[Vec<Vec<Vec<u32>>>],
    n: usize,
    next: usize,
    members: &mut Vec<Option<usize>>,
    min_cameras: usize,
    out: &mut Vec<Vec<Option<usize>>>,
) {
    if next == n {
        let count = members.iter().flatten().count();
        if count < min_cameras {
            return;
        }
        // Maximal: no camera left out has a target consistent with all.
        let maximal = (0..n)
            .filter(|&k| members[k].is_none())
            .all(|k| consistent(adj, members, k).is_empty());
        if maximal {
            out.push(members.clone());
        }
        return;
    }
    // Too few cameras left to reach the least: stop early.
    let have = members.iter().flatten().count();
    if have + (n - next) < min_cameras {
        return;
    }
    for b in consistent(adj, members, next) {
        members[next] = Some(b as usize);
        extend(adj, n, next + 1, members, min_cameras, out);
    }
    members[next] = None;
    extend(adj, n, next + 1, members, min_cameras, out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::camera::{rotation_angles, rotation_matrix, CameraParameters};
    use crate::photogrammetry::correspond::{Matcher, MatchingParameters};
    use crate::photogrammetry::simulate::{self, RigSpec};
    use nalgebra::Vector3;
    use rand::Rng;
    use std::collections::HashMap;

    /// The simulated 4-camera rig moved by `shift` mm and `turn` rad per
    /// camera, `frames` x 2,000 particles at 0.1 px noise: the peaks'
    /// contrast, and how many kept groups are true.
    fn measure(shift: f64, turn: f64, band: f64, count: usize) -> (Vote, usize) {
        let spec = RigSpec::convergent(4);
        let truth = spec.build().unwrap();
        let mut rng = simulate::rng(3);
        let mut unit = || Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
        let rough: Vec<Camera> = truth
            .iter()
            .map(|c| {
                let mut p: CameraParameters = c.parameters().clone();
                p.exterior.position += unit() * shift;
                let e = &p.exterior;
                let r = nalgebra::Rotation3::from_scaled_axis(unit() * turn).matrix()
                    * rotation_matrix(e.omega, e.phi, e.kappa);
                (p.exterior.omega, p.exterior.phi, p.exterior.kappa) = rotation_angles(&r);
                Camera::new(p).unwrap()
            })
            .collect();
        let mut rng = simulate::rng(7);
        let simulated: Vec<_> = (0..count)
            .map(|_| {
                let points = simulate::particles(&spec.volume, 2000, &mut rng);
                simulate::target_frame(&truth, &points, 0.1, 0.0, &mut rng)
            })
            .collect();
        let mut owner = HashMap::new();
        for (f, s) in simulated.iter().enumerate() {
            for (c, targets) in s.targets.iter().enumerate() {
                for (t, target) in targets.iter().enumerate() {
                    owner.insert((c, target.x.to_bits()), (f, s.truth[c][t]));
                }
            }
        }
        let frames: Vec<Vec<Vec<Target>>> = simulated.into_iter().map(|s| s.targets).collect();
        let volume = Matcher::new(
            &rough,
            &MatchingParameters {
                tolerance: band,
                ..MatchingParameters::default()
            },
        )
        .unwrap()
        .volume()
        .to_owned();
        let vote = vote(
            &frames,
            &rough,
            &volume,
            [4, 4, 4],
            band,
            1.0,
            3,
            4000,
            &Cancel::new(),
        )
        .unwrap();
        let correct = vote
            .tracks
            .iter()
            .filter(|t| {
                let owners: Vec<_> = t
                    .observations
                    .iter()
                    .map(|(c, p, _)| owner.get(&(*c, p.x.to_bits())))
                    .collect();
                owners.iter().all(|o| o.is_some() && *o == owners[0])
            })
            .count();
        (vote, correct)
    }

    /// Prints the peaks' contrast over the ghost floor and the kept groups'
    /// truth for the disturbances of issue 14 (run with --nocapture), and
    /// asserts that enough groups are kept for an adjustment of 4 x 6
    /// exterior parameters (500, several times [`super::super::MIN_PARTICLES`])
    /// and that nearly all are true (a ghost passes 3 pairwise tests of
    /// 2 px in 16 px by chance with odds of about 1/500, and the
    /// uniqueness rule removes most; measured 862 of 863, 773 of 777).
    #[test]
    fn peak_contrast_on_the_simulated_rig() {
        for (label, shift, turn, band) in [
            ("0.7 mm 1 mrad", 0.7, 1e-3, 8.0),
            ("2 mm 3 mrad", 2.0, 3e-3, 20.0),
        ] {
            let (vote, correct) = measure(shift, turn, band, 10);
            for ((i, j), c) in &vote.contrasts {
                let min = c.iter().copied().fold(f64::INFINITY, f64::min);
                let mut sorted = c.clone();
                sorted.sort_by(f64::total_cmp);
                println!(
                    "{label}: pair {i}-{j}: {} cells, contrast min {min:.1}, median {:.1}",
                    c.len(),
                    sorted[c.len() / 2]
                );
            }
            println!(
                "{label}: {} maximal groups, kept {} ({:?} by cameras), {correct} true",
                vote.candidates,
                vote.tracks.len(),
                vote.by_cameras
            );
            assert!(vote.tracks.len() >= 500, "{}", vote.tracks.len());
            assert!(
                correct as f64 >= 0.95 * vote.tracks.len() as f64,
                "{correct}"
            );
        }
    }
}
