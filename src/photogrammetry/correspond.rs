//! Stereo correspondences: which particle images in 2..N cameras belong to
//! one particle, and where that particle is (design paper, section 6:
//! establishment of correspondences by epipolar geometry with three and
//! more cameras; 3D coordinates by spatial intersection, section 4.3).
//!
//! The search, for a frame of targets per camera:
//!
//! 1. Every target's ray into the object medium is traced once (Eq. 13-17).
//!    Targets of each camera go into a uniform grid (a spatial index, with
//!    the targets stored in cell order) for searches around a point, and,
//!    per camera pair, into a grid of thin sectors along the epipolar
//!    curves for the bands (`pencil`): no search scans all targets.
//! 2. **Seed pairs**, one stage each: camera pairs `(i, j)` chosen so that
//!    every set of three cameras contains one of them (the cameras split
//!    into two halves, all pairs within each half: 2 pairs for 4 cameras
//!    instead of 6). Each still unused target of camera i has its ray cut by
//!    the observation volume; the segment between the near and far points is
//!    projected into camera j as a bent curve (a parabola or polyline within
//!    a tenth of the tolerance of the true curve) and widened by the
//!    tolerance: the epipolar band. Its candidates come from an index of
//!    camera j's targets in thin sectors along the curves (`pencil`).
//! 3. **Completion.** Each candidate pair's rays meet (nearly) in a 3D
//!    point; its image in every other camera (on the first target's
//!    epipolar curve there) is searched within `COMPLETION_RADIUS` (3)
//!    tolerances, and a target joins if its ray meets the pair's within the
//!    tolerance. A camera with several such targets gives several candidate
//!    groups; members that do not fit together are dropped worst first.
//! 4. **Selection**, best first: larger groups before smaller (a fourth
//!    camera cuts the ambiguities the design paper's Table 2 counts by at
//!    least an order of magnitude), then by the rays' spread in pixels; each
//!    target is used at most once. The first stage's groups give the frame's
//!    image noise, from which the acceptance thresholds follow
//!    (`Search::estimate_noise`). Then targets are exchanged between
//!    accepted groups where that fits both better (near-coincident images).
//! 5. **Pairs**, when two cameras suffice (`min_cameras = 2`): among the
//!    targets still unused, a pair is accepted only when each target is the
//!    other's single candidate in its band.
//! 6. Every accepted group's point by least-squares intersection
//!    ([`intersect_from`]), with standard deviations and residuals; a group
//!    whose largest residual exceeds the acceptance is dropped.
//!
//! There is no fixed limit on cameras or targets: memory grows linearly
//! with the targets, and the work with the targets times the (small) number
//! of band candidates.

use nalgebra::{Point2, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::camera::{Camera, Ray};
use super::intersect::{intersect_from, ray_midpoint, Observation};
use super::target::Target;
use super::volume::Volume;

mod pencil;

use pencil::{index_range, Pencil, PencilGrid};

/// Default epipolar band half-width (px).
pub const DEFAULT_TOLERANCE_PX: f64 = 1.0;

/// Optional similarity criteria: a candidate's size and brightness must be
/// within these factors of the target it is matched with (where both are
/// known).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Similarity {
    /// Largest ratio of pixel counts (>= 1).
    pub max_size_ratio: f64,
    /// Largest ratio of grey-value sums (>= 1).
    pub max_brightness_ratio: f64,
}

/// How to match.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MatchingParameters {
    /// Half-width of the epipolar band, and the largest accepted residual
    /// of a particle's intersection (px).
    pub tolerance: f64,
    /// The observation volume; `None` for the region all cameras look at
    /// (see [`default_volume`]).
    pub volume: Option<Volume>,
    /// The fewest cameras that must see a particle (2..N).
    pub min_cameras: usize,
    /// Similarity criteria, if any.
    pub similarity: Option<Similarity>,
}

impl Default for MatchingParameters {
    fn default() -> Self {
        MatchingParameters {
            tolerance: DEFAULT_TOLERANCE_PX,
            volume: None,
            min_cameras: 2,
            similarity: None,
        }
    }
}

/// Why matching cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MatchError {
    /// Fewer than two cameras.
    #[error("matching needs at least 2 cameras, the calibration has {0}")]
    TooFewCameras(usize),
    /// A target list per camera is expected.
    #[error("got targets for {targets} cameras, but the calibration has {cameras}; give one target list per camera, in camera order")]
    CameraCount {
        /// Target lists given.
        targets: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// The tolerance must be positive and finite.
    #[error("the tolerance must be a positive number of pixels, got {0}")]
    Tolerance(f64),
    /// The volume is empty or not finite.
    #[error(
        "the observation volume is empty: every minimum must be below its maximum, got \
         x {}..{}, y {}..{}, z {}..{} mm",
        .0.min.x, .0.max.x, .0.min.y, .0.max.y, .0.min.z, .0.max.z
    )]
    EmptyVolume(Volume),
    /// `min_cameras` out of range.
    #[error("min_cameras must be between 2 and the number of cameras ({cameras}), got {min}")]
    MinCameras {
        /// The value given.
        min: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// A similarity ratio below 1.
    #[error("similarity ratios must be at least 1, got size {0} and brightness {1}")]
    Similarity(f64, f64),
    /// A target with a non-finite position.
    #[error("camera {camera}, target {index}: its position is not a finite number")]
    InvalidTarget {
        /// The camera.
        camera: usize,
        /// The target's index in its list.
        index: usize,
    },
}

/// A particle found in the frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Particle {
    /// Position (mm).
    pub position: Point3<f64>,
    /// Standard deviations of X, Y, Z from the intersection (mm).
    pub sigma: Vector3<f64>,
    /// Root mean square reprojection residual (px).
    pub rms_px: f64,
    /// Per camera, the index of its target, `None` where it has none.
    pub targets: Vec<Option<usize>>,
}

impl Particle {
    /// How many cameras see this particle.
    pub fn camera_count(&self) -> usize {
        self.targets.iter().filter(|t| t.is_some()).count()
    }
}

/// The region all cameras look at: a cube around the point nearest to the
/// cameras' optical axes (traced through their walls), whose half-size is
/// the smallest half-width of the cameras' fields of view at that distance.
pub fn default_volume(cameras: &[Camera]) -> Option<Volume> {
    let axes: Vec<Ray> = cameras
        .iter()
        .filter_map(|camera| {
            let sensor = camera.sensor();
            let centre = Point2::new(
                f64::from(sensor.width) / 2.0,
                f64::from(sensor.height) / 2.0,
            );
            camera.ray(centre).ok()
        })
        .collect();
    if axes.len() < 2 {
        return None;
    }
    let centre = ray_midpoint(axes.iter().copied())?;
    let half = cameras
        .iter()
        .map(|camera| {
            let sensor = camera.sensor();
            let half_sensor = f64::min(
                f64::from(sensor.width) * sensor.pixel_size_x,
                f64::from(sensor.height) * sensor.pixel_size_y,
            ) / 2.0;
            (centre - camera.position()).norm() * half_sensor / camera.parameters().interior.c
        })
        .fold(f64::INFINITY, f64::min);
    let extent = Vector3::repeat(half);
    Some(Volume {
        min: centre - extent,
        max: centre + extent,
    })
}

/// How far around a pair's predicted image a third camera is searched, in
/// tolerances.
const COMPLETION_RADIUS: f64 = 3.0;

/// Per pair and other camera, the most targets (the best fitting) that may
/// complete the pair's group. More arise only where the tolerance is large
/// for the target density; the candidates beyond the best few are then
/// practically never the particle's image, and their combinations would
/// multiply the work and memory.
const MAX_CANDIDATES_PER_CAMERA: usize = 3;

/// Per target of a seed camera, the most candidate groups kept (the largest
/// with the smallest spread): a target ends in at most one particle, and
/// this bounds the candidates' memory by the target count.
const MAX_GROUPS_PER_TARGET: usize = 8;

/// The fewest candidate groups from which the frame's image noise is
/// estimated.
const NOISE_SAMPLE: usize = 50;

/// Cells per target of the square grid that serves searches around a point
/// (completion, exchanges); bands use the pencil grids.
const CELLS_PER_TARGET: f64 = 1.0;

/// How far (in tolerances) an epipolar curve's parabolas may stray from
/// the true curve at the sampled rays: a tenth, less a fifth for what the
/// samples miss. It admits one parabola for every camera pair of the
/// simulator's rigs (0.05 needed more for the pairs at right angles).
const PARABOLA_SHARE: f64 = 0.08;

/// A marker for "no target" in the flat group arrays.
const NONE: u32 = u32::MAX;

/// Matches frames of targets against one calibration: the cameras are
/// prepared (refraction tables over the volume) once, for many frames.
#[derive(Clone, Debug)]
pub struct Matcher {
    cameras: Vec<Camera>,
    tolerance: f64,
    volume: Volume,
    min_cameras: usize,
    similarity: Option<Similarity>,
    /// Seed camera pairs, in the order that decides which seed keeps a group.
    seeds: Vec<(usize, usize)>,
    /// Per camera: principal distance over pixel size, for pixel-scale
    /// estimates of distances in object space.
    pixels_per_unit_angle: Vec<f64>,
    /// Per ordered camera pair `(i, k)` at `i * count + k`: the shape of
    /// the epipolar curves from i in k.
    epipolar: Vec<EpipolarGeometry>,
}

/// Camera pairs such that every set of three cameras contains one: all
/// pairs within the first half of the cameras and within the second half
/// (the complement graph is bipartite, hence free of triangles). Two
/// cameras have the one pair.
fn seed_pairs(cameras: usize) -> Vec<(usize, usize)> {
    if cameras == 2 {
        return vec![(0, 1)];
    }
    let half = cameras.div_ceil(2);
    let mut seeds = Vec::new();
    for (from, to) in [(0, half), (half, cameras)] {
        for i in from..to {
            for j in i + 1..to {
                seeds.push((i, j));
            }
        }
    }
    seeds
}

impl Matcher {
    /// Validates the parameters and prepares the cameras.
    pub fn new(cameras: &[Camera], parameters: &MatchingParameters) -> Result<Matcher, MatchError> {
        let count = cameras.len();
        if count < 2 {
            return Err(MatchError::TooFewCameras(count));
        }
        if !(parameters.tolerance.is_finite() && parameters.tolerance > 0.0) {
            return Err(MatchError::Tolerance(parameters.tolerance));
        }
        if !(2..=count).contains(&parameters.min_cameras) {
            return Err(MatchError::MinCameras {
                min: parameters.min_cameras,
                cameras: count,
            });
        }
        if let Some(s) = parameters.similarity {
            if !(s.max_size_ratio >= 1.0 && s.max_brightness_ratio >= 1.0) {
                return Err(MatchError::Similarity(
                    s.max_size_ratio,
                    s.max_brightness_ratio,
                ));
            }
        }
        let volume = match parameters.volume {
            Some(volume) => volume,
            None => default_volume(cameras).ok_or(MatchError::TooFewCameras(0))?,
        };
        let valid = (0..3).all(|i| {
            volume.min[i] < volume.max[i] && !volume.min[i].is_nan() && !volume.max[i].is_nan()
        });
        if !valid {
            return Err(MatchError::EmptyVolume(volume));
        }
        // The refraction table needs a bounded region; an unbounded axis
        // (allowed, as in OpenPTV, which bounds only the depth) is left to
        // the exact solve.
        let bounded = (0..3).all(|i| volume.min[i].is_finite() && volume.max[i].is_finite());
        let cameras: Vec<Camera> = cameras
            .iter()
            .map(|camera| {
                if bounded {
                    camera.clone().with_refraction_table(&volume)
                } else {
                    camera.clone()
                }
            })
            .collect();
        let pixels_per_unit_angle = cameras
            .iter()
            .map(|camera| {
                let sensor = camera.sensor();
                camera.parameters().interior.c / sensor.pixel_size_x.min(sensor.pixel_size_y)
            })
            .collect();
        let epipolar = (0..count * count)
            .map(|index| {
                let (i, k) = (index / count, index % count);
                EpipolarGeometry::sample(
                    &cameras,
                    &volume,
                    (i, k),
                    PARABOLA_SHARE * parameters.tolerance,
                )
            })
            .collect();
        Ok(Matcher {
            epipolar,
            seeds: seed_pairs(count),
            cameras,
            tolerance: parameters.tolerance,
            volume,
            min_cameras: parameters.min_cameras,
            similarity: parameters.similarity,
            pixels_per_unit_angle,
        })
    }

    /// The cameras, with refraction tables.
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    /// The observation volume in use.
    pub fn volume(&self) -> &Volume {
        &self.volume
    }

    /// Finds the particles of one frame: `targets[c]` are camera c's targets.
    pub fn match_frame(&self, targets: &[Vec<Target>]) -> Result<Vec<Particle>, MatchError> {
        let count = self.cameras.len();
        if targets.len() != count {
            return Err(MatchError::CameraCount {
                targets: targets.len(),
                cameras: count,
            });
        }
        for (camera, list) in targets.iter().enumerate() {
            if let Some(index) = list
                .iter()
                .position(|t| !(t.x.is_finite() && t.y.is_finite()))
            {
                return Err(MatchError::InvalidTarget { camera, index });
            }
        }
        let frames: Vec<CameraFrame> = self
            .cameras
            .iter()
            .zip(targets)
            .map(|(camera, list)| CameraFrame::new(camera, list, self.tolerance))
            .collect();
        let mut search = Search::new(self, &frames);
        if count >= 3 {
            for (stage, &seed) in self.seeds.iter().enumerate() {
                let groups = search.candidate_groups(seed);
                if stage == 0 {
                    search.estimate_noise(&groups);
                }
                search.select(groups);
            }
        }
        search.improve();
        if self.min_cameras == 2 {
            search.pairs();
        }
        Ok(search.finish())
    }

    /// Whether `a` and `b` pass the similarity criteria.
    fn similar(&self, a: &Target, b: &Target) -> bool {
        let Some(s) = self.similarity else {
            return true;
        };
        let within =
            |x: f64, y: f64, limit: f64| x <= 0.0 || y <= 0.0 || (x / y).max(y / x) <= limit;
        within(f64::from(a.n), f64::from(b.n), s.max_size_ratio)
            && within(a.sumg as f64, b.sumg as f64, s.max_brightness_ratio)
    }
}

/// A uniform grid over target positions (pixels).
#[derive(Debug)]
struct TargetGrid {
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
    fn density(&self) -> f64 {
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
    fn visit(&self, lo: Point2<f64>, hi: Point2<f64>, mut visit: impl FnMut(usize)) {
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
struct CameraFrame {
    targets: Vec<Target>,
    /// Per target, its index in the caller's list.
    original: Vec<u32>,
    sightings: Vec<Sighting>,
    grid: TargetGrid,
}

impl CameraFrame {
    fn new(camera: &Camera, targets: &[Target], tolerance: f64) -> CameraFrame {
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
    fn position(&self, target: usize) -> Point2<f64> {
        self.sightings[target].position
    }

    #[inline]
    fn ray(&self, target: usize) -> Option<Ray> {
        self.sightings[target].ray()
    }
}

/// The part of a ray inside a box, as ray parameters (the ray starts at
/// its origin: t >= 0).
fn clip(ray: &Ray, volume: &Volume) -> Option<(f64, f64)> {
    let (mut near, mut far) = (0.0f64, f64::INFINITY);
    for i in 0..3 {
        let (o, d) = (ray.origin[i], ray.direction[i]);
        if d.abs() < 1e-15 {
            if o < volume.min[i] || o > volume.max[i] {
                return None;
            }
            continue;
        }
        let (a, b) = ((volume.min[i] - o) / d, (volume.max[i] - o) / d);
        near = near.max(a.min(b));
        far = far.min(a.max(b));
    }
    (near < far && far.is_finite()).then_some((near, far))
}

/// Where two rays pass closest: the parameter along `a` of its point
/// nearest to `b`, and the point midway between the two rays.
#[inline]
fn closest_approach(a: &Ray, b: &Ray) -> Option<(f64, Point3<f64>)> {
    let w = a.origin - b.origin;
    let cos = a.direction.dot(&b.direction);
    let denominator = 1.0 - cos * cos;
    if denominator < 1e-12 {
        return None;
    }
    let (d, e) = (a.direction.dot(&w), b.direction.dot(&w));
    let ta = (cos * e - d) / denominator;
    let tb = (e - cos * d) / denominator;
    Some((ta, nalgebra::center(&a.at(ta), &b.at(tb))))
}

/// A parabola `P(u) = a + b u + c u^2`, u in [0, 1] (pixels).
#[derive(Clone, Copy, Debug)]
struct Parabola {
    a: Vector2<f64>,
    b: Vector2<f64>,
    c: Vector2<f64>,
    /// The chord `P(1) - P(0) = b + c` over its squared length (zero for
    /// a point): projections on the chord without a division.
    chord_scaled: Vector2<f64>,
}

impl Parabola {
    /// The parabola through `p0`, `pm`, `p1` at u = 0, 1/2, 1.
    fn through(p0: Point2<f64>, pm: Point2<f64>, p1: Point2<f64>) -> Parabola {
        let c = (p0.coords + p1.coords - pm.coords * 2.0) * 2.0;
        let chord = p1 - p0;
        let length_sq = chord.norm_squared();
        Parabola {
            a: p0.coords,
            b: chord - c,
            c,
            chord_scaled: if length_sq > 0.0 {
                chord / length_sq
            } else {
                Vector2::zeros()
            },
        }
    }

    #[inline]
    fn at(&self, u: f64) -> Point2<f64> {
        Point2::from(self.a + (self.b + self.c * u) * u)
    }

    /// How far the parabola strays from the chord of a span `du` long in
    /// u: `|c| du^2 / 4`.
    #[inline]
    fn deviation(&self, du: f64) -> f64 {
        self.c.norm() * du * du / 4.0
    }

    /// Whether `p` lies within `sqrt(limit_sq)` of the parabola: Newton's
    /// method on the foot point, `(P(u) - p) . P'(u) = 0`, from the
    /// projection on the chord, u kept in [0, 1], stopped as soon as the
    /// answer is certain (or, failing that, once a step moves the foot
    /// point by less than 1e-6 px).
    ///
    /// Yes, once a curve point is within the limit. No, once a lower bound
    /// on the distance exceeds it: expanding `D(u) = |P(u) - p|^2` about an
    /// iterate u, with `q = P(u) - p` and `T = P'(u)`, gives exactly
    /// `D(u + s) = D + 2 (q.T) s + (|T|^2 + 2 q.c) s^2 + 2 (T.c) s^3 +
    /// |c|^2 s^4`, so for |s| <= 1 (both in [0, 1])
    /// `D(u + s) >= D + 2 g s + h s^2 >= D - g^2 / h` with `g = q.T`,
    /// `h = |T|^2 + 2 q.c - 2 |T.c| > 0`. Epipolar parabolas are nearly
    /// straight, so the bound is within a percent of the distance at the
    /// first iterate and most targets of a band's cells are decided
    /// without a step.
    #[inline]
    fn within(&self, p: &Point2<f64>, limit_sq: f64) -> bool {
        const MAX_STEPS: usize = 8;
        const SETTLED_SQ: f64 = 1e-12;
        let d = p.coords - self.a;
        let mut u = d.dot(&self.chord_scaled).clamp(0.0, 1.0);
        if !u.is_finite() {
            return d.norm_squared() <= limit_sq;
        }
        for _ in 0..MAX_STEPS {
            let q = (self.b + self.c * u) * u - d;
            let distance_sq = q.norm_squared();
            if distance_sq <= limit_sq {
                return true;
            }
            let tangent = self.b + self.c * (2.0 * u);
            let tangent_sq = tangent.norm_squared();
            let g = q.dot(&tangent);
            let slope = tangent_sq + 2.0 * q.dot(&self.c);
            let bound = slope - 2.0 * tangent.dot(&self.c).abs();
            // distance_sq - g^2 / bound > limit_sq, without the division.
            if bound > 0.0 && (distance_sq - limit_sq) * bound > g * g {
                return false;
            }
            if slope <= 0.0 {
                break;
            }
            let next = (u - g / slope).clamp(0.0, 1.0);
            let moved = next - u;
            u = next;
            if moved * moved * tangent_sq < SETTLED_SQ {
                break;
            }
        }
        ((self.b + self.c * u) * u - d).norm_squared() <= limit_sq
    }
}

/// The image in one camera of a ray's segment inside the volume.
///
/// A chain of parabolas, each through the images of the ends and middle of
/// its part of the segment (2m + 1 projections for m parts): within a tenth
/// of the tolerance of the true (bent) curve, as bands need, where the
/// pair's [`EpipolarGeometry`] says how many parts that takes (one, for
/// every pair of the simulator's rigs). Bands measure distances to the
/// parabolas themselves, so no further approximation enters.
#[derive(Default)]
struct EpipolarCurve {
    near: f64,
    far: f64,
    /// The parts, in order along the ray; empty if the ray was not traced.
    parts: Vec<Parabola>,
}

impl EpipolarCurve {
    /// Traces `ray` between `near` and `far` into `camera` in `parts`
    /// parabolas; false (and no parts) if the segment does not image there.
    fn trace(&mut self, camera: &Camera, ray: &Ray, (near, far): (f64, f64), parts: usize) -> bool {
        self.near = near;
        self.far = far;
        self.parts.clear();
        let project = |s: usize| {
            let u = s as f64 / (2 * parts) as f64;
            camera.project(&ray.at(near + (far - near) * u)).ok()
        };
        let Some(mut start) = project(0) else {
            return false;
        };
        for part in 0..parts {
            let (Some(middle), Some(end)) = (project(2 * part + 1), project(2 * part + 2)) else {
                self.parts.clear();
                return false;
            };
            self.parts.push(Parabola::through(start, middle, end));
            start = end;
        }
        true
    }

    /// The image of the ray's point at parameter `t`; `None` outside the
    /// traced segment.
    #[inline]
    fn at(&self, t: f64) -> Option<Point2<f64>> {
        let u = (t - self.near) / (self.far - self.near);
        if !(0.0..=1.0).contains(&u) || self.parts.is_empty() {
            return None;
        }
        let scaled = u * self.parts.len() as f64;
        let part = (scaled as usize).min(self.parts.len() - 1);
        Some(self.parts[part].at(scaled - part as f64))
    }

    /// Whether `p` lies within `sqrt(limit_sq)` of the curve.
    #[inline]
    fn within(&self, p: &Point2<f64>, limit_sq: f64) -> bool {
        self.parts.iter().any(|part| part.within(p, limit_sq))
    }
}

/// The most parabolas an epipolar curve is traced in.
const MAX_PARTS: usize = 32;

/// What the matcher knows in advance of the epipolar curves from camera `i`
/// in camera `k`, from the rays through a 13 x 13 grid of camera i's pixels
/// cut by the volume: how many parabolas trace them within the limit, and
/// the pencil their chords form.
#[derive(Clone, Debug)]
struct EpipolarGeometry {
    parts: usize,
    pencil: Pencil,
}

impl EpipolarGeometry {
    /// Samples the pair. Parabolas are checked at a quarter and three
    /// quarters of each part, where their error peaks; rays that miss the
    /// volume or do not image are skipped.
    fn sample(cameras: &[Camera], volume: &Volume, (i, k): (usize, usize), limit: f64) -> Self {
        const SAMPLES: u32 = 12;
        let mut segments = Vec::new();
        let sensor = cameras[i].sensor();
        for row in 0..=SAMPLES {
            for column in 0..=SAMPLES {
                let pixel = Point2::new(
                    f64::from(sensor.width) * f64::from(column) / f64::from(SAMPLES),
                    f64::from(sensor.height) * f64::from(row) / f64::from(SAMPLES),
                );
                let Ok(ray) = cameras[i].ray(pixel) else {
                    continue;
                };
                if let Some(span) = clip(&ray, volume) {
                    segments.push((ray, span));
                }
            }
        }
        let project = |ray: &Ray, (near, far): (f64, f64), u: f64| {
            cameras[k].project(&ray.at(near + (far - near) * u)).ok()
        };
        let chords: Vec<(Point2<f64>, Point2<f64>)> = segments
            .iter()
            .filter_map(|(ray, span)| Some((project(ray, *span, 0.0)?, project(ray, *span, 1.0)?)))
            .collect();
        let pencil = Pencil::fit(&chords).unwrap_or_else(Pencil::strips);
        let fits = |parts: usize| {
            segments.iter().all(|(ray, span)| {
                let points: Option<Vec<Point2<f64>>> = (0..=4 * parts)
                    .map(|s| project(ray, *span, s as f64 / (4 * parts) as f64))
                    .collect();
                let Some(points) = points else {
                    return true;
                };
                points.chunks_exact(4).enumerate().all(|(part, quarter)| {
                    let parabola = Parabola::through(quarter[0], quarter[2], points[4 * part + 4]);
                    (parabola.at(0.25) - quarter[1]).norm() <= limit
                        && (parabola.at(0.75) - quarter[3]).norm() <= limit
                })
            })
        };
        let parts = if i == k {
            1
        } else {
            (1..=MAX_PARTS)
                .find(|&parts| fits(parts))
                .unwrap_or(MAX_PARTS)
        };
        EpipolarGeometry { parts, pencil }
    }
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

/// Candidate groups: per group, one target (or NONE) per camera, in a flat
/// array with a stride of the camera count.
#[derive(Default)]
struct CandidateGroups {
    members: Vec<u32>,
    sizes: Vec<u8>,
    spreads: Vec<f64>,
    /// The largest miss of a member (px).
    largest: Vec<f64>,
}

/// The state of one frame's search.
struct Search<'m, 'f> {
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
    /// The largest miss (px) a group member may have, and the largest
    /// residual of a particle's intersection: the tolerance, or less once
    /// the frame's image noise is known (see [`Search::estimate_noise`]).
    acceptance: f64,
    /// The groups accepted so far: members per camera (NONE for none),
    /// group after group, a stride of the camera count.
    accepted: Vec<u32>,
    /// Per camera and target, the accepted group that holds it, or NONE.
    owner: Vec<Vec<u32>>,
}

impl<'m, 'f> Search<'m, 'f> {
    fn new(matcher: &'m Matcher, frames: &'f [CameraFrame]) -> Self {
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
            acceptance: matcher.tolerance,
            accepted: Vec::new(),
            owner: frames.iter().map(|f| vec![NONE; f.targets.len()]).collect(),
        }
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
    /// `found` once for each unused target of camera j within the
    /// tolerance of the curve.
    fn band(&mut self, i: usize, a: usize, j: usize, mut found: impl FnMut(usize)) {
        if !self.trace(i, a, j) {
            return;
        }
        let tolerance = self.matcher.tolerance;
        let frame = &self.frames[j];
        let pair = i * self.frames.len() + j;
        let used = &self.used[j];
        let grid = self.pencil_grids[pair].get_or_insert_with(|| {
            PencilGrid::new(
                self.matcher.epipolar[pair].pencil,
                (0..frame.sightings.len())
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
        for part in &curve.parts {
            let spans = ((part.b + part.c).norm() / (2.0 * grid.cell_diameter()))
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
            let size = group.iter().filter(|&&m| m != NONE).count();
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

    /// Steps 2 and 3: candidate groups of three or more cameras.
    ///
    /// The point where a pair's rays meet is uncertain along their epipolar
    /// lines, most where those lines run nearly parallel in a third camera,
    /// so the third camera is searched within `COMPLETION_RADIUS` (3)
    /// tolerances of its image, and a target there is kept only if its ray
    /// meets the pair's within the tolerance.
    fn candidate_groups(&mut self, (i, j): (usize, usize)) -> CandidateGroups {
        let count = self.frames.len();
        let tolerance = self.matcher.tolerance;
        let mut groups = CandidateGroups::default();
        let mut partners = Vec::new();
        let mut near: Vec<Vec<u32>> = vec![Vec::new(); count];
        let mut members = vec![NONE; count];
        let mut group = vec![NONE; count];
        let mut seen = Vec::with_capacity(count);
        let mut choice = Vec::with_capacity(count);
        let mut traced = vec![false; count];
        let mut fits: Vec<(f64, u32)> = Vec::new();
        // This target's candidate groups: (size, spread, offset in own_members).
        let mut own: Vec<(u8, GroupFit, usize)> = Vec::new();
        let mut own_members: Vec<u32> = Vec::new();
        {
            for a in 0..self.frames[i].targets.len() {
                if self.used[i][a] {
                    continue;
                }
                let Some(ray_a) = self.frames[i].ray(a) else {
                    continue;
                };
                partners.clear();
                // Each partner's ray is read as the band finds it, from
                // the cache line its position was just tested from.
                let frame_j = &self.frames[j];
                self.band(i, a, j, |b| partners.push((b, frame_j.ray(b))));
                if partners.is_empty() {
                    continue;
                }
                own.clear();
                own_members.clear();
                // The ray's images in the other cameras, traced on demand.
                traced.fill(false);
                for &(b, ray_b) in &partners {
                    let Some((t, point)) = ray_b.and_then(|ray_b| closest_approach(&ray_a, &ray_b))
                    else {
                        continue;
                    };
                    seen.clear();
                    members.fill(NONE);
                    members[i] = a as u32;
                    members[j] = b as u32;
                    for k in 0..count {
                        near[k].clear();
                        if k == i || k == j {
                            continue;
                        }
                        if !traced[k] {
                            traced[k] = true;
                            self.trace(i, a, k);
                        }
                        // Where the pair's point images, to within half the
                        // rays' gap (the curve follows ray a).
                        let Some(pixel) = self.curves[k].at(t) else {
                            continue;
                        };
                        let reference = &self.frames[i].targets[a];
                        let mut list = std::mem::take(&mut near[k]);
                        self.near(
                            k,
                            pixel,
                            COMPLETION_RADIUS * tolerance,
                            reference,
                            &mut list,
                        );
                        // Only targets whose rays meet the pair's, the best
                        // few (see MAX_CANDIDATES_PER_CAMERA).
                        let mut fitting = std::mem::take(&mut fits);
                        fitting.clear();
                        fitting.extend(list.iter().filter_map(|&c| {
                            members[k] = c;
                            let fit = self.fit(&members, |_| false);
                            members[k] = NONE;
                            fit.filter(|f| f.largest <= tolerance)
                                .map(|f| (f.largest, c))
                        }));
                        fitting.sort_unstable_by(|x, y| x.0.total_cmp(&y.0));
                        fitting.truncate(MAX_CANDIDATES_PER_CAMERA);
                        list.clear();
                        list.extend(fitting.iter().map(|&(_, c)| c));
                        fits = fitting;
                        if !list.is_empty() {
                            seen.push(k);
                        }
                        near[k] = list;
                    }
                    let _ = point;
                    if seen.is_empty() {
                        continue;
                    }
                    // Every combination of one target per camera that has
                    // any; targets that each fit the pair may not fit
                    // together (one imaging another particle), so the worst
                    // is dropped until they do.
                    choice.clear();
                    choice.resize(seen.len(), 0usize);
                    loop {
                        group.copy_from_slice(&members);
                        for (slot, &k) in seen.iter().enumerate() {
                            group[k] = near[k][choice[slot]];
                        }
                        if let Some(fit) = self.trim(&mut group, tolerance, |k| k == i || k == j) {
                            let size = group.iter().filter(|&&m| m != NONE).count() as u8;
                            own.push((size, fit, own_members.len()));
                            own_members.extend_from_slice(&group);
                        }
                        // Next combination (odometer).
                        let mut slot = 0;
                        while slot < seen.len() {
                            choice[slot] += 1;
                            if choice[slot] < near[seen[slot]].len() {
                                break;
                            }
                            choice[slot] = 0;
                            slot += 1;
                        }
                        if slot == seen.len() {
                            break;
                        }
                    }
                }
                // The target's best candidates only (see
                // MAX_GROUPS_PER_TARGET): memory stays linear in the targets.
                own.sort_unstable_by(|x, y| y.0.cmp(&x.0).then(x.1.spread.total_cmp(&y.1.spread)));
                for &(size, fit, at) in own.iter().take(MAX_GROUPS_PER_TARGET) {
                    groups
                        .members
                        .extend_from_slice(&own_members[at..at + count]);
                    groups.sizes.push(size);
                    groups.spreads.push(fit.spread);
                    groups.largest.push(fit.largest);
                }
            }
        }
        groups
    }

    /// Sets the acceptance threshold from the frame itself.
    ///
    /// The largest groups are nearly all true; their spreads give the image
    /// noise sigma (a member's miss is a 2D residual, so for m rays the mean
    /// squared miss is about 2 sigma^2 (1 - 3/(2m))). A member is then
    /// accepted where it is likelier to be the particle's image than a
    /// stranger's: its miss r has to satisfy
    /// `exp(-r^2 / 2 sigma^2) / (2 pi sigma^2) > density`, i.e.
    /// `r^2 < 2 sigma^2 ln(1 / (2 pi sigma^2 density))`, and at least
    /// 2 sigma and at most 3 sigma (1.1% of true members lost: a group of
    /// four then stays a triplet, a triplet is lost, about 3% of them), and
    /// between a tenth of the tolerance (noise-free data) and the tolerance.
    /// On the benchmark scenes a more lenient limit for a group's last three
    /// members (3.5 or 4 sigma) found fewer particles, not more: the random
    /// groups it lets in take targets from true ones. With fewer than
    /// [`NOISE_SAMPLE`] groups the tolerance stands.
    fn estimate_noise(&mut self, groups: &CandidateGroups) {
        let Some(&largest) = groups.sizes.iter().max() else {
            return;
        };
        let mut spreads: Vec<f64> = groups
            .sizes
            .iter()
            .zip(&groups.spreads)
            .filter(|(&size, _)| size == largest)
            .map(|(_, &spread)| spread * spread)
            .collect();
        if spreads.len() < NOISE_SAMPLE {
            return;
        }
        let middle = spreads.len() / 2;
        let (_, median, _) = spreads.select_nth_unstable_by(middle, f64::total_cmp);
        let m = f64::from(largest);
        let sigma_sq = *median / (2.0 * (1.0 - 1.5 / m));
        let density = self
            .frames
            .iter()
            .map(|f| f.grid.density())
            .fold(0.0, f64::max);
        let odds = 1.0 / (2.0 * std::f64::consts::PI * sigma_sq * density);
        let limit_sq = sigma_sq * (2.0 * odds.max(1.0).ln()).clamp(2.0 * 2.0, 3.0 * 3.0);
        let tolerance = self.matcher.tolerance;
        self.acceptance = limit_sq.sqrt().clamp(tolerance / 10.0, tolerance);
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

    /// Step 4: best-first selection of groups of three or more.
    fn select(&mut self, groups: CandidateGroups) {
        let count = self.frames.len();
        // Re-trim every candidate to the acceptance threshold (those within
        // it already stand as they are), then order.
        let mut ranked: Vec<(u8, f64, usize)> = Vec::with_capacity(groups.sizes.len());
        let mut members = groups.members;
        let limit = self.acceptance;
        for g in 0..groups.sizes.len() {
            if groups.largest[g] <= limit {
                ranked.push((groups.sizes[g], groups.spreads[g], g));
                continue;
            }
            let group = &mut members[g * count..(g + 1) * count];
            if let Some(fit) = self.trim(group, limit, |_| false) {
                let size = group.iter().filter(|&&m| m != NONE).count() as u8;
                ranked.push((size, fit.spread, g));
            }
        }
        ranked.sort_unstable_by(|x, y| y.0.cmp(&x.0).then(x.1.total_cmp(&y.1)));
        for (_, _, g) in ranked {
            let group = &members[g * count..(g + 1) * count];
            let free = group
                .iter()
                .enumerate()
                .all(|(k, &m)| m == NONE || !self.used[k][m as usize]);
            if free {
                self.keep(group);
            }
        }
    }

    /// The sum of squared misses of a group's rays (px^2).
    fn cost(&self, members: &[u32]) -> f64 {
        let size = members.iter().filter(|&&m| m != NONE).count() as f64;
        self.fit(members, |_| false)
            .map_or(f64::INFINITY, |f| f.spread * f.spread * size)
    }

    /// Exchanges of targets between accepted groups (and with unused
    /// targets) where that lowers their summed squared misses.
    ///
    /// Best-first selection decides two groups that compete for two nearly
    /// coincident targets by the first group alone; where two particles'
    /// images nearly coincide in one camera, that gives each the other's
    /// target about as often as not. Comparing both assignments at once
    /// settles it by all the evidence.
    fn improve(&mut self) {
        self.pencil_grids.fill_with(|| None);
        let count = self.frames.len();
        let radius = 2.0 * self.acceptance;
        let radius_sq = radius * radius;
        let neighbours = |k: usize, t: usize, out: &mut Vec<u32>| {
            let frame = &self.frames[k];
            let position = frame.position(t);
            let margin = Vector2::repeat(radius);
            frame.grid.visit(position - margin, position + margin, |c| {
                if c != t && (frame.position(c) - position).norm_squared() <= radius_sq {
                    out.push(c as u32);
                }
            });
        };
        // Most targets have no other within the radius. Found in one pass
        // in memory order, they are skipped below without a search.
        let mut nearby = Vec::new();
        let crowded: Vec<Vec<bool>> = (0..count)
            .map(|k| {
                (0..self.frames[k].sightings.len())
                    .map(|t| {
                        nearby.clear();
                        neighbours(k, t, &mut nearby);
                        !nearby.is_empty()
                    })
                    .collect()
            })
            .collect();
        let mut p_alternative = vec![NONE; count];
        let mut q_alternative = vec![NONE; count];
        for p in 0..self.accepted.len() / count {
            for k in 0..count {
                let t = self.group(p)[k];
                if t == NONE || !crowded[k][t as usize] {
                    continue;
                }
                nearby.clear();
                neighbours(k, t as usize, &mut nearby);
                for &other in &nearby {
                    let q = self.owner[k][other as usize];
                    if q as usize == p {
                        continue;
                    }
                    p_alternative.copy_from_slice(self.group(p));
                    p_alternative[k] = other;
                    let p_cost = self.cost(self.group(p));
                    if q == NONE {
                        if self.cost(&p_alternative) < p_cost {
                            self.used[k][t as usize] = false;
                            self.owner[k][t as usize] = NONE;
                            self.used[k][other as usize] = true;
                            self.owner[k][other as usize] = p as u32;
                            self.accepted[p * count..(p + 1) * count]
                                .copy_from_slice(&p_alternative);
                            break;
                        }
                        continue;
                    }
                    let q = q as usize;
                    q_alternative.copy_from_slice(self.group(q));
                    q_alternative[k] = t;
                    let before = p_cost + self.cost(self.group(q));
                    if self.cost(&p_alternative) + self.cost(&q_alternative) < before {
                        self.owner[k][t as usize] = q as u32;
                        self.owner[k][other as usize] = p as u32;
                        self.accepted[p * count..(p + 1) * count].copy_from_slice(&p_alternative);
                        self.accepted[q * count..(q + 1) * count].copy_from_slice(&q_alternative);
                        break;
                    }
                }
            }
        }
    }

    /// The particles: every accepted group's least-squares intersection.
    fn finish(&self) -> Vec<Particle> {
        let mut observations = Vec::with_capacity(self.frames.len());
        self.accepted
            .chunks_exact(self.frames.len())
            .filter_map(|members| self.intersect(members, &mut observations))
            .collect()
    }

    /// Step 5: unambiguous pairs among the unused targets.
    fn pairs(&mut self) {
        let count = self.frames.len();
        let mut candidates: Vec<(f64, [(usize, u32); 2])> = Vec::new();
        let mut found = Vec::with_capacity(4);
        let mut members = vec![NONE; count];
        for i in 0..count {
            for j in i + 1..count {
                for a in 0..self.frames[i].targets.len() {
                    if self.used[i][a] {
                        continue;
                    }
                    found.clear();
                    self.band(i, a, j, |b| found.push(b));
                    let [b] = found[..] else {
                        continue;
                    };
                    found.clear();
                    self.band(j, b, i, |c| found.push(c));
                    if found[..] != [a] {
                        continue;
                    }
                    members.fill(NONE);
                    members[i] = a as u32;
                    members[j] = b as u32;
                    if let Some(fit) = self.fit(&members, |_| false) {
                        if fit.largest <= self.acceptance {
                            candidates.push((fit.spread, [(i, a as u32), (j, b as u32)]));
                        }
                    }
                }
            }
        }
        candidates.sort_unstable_by(|x, y| x.0.total_cmp(&y.0));
        for (_, pair) in candidates {
            if pair.iter().any(|&(k, t)| self.used[k][t as usize]) {
                continue;
            }
            members.fill(NONE);
            for (k, t) in pair {
                members[k] = t;
            }
            self.keep(&members);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::{self, MatchScore, RigSpec, TargetFrame};

    struct Scene {
        cameras: Vec<Camera>,
        points: Vec<Point3<f64>>,
        frame: TargetFrame,
        volume: Volume,
    }

    fn scene(cameras: usize, particles: usize, noise: f64, drop: f64, seed: u64) -> Scene {
        let spec = RigSpec::convergent(cameras);
        let rig = spec.build().unwrap();
        let mut rng = simulate::rng(seed);
        let points = simulate::particles(&spec.volume, particles, &mut rng);
        let frame = simulate::target_frame(&rig, &points, noise, drop, &mut rng);
        Scene {
            cameras: rig,
            points,
            frame,
            volume: spec.volume,
        }
    }

    fn run(scene: &Scene, tolerance: f64, min_cameras: usize) -> (Vec<Particle>, MatchScore) {
        let parameters = MatchingParameters {
            tolerance,
            volume: Some(scene.volume),
            min_cameras,
            similarity: None,
        };
        let particles = Matcher::new(&scene.cameras, &parameters)
            .unwrap()
            .match_frame(&scene.frame.targets)
            .unwrap();
        let score = MatchScore::of(&particles, &scene.frame, &scene.points);
        (particles, score)
    }

    #[test]
    fn noise_free_particles_are_exact() {
        // Every correct particle within 1 um of the truth; the tolerance is
        // what any real frame would need (0.5 px), not tuned to noise-free data.
        let scene = scene(4, 2000, 0.0, 0.1, 11);
        let (_, score) = run(&scene, 0.5, 2);
        assert!(score.max_error < 1e-3, "{score:?}");
        // At least as complete as the 10% losses allow: a particle needs two
        // of its four images (99.6% of them have that).
        assert!(score.correct as f64 > 0.98 * 2000.0, "{score:?}");
    }

    #[test]
    fn reported_sigmas_match_the_errors() {
        // The RMS error per axis over the mean reported sigma: the adjustment's
        // a posteriori sigmas must describe the actual scatter.
        let scene = scene(4, 3000, 0.1, 0.1, 12);
        let (_, score) = run(&scene, 0.5, 2);
        let ratio = score.rms_error / score.mean_sigma;
        assert!((0.8..=1.25).contains(&ratio), "ratio {ratio}: {score:?}");
    }

    #[test]
    fn three_cameras_find_nearly_all_particles_as_triplets() {
        let scene = scene(3, 2000, 0.1, 0.0, 13);
        let (_, score) = run(&scene, 0.5, 2);
        assert!(score.by_cameras[3] as f64 >= 0.99 * 2000.0, "{score:?}");
        assert!(score.ghosts <= 10, "{score:?}");
    }

    #[test]
    fn two_four_and_six_cameras_work() {
        for (cameras, particles) in [(4, 2000), (6, 2000)] {
            let scene = scene(cameras, particles, 0.1, 0.0, 14);
            let (found, score) = run(&scene, 0.5, 2);
            assert!(
                score.correct as f64 >= 0.99 * particles as f64,
                "{cameras} cameras: {score:?}"
            );
            assert!(
                score.ghosts * 100 <= particles,
                "{cameras} cameras: {score:?}"
            );
            let full = found.iter().filter(|p| p.camera_count() == cameras).count();
            assert!(
                full as f64 >= 0.95 * particles as f64,
                "{cameras} cameras: {full} seen by all"
            );
        }
    }

    #[test]
    fn two_cameras_find_the_unambiguous_pairs() {
        // With two cameras only a pair whose targets are each other's single
        // candidate may be accepted. Count those among the true pairs with
        // the matcher's own bands; each is lost only if its miss exceeds the
        // 3-sigma acceptance (1.1%). Of the ~200 here, at least 97% (four
        // binomial standard deviations, 0.7% each, below 98.9%).
        let scene = scene(2, 300, 0.1, 0.0, 14);
        let (found, score) = run(&scene, 0.5, 2);
        assert!(score.ghosts <= 3, "{score:?}");
        let parameters = MatchingParameters {
            tolerance: 0.5,
            volume: Some(scene.volume),
            ..MatchingParameters::default()
        };
        let matcher = Matcher::new(&scene.cameras, &parameters).unwrap();
        let frames: Vec<CameraFrame> = matcher
            .cameras
            .iter()
            .zip(&scene.frame.targets)
            .map(|(camera, targets)| CameraFrame::new(camera, targets, 0.5))
            .collect();
        let mut search = Search::new(&matcher, &frames);
        // Sorted index of each particle's target per camera.
        let sorted = |c: usize, j: usize| {
            frames[c]
                .original
                .iter()
                .position(|&o| scene.frame.truth[c][o as usize] == j)
                .unwrap()
        };
        let mut unambiguous = Vec::new();
        for j in 0..scene.points.len() {
            let (a, b) = (sorted(0, j), sorted(1, j));
            let (mut forward, mut back) = (Vec::new(), Vec::new());
            search.band(0, a, 1, |t| forward.push(t));
            search.band(1, b, 0, |t| back.push(t));
            if forward == [b] && back == [a] {
                unambiguous.push(j);
            }
        }
        let found_pairs = unambiguous
            .iter()
            .filter(|&&j| {
                found.iter().any(|p| {
                    p.targets
                        .iter()
                        .enumerate()
                        .all(|(c, t)| t.is_some_and(|t| scene.frame.truth[c][t] == j))
                })
            })
            .count();
        assert!(
            unambiguous.len() >= 100,
            "{} unambiguous",
            unambiguous.len()
        );
        assert!(
            found_pairs as f64 >= 0.97 * unambiguous.len() as f64,
            "{found_pairs} of {} unambiguous pairs found",
            unambiguous.len()
        );
    }

    /// Hides every tenth particle in one of the four cameras (in turn) and
    /// counts how many of those are found from their three other images.
    fn hidden_found_from_three(noise: f64) -> usize {
        let scene = scene(4, 1000, noise, 0.0, 15);
        let mut frame = scene.frame.clone();
        for j in (0..scene.points.len()).step_by(10) {
            let camera = (j / 10) % 4;
            let index = frame.truth[camera].iter().position(|&p| p == j).unwrap();
            frame.truth[camera].remove(index);
            frame.targets[camera].remove(index);
        }
        let hidden = Scene { frame, ..scene };
        let (found, _) = run(&hidden, 0.5, 3);
        (0..hidden.points.len())
            .step_by(10)
            .filter(|&j| {
                found.iter().any(|p| {
                    p.camera_count() == 3
                        && p.targets
                            .iter()
                            .enumerate()
                            .all(|(c, t)| t.is_none_or(|t| hidden.frame.truth[c][t] == j))
                })
            })
            .count()
    }

    #[test]
    fn a_particle_hidden_in_one_of_four_images_is_found_from_three() {
        // Without noise, every one.
        assert_eq!(hidden_found_from_three(0.0), 100);
        // With noise, each of the three members must miss by at most the
        // 3-sigma acceptance (see estimate_noise): a triplet survives with
        // probability (1 - exp(-4.5))^3 = 0.967; of 100, at least 89 (four
        // binomial standard deviations, 1.8 each, below the expected 96.7).
        let found = hidden_found_from_three(0.1);
        assert!(found >= 89, "{found} of 100");
    }

    #[test]
    fn empty_frames_give_no_particles() {
        let scene = scene(4, 10, 0.1, 0.0, 16);
        let matcher = Matcher::new(&scene.cameras, &MatchingParameters::default()).unwrap();
        assert!(matcher
            .match_frame(&vec![Vec::new(); 4])
            .unwrap()
            .is_empty());
        let mut one_empty = scene.frame.targets.clone();
        one_empty[2].clear();
        assert!(matcher.match_frame(&one_empty).is_ok());
    }

    #[test]
    fn bad_parameters_and_input_are_errors() {
        let scene = scene(4, 10, 0.1, 0.0, 17);
        let with = |f: &dyn Fn(&mut MatchingParameters)| {
            let mut parameters = MatchingParameters {
                volume: Some(scene.volume),
                ..MatchingParameters::default()
            };
            f(&mut parameters);
            Matcher::new(&scene.cameras, &parameters).map(|_| ())
        };
        assert_eq!(
            with(&|p| p.tolerance = -1.0),
            Err(MatchError::Tolerance(-1.0))
        );
        assert!(matches!(
            with(&|p| p.tolerance = f64::NAN),
            Err(MatchError::Tolerance(_))
        ));
        assert!(matches!(
            with(&|p| p.min_cameras = 5),
            Err(MatchError::MinCameras { min: 5, cameras: 4 })
        ));
        let flat = Volume {
            min: Point3::new(0.0, 0.0, 0.0),
            max: Point3::new(10.0, 10.0, 0.0),
        };
        assert!(matches!(
            with(&|p| p.volume = Some(flat)),
            Err(MatchError::EmptyVolume(_))
        ));
        let matcher = Matcher::new(&scene.cameras, &MatchingParameters::default()).unwrap();
        assert_eq!(
            matcher.match_frame(&scene.frame.targets[..3]),
            Err(MatchError::CameraCount {
                targets: 3,
                cameras: 4
            })
        );
        let mut nan = scene.frame.targets.clone();
        nan[1][0].x = f64::NAN;
        assert_eq!(
            matcher.match_frame(&nan),
            Err(MatchError::InvalidTarget {
                camera: 1,
                index: 0
            })
        );
    }

    #[test]
    fn default_volume_covers_the_simulated_volume() {
        // The simulator aims its cameras at the volume's centre, so their
        // axes meet there and the default volume must hold nearly all of it.
        let spec = RigSpec::convergent(4);
        let volume = default_volume(&spec.build().unwrap()).unwrap();
        assert!(
            (volume.centre() - spec.volume.centre()).norm() < 1e-6,
            "{volume:?}"
        );
        let points = simulate::particles(&spec.volume, 1000, &mut simulate::rng(18));
        let inside = points.iter().filter(|p| volume.contains(p)).count();
        assert!(inside >= 900, "{inside} of 1000 in {volume:?}");
    }

    /// The distance to a parabola by brute force: the best of 2001 samples,
    /// refined by ternary search between its neighbours.
    fn brute_force_distance(parabola: &Parabola, p: &Point2<f64>) -> f64 {
        let distance = |u: f64| (parabola.at(u) - p).norm();
        let best = (0..=2000)
            .map(|i| f64::from(i) / 2000.0)
            .min_by(|x, y| distance(*x).total_cmp(&distance(*y)))
            .unwrap();
        let (mut lo, mut hi) = ((best - 5e-4).max(0.0), (best + 5e-4).min(1.0));
        for _ in 0..100 {
            let (m1, m2) = (lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0);
            if distance(m1) <= distance(m2) {
                hi = m2;
            } else {
                lo = m1;
            }
        }
        distance((lo + hi) / 2.0)
    }

    proptest::proptest! {
        /// `within` decides exactly as the distance does, for parabolas
        /// bent as epipolar curves are (a bend up to a fortieth of the
        /// length; the simulator's curves bend about a hundredth) and
        /// points across and beyond their ends.
        #[test]
        fn parabola_within_agrees_with_the_distance(
            length in 1.0..800.0f64,
            heading in 0.0..std::f64::consts::TAU,
            bend in -0.1..0.1f64,
            skew in -0.05..0.05f64,
            along in -0.2..1.2f64,
            across in -4.0..4.0f64,
            limit in 0.01..2.0f64,
        ) {
            let direction = Vector2::new(heading.cos(), heading.sin());
            let normal = Vector2::new(-direction.y, direction.x);
            let a = Point2::new(300.0, 200.0);
            let end = a + direction * length;
            let middle = nalgebra::center(&a, &end)
                + (normal * bend + direction * skew) * length / 4.0;
            let parabola = Parabola::through(a, middle, end);
            let p = parabola.at(along.clamp(0.0, 1.0))
                + direction * (along - along.clamp(0.0, 1.0)) * length
                + normal * across;
            let distance = brute_force_distance(&parabola, &p);
            let within = parabola.within(&p, limit * limit);
            if distance < limit - 1e-6 {
                proptest::prop_assert!(within, "distance {distance} < limit {limit}");
            }
            if distance > limit + 1e-6 {
                proptest::prop_assert!(!within, "distance {distance} > limit {limit}");
            }
        }
    }

    /// The traced curves stay within a tenth of the tolerance of the exact
    /// projections, for rays between the sampled ones and for tolerances
    /// tight enough that one parabola per curve no longer does.
    #[test]
    fn epipolar_curves_stay_within_a_tenth_of_the_tolerance() {
        let spec = RigSpec::convergent(4);
        let cameras: Vec<Camera> = spec.build().unwrap();
        let volume = spec.volume;
        let mut most_parts = 0;
        for tolerance in [0.5, 0.01] {
            for (i, k) in (0..4).flat_map(|i| (0..4).map(move |k| (i, k))) {
                if i == k {
                    continue;
                }
                let geometry =
                    EpipolarGeometry::sample(&cameras, &volume, (i, k), PARABOLA_SHARE * tolerance);
                most_parts = most_parts.max(geometry.parts);
                let sensor = cameras[i].sensor();
                let mut curve = EpipolarCurve::default();
                // Pixels halfway between the sampled ones (12 x 12 grid).
                for (row, column) in (0..12).flat_map(|r| (0..12).map(move |c| (r, c))) {
                    let pixel = Point2::new(
                        f64::from(sensor.width) * (column as f64 + 0.5) / 12.0,
                        f64::from(sensor.height) * (row as f64 + 0.5) / 12.0,
                    );
                    let ray = cameras[i].ray(pixel).unwrap();
                    let Some((near, far)) = clip(&ray, &volume) else {
                        continue;
                    };
                    assert!(curve.trace(&cameras[k], &ray, (near, far), geometry.parts));
                    for step in 0..=100 {
                        let t = (near + (far - near) * f64::from(step) / 100.0).min(far);
                        let exact = cameras[k].project(&ray.at(t)).unwrap();
                        let error = (curve.at(t).unwrap() - exact).norm();
                        assert!(
                            error <= tolerance / 10.0,
                            "pair ({i}, {k}), tolerance {tolerance}: {error} px off"
                        );
                        assert!(curve.within(&exact, error * error + 1e-18));
                    }
                }
            }
        }
        assert!(most_parts > 1, "no pair needed more than one parabola");
    }
}
