//! Multimedia geometry: rays from air through plane-parallel walls into the
//! object medium (design paper, section 4.2).
//!
//! A camera looks through a stack of plane-parallel layers: air (index
//! `n_air`), then its walls from the outside in, then the object medium
//! (`n_object`, water). The planes are given as OpenPTV's *glass vector*
//! `g`: from the world origin to the water-side surface of the wall, normal
//! to it, pointing towards the camera's side. Walls are listed from the water
//! outward, the first starting at the plane of `g`. Any number of walls and
//! any orientation of `g` are supported; every camera has its own.
//!
//! Two directions are computed:
//!
//! * **Forward** ([`MediaGeometry::air_direction`]): the direction in air of
//!   the ray that reaches a given object point. Snell's law (Eq. 7) conserves
//!   `n sin(beta)` across parallel interfaces, so with heights `h_i` of the
//!   layers between camera and point and the radial distance `R` of the point
//!   from the camera's nadir, Eq. (6) generalises to
//!   `sum_i h_i tan(beta_i) = R`. The design solves it by the radial-shift
//!   iteration of Eq. (8)-(11), to a tolerance (OpenPTV: 0.001 mm in object
//!   space). We solve the same equation exactly, by safeguarded Newton
//!   iteration on `q = tan(beta_ref)` (the angle in the layer of lowest index)
//!   from the paraxial solution, which is a proven lower bound; it converges
//!   to machine precision in a few steps. The radially shifted point of
//!   Eq. (12) lies on the resulting air ray, so collinearity with it (Eq. 2)
//!   is collinearity with this direction.
//! * **Backward** ([`MediaGeometry::trace`]): the ray in the object medium for
//!   a direction in air, Eq. (13)-(17), in vector form for any plane.
//!
//! [`MediaGeometry::air_direction_with_jacobian`] also differentiates the
//! forward map (implicit differentiation of Eq. 6), which the least-squares
//! intersection and resection need.

use nalgebra::{Matrix3, Point3, Vector3};
use serde::{Deserialize, Serialize};

use super::camera::{InvalidCamera, ProjectionError, Ray};
use super::volume::Volume;

/// One plane-parallel wall.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Wall {
    /// Refractive index.
    pub n: f64,
    /// Thickness (mm).
    pub thickness: f64,
}

/// The optical media between a camera and the particles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Media {
    /// Refractive index on the camera's side (air).
    pub n_air: f64,
    /// Walls, listed from the object medium outward.
    pub walls: Vec<Wall>,
    /// Refractive index of the object medium (water).
    pub n_object: f64,
    /// From the world origin to the object-side surface of the innermost
    /// wall, normal to it, towards the camera (mm).
    pub glass_vector: Vector3<f64>,
}

impl Media {
    /// A camera in air looking at particles in air: no refraction.
    pub fn air() -> Media {
        Media {
            n_air: 1.0,
            walls: Vec::new(),
            n_object: 1.0,
            glass_vector: Vector3::zeros(),
        }
    }

    /// Whether every medium has the same index, so that rays run straight.
    pub fn is_homogeneous(&self) -> bool {
        self.n_object == self.n_air && self.walls.iter().all(|w| w.n == self.n_air)
    }
}

/// One layer of the optical path, as seen from the camera.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Layer {
    /// Refractive index.
    n: f64,
    /// Distance from the camera's projective centre, along the wall normal,
    /// where the layer starts (mm).
    start: f64,
    /// Where it ends (`f64::INFINITY` for the object medium).
    end: f64,
    /// The lowest index of this layer and all before it: the reference
    /// index of a path that ends in this layer.
    n_ref: f64,
}

/// A camera's refracting geometry, precomputed from its [`Media`] and position.
#[derive(Clone, Debug, PartialEq)]
pub struct MediaGeometry {
    /// Unit normal of the walls, from the object medium towards the camera.
    normal: Vector3<f64>,
    /// Layers from the camera outward: air, walls (outermost first), object.
    layers: Vec<Layer>,
    /// Optional starting values of the solve over an observation volume.
    table: Option<RefractionTable>,
}

/// Starting values of the refraction solve tabulated over a region: the
/// accelerator that OpenPTV calls `mmlut`.
///
/// OpenPTV interpolates its table and stops there, so its error is that of
/// the interpolation. Here the interpolated `q` only starts one Newton step;
/// the step's size measures the start's error, and by Newton's quadratic
/// convergence the error left after it is of the order of the step squared
/// (relative to `q`; this function is close to linear in `q`, so the
/// constant is of order one). A step above [`TABLE_STEP_LIMIT`] (a point
/// outside the tabulated region, or near a layer boundary where the
/// interpolation is poor) is followed by another, up to three, before the
/// full iteration takes over. The error of a
/// tabulated projection is therefore below about 1e-12 relative in the ray
/// angle, 1e-11 mm on the image plane, and the tests check it against the
/// exact solution at 1e-9 mm.
#[derive(Clone, Debug, PartialEq)]
struct RefractionTable {
    /// Radial distance of the first column and the spacing (mm).
    radial_min: f64,
    radial_step: f64,
    /// Depth of the first row and the spacing (mm).
    depth_min: f64,
    depth_step: f64,
    /// 1 / radial_step and 1 / depth_step.
    radial_scale: f64,
    depth_scale: f64,
    /// Nodes along radial distance and depth.
    radial_nodes: usize,
    depth_nodes: usize,
    /// `q = tan(beta_ref)` at the nodes, row-major by depth.
    q: Vec<f64>,
}

/// Largest relative Newton step accepted after a table lookup (see [`RefractionTable`]).
const TABLE_STEP_LIMIT: f64 = 1e-6;
/// Nodes of the table along each axis: 65 x 65 x 8 bytes = 34 KB per camera,
/// built in about a millisecond, with start errors around 1e-7 relative
/// over a typical observation volume.
const TABLE_NODES: usize = 65;

impl RefractionTable {
    /// Bilinear interpolation of `q`; `None` outside the table.
    fn lookup(&self, radial: f64, depth: f64) -> Option<f64> {
        let u = (radial - self.radial_min) * self.radial_scale;
        let v = (depth - self.depth_min) * self.depth_scale;
        if !(u >= 0.0 && v >= 0.0) {
            return None;
        }
        let (i, j) = (u as usize, v as usize);
        if i + 1 >= self.radial_nodes || j + 1 >= self.depth_nodes {
            return None;
        }
        let (a, b) = (u - i as f64, v - j as f64);
        let row = j * self.radial_nodes + i;
        let next_row = row + self.radial_nodes;
        let q = &self.q;
        Some(
            (1.0 - b) * ((1.0 - a) * q[row] + a * q[row + 1])
                + b * ((1.0 - a) * q[next_row] + a * q[next_row + 1]),
        )
    }
}

/// Largest number of Newton steps of the refraction solve; a safeguard only
/// (it converges in 3..6).
const MAX_REFRACTION_ITERATIONS: usize = 100;

/// The solved ray through the layers for one object point.
#[derive(Clone, Copy, Debug)]
struct RefractedPath {
    /// tan of the angle of the ray in air to the wall normal.
    tan_air: f64,
    /// d(tan_air)/dq, with q = tan(beta_ref).
    d_tan_air_dq: f64,
    /// d(sum h_i tan beta_i)/dq at the solution.
    d_radial_dq: f64,
    /// tan of the angle in the layer that contains the point.
    tan_last: f64,
}

/// Eq. (6) generalised to the layers between the camera and one depth:
/// `sum_i h_i tan(beta_i(q))` with `sin(beta_i) = (n_ref / n_i) sin(beta_ref)`
/// and `q = tan(beta_ref)`, `n_ref` the lowest index on the path (so every
/// other layer's `tan(beta_i)` stays bounded as `q` grows).
struct PathEquation<'a> {
    /// The layers the path crosses; the last one contains the point.
    layers: &'a [Layer],
    /// Height of the path in the last layer (mm).
    last_height: f64,
    /// The reference index.
    n_ref: f64,
}

/// [`PathEquation`] evaluated at one `q`.
#[derive(Clone, Copy, Debug)]
struct PathValue {
    /// `sum_i h_i tan(beta_i)`: the radial distance the ray covers (mm).
    radial: f64,
    /// Its derivative with respect to q.
    slope: f64,
    /// tan of the angle in the layer that contains the point.
    tan_last: f64,
}

/// `tan(beta)` and its derivative with respect to `q = tan(beta_ref)` in a
/// layer where `sin(beta) = k sin(beta_ref)`, `k = n_ref / n <= 1`:
/// `tan(beta) = k q / sqrt(1 + (1 - k^2) q^2)`, `d tan(beta) / dq =
/// k / (1 + (1 - k^2) q^2)^(3/2)`. One square root and one division, the
/// layers independent of each other: the projection's critical path.
#[inline]
fn tan_in(k: f64, q: f64) -> (f64, f64) {
    if k == 1.0 {
        return (q, 1.0);
    }
    let inv = 1.0 / (1.0 + (1.0 - k * k) * q * q).sqrt();
    (k * q * inv, k * inv * inv * inv)
}

impl PathEquation<'_> {
    /// Height of the path in layer `i`.
    fn height(&self, i: usize) -> f64 {
        if i + 1 == self.layers.len() {
            self.last_height
        } else {
            self.layers[i].end - self.layers[i].start
        }
    }

    #[inline]
    fn at(&self, q: f64) -> PathValue {
        let mut value = PathValue {
            radial: 0.0,
            slope: 0.0,
            tan_last: 0.0,
        };
        for (i, layer) in self.layers.iter().enumerate() {
            let height = self.height(i);
            let (tan, slope) = tan_in(self.n_ref / layer.n, q);
            value.tan_last = tan;
            value.radial += height * tan;
            value.slope += height * slope;
        }
        value
    }

    /// Total height of the layers of the reference index.
    fn reference_height(&self) -> f64 {
        (0..self.layers.len())
            .filter(|&i| self.layers[i].n == self.n_ref)
            .map(|i| self.height(i))
            .sum()
    }
}

/// The most walls a camera may look through: 8.
///
/// A tank has one glass wall per camera; a water-filled prism against it
/// adds two more layers, a window with a coating or a second pane one or
/// two. Eight leaves margin; every projection and ray costs one Newton
/// term per layer, so the count also bounds that work.
pub const MAX_WALLS: usize = 8;

impl MediaGeometry {
    /// Validates the media for a camera at `camera` and precomputes its
    /// layers; `Ok(None)` when all indices are equal (straight rays).
    pub fn new(
        media: &Media,
        camera: &Vector3<f64>,
    ) -> Result<Option<MediaGeometry>, InvalidCamera> {
        let positive = |field: String, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(InvalidCamera::new(
                    field,
                    format!("must be positive, got {value}"),
                ))
            }
        };
        if media.walls.len() > MAX_WALLS {
            return Err(InvalidCamera::new(
                "media.walls",
                format!(
                    "{} walls are more than the limit of {MAX_WALLS} (MAX_WALLS); list the \
                     layers between the camera and the water: usually one glass wall",
                    media.walls.len()
                ),
            ));
        }
        positive("media.n_air".into(), media.n_air)?;
        positive("media.n_object".into(), media.n_object)?;
        for (i, wall) in media.walls.iter().enumerate() {
            positive(format!("media.walls[{i}].n"), wall.n)?;
            if !(wall.thickness.is_finite() && wall.thickness >= 0.0) {
                return Err(InvalidCamera::new(
                    format!("media.walls[{i}].thickness"),
                    format!("must be zero or positive, got {}", wall.thickness),
                ));
            }
        }
        for (i, v) in media.glass_vector.iter().enumerate() {
            if !v.is_finite() {
                return Err(InvalidCamera::new(
                    format!("media.glass_vector[{i}]"),
                    format!("must be a finite number, got {v}"),
                ));
            }
        }
        if media.is_homogeneous() {
            return Ok(None);
        }
        let distance = media.glass_vector.norm();
        if distance == 0.0 {
            return Err(InvalidCamera::new(
                "media.glass_vector",
                "must be non-zero when the media refract: it points from the origin to the \
                 water-side surface of the wall, towards the camera",
            ));
        }
        let normal = media.glass_vector / distance;
        let camera_height = camera.dot(&normal) - distance;
        let wall_total: f64 = media.walls.iter().map(|w| w.thickness).sum();
        let air_height = camera_height - wall_total;
        if air_height <= 0.0 {
            return Err(InvalidCamera::new(
                "media.glass_vector",
                format!(
                    "the camera must be on the air side of its wall, but its projective centre is \
                     {air_height:.3} mm from the wall's outer surface (negative: inside the wall or \
                     on the water side); the glass vector points from the origin towards the \
                     camera's side"
                ),
            ));
        }
        let mut layers = Vec::with_capacity(media.walls.len() + 2);
        let mut push = |n: f64, start: f64, end: f64| {
            let n_ref = layers.last().map_or(n, |l: &Layer| l.n_ref.min(n));
            layers.push(Layer {
                n,
                start,
                end,
                n_ref,
            });
        };
        push(media.n_air, 0.0, air_height);
        let mut start = air_height;
        // A wall of zero thickness (OpenPTV's way to say "no wall") bends no ray.
        for wall in media.walls.iter().rev().filter(|w| w.thickness > 0.0) {
            push(wall.n, start, start + wall.thickness);
            start += wall.thickness;
        }
        push(media.n_object, camera_height, f64::INFINITY);
        Ok(Some(MediaGeometry {
            normal,
            layers,
            table: None,
        }))
    }

    /// Unit normal of the walls, from the object medium towards the camera.
    pub fn normal(&self) -> &Vector3<f64> {
        &self.normal
    }

    /// Tabulates the refraction solve over `volume` for a camera at
    /// `camera` (a lookup table of starting values, see the module doc); points elsewhere are solved
    /// without it. Results stay exact to rounding either way.
    pub fn with_table(mut self, camera: &Point3<f64>, volume: &Volume) -> MediaGeometry {
        self.table = None;
        // Depth is linear in the point, so its extremes are at corners. The
        // radial distance is convex with a Lipschitz constant of 1: its
        // maximum is at a corner, and its minimum lies at most half a sample
        // cell's diagonal below the least of a sample grid.
        let (mut depth_min, mut depth_max) = (f64::INFINITY, f64::NEG_INFINITY);
        for corner in volume.corners() {
            let depth = -(corner - camera).dot(&self.normal);
            depth_min = depth_min.min(depth);
            depth_max = depth_max.max(depth);
        }
        const SAMPLES: usize = 8;
        let cell = (volume.max - volume.min) / SAMPLES as f64;
        let (mut radial_min, mut radial_max) = (f64::INFINITY, 0f64);
        for i in 0..=SAMPLES {
            for j in 0..=SAMPLES {
                for k in 0..=SAMPLES {
                    let point = volume.min
                        + cell.component_mul(&Vector3::new(i as f64, j as f64, k as f64));
                    let rel = point - camera;
                    let radial = (rel - self.normal * rel.dot(&self.normal)).norm();
                    radial_min = radial_min.min(radial);
                    radial_max = radial_max.max(radial);
                }
            }
        }
        radial_min = (radial_min - cell.norm() / 2.0).max(0.0);
        // A volume behind the camera has nothing to tabulate.
        depth_min = depth_min.max(depth_max * 1e-3);
        if !(radial_max > radial_min && depth_max > depth_min) {
            return self;
        }
        // Nodes one step beyond each edge, so the whole volume lies inside.
        let inner = (TABLE_NODES - 3) as f64;
        let radial_step = (radial_max - radial_min) / inner;
        let depth_step = (depth_max - depth_min) / inner;
        let radial_min = (radial_min - radial_step).max(0.0);
        let depth_min = depth_min - depth_step;
        let q = (0..TABLE_NODES)
            .flat_map(|j| (0..TABLE_NODES).map(move |i| (i, j)))
            .map(|(i, j)| {
                self.solve_exact(
                    radial_min + i as f64 * radial_step,
                    depth_min + j as f64 * depth_step,
                )
                .0
            })
            .collect();
        self.table = Some(RefractionTable {
            radial_min,
            radial_step,
            depth_min,
            depth_step,
            radial_scale: 1.0 / radial_step,
            depth_scale: 1.0 / depth_step,
            radial_nodes: TABLE_NODES,
            depth_nodes: TABLE_NODES,
            q,
        });
        self
    }

    /// The equation of the path to a point at `depth` (distance from the
    /// camera along the inward normal).
    #[inline]
    fn path_to(&self, depth: f64) -> PathEquation<'_> {
        // The layer that contains the point: the last one starting before it
        // (the air layer starts at 0, and depth > 0).
        let count = self
            .layers
            .iter()
            .take_while(|layer| layer.start < depth)
            .count()
            .max(1);
        let layers = &self.layers[..count];
        let last = &layers[count - 1];
        PathEquation {
            layers,
            last_height: depth.min(last.end) - last.start,
            n_ref: last.n_ref,
        }
    }

    /// Solves `sum_i h_i tan(beta_i) = radial` for a point at `depth` by
    /// safeguarded Newton iteration from the paraxial solution; returns `q`
    /// and the equation's value, slope and last tan at the final iterate.
    fn solve_exact(&self, radial: f64, depth: f64) -> (f64, PathValue) {
        let equation = self.path_to(depth);
        let mut at = equation.at(0.0);
        if radial <= 0.0 {
            return (0.0, at);
        }
        // Paraxial solution: tan(beta_i) <= (n_ref/n_i) q for n_i >= n_ref,
        // so it never overshoots and brackets the root from below.
        let mut lo = radial / at.slope;
        // Layers of the reference index alone reach `radial` at this q.
        let mut hi = radial / equation.reference_height();
        let mut q = lo;
        for _ in 0..MAX_REFRACTION_ITERATIONS {
            at = equation.at(q);
            let residual = at.radial - radial;
            if residual == 0.0 {
                break;
            }
            if residual > 0.0 {
                hi = q;
            } else {
                lo = q;
            }
            let mut next = q - residual / at.slope;
            if !(next >= lo && next <= hi) {
                next = 0.5 * (lo + hi);
            }
            let step = next - q;
            q = next;
            // Newton converges quadratically here, the error after a step
            // being about (step / q)^2 relative (the equation is close to
            // linear in q): after a relative step of 1e-7 it is at rounding.
            if step.abs() <= 1e-7 * q || hi - lo <= 1e-15 * hi {
                break;
            }
        }
        (q, at)
    }

    /// The ray to a point at `radial` distance from the camera's nadir line
    /// and `depth`: from the table and one Newton step where the table
    /// covers the point, else by [`MediaGeometry::solve_exact`].
    #[inline]
    fn solve(&self, radial: f64, depth: f64) -> RefractedPath {
        let equation = self.path_to(depth);
        let tabulated = self.table.as_ref().and_then(|table| {
            let mut q = table.lookup(radial, depth)?;
            // Usually one step; a start a little off (near the table's
            // edges) takes one or two more.
            for _ in 0..3 {
                let at = equation.at(q);
                let step = (at.radial - radial) / at.slope;
                q -= step;
                if step.abs() <= TABLE_STEP_LIMIT * q {
                    return Some((q, at));
                }
            }
            None
        });
        let (q, at) = tabulated.unwrap_or_else(|| self.solve_exact(radial, depth));
        let (tan_air, d_tan_air_dq) = tan_in(equation.n_ref / self.layers[0].n, q);
        RefractedPath {
            tan_air,
            d_tan_air_dq,
            d_radial_dq: at.slope,
            tan_last: at.tan_last,
        }
    }

    /// The radial vector of a point (from the camera's nadir line to the
    /// point, across the normal), its length, and the point's depth along
    /// the inward normal.
    fn polar(
        &self,
        camera: &Point3<f64>,
        point: &Point3<f64>,
    ) -> Result<(Vector3<f64>, f64, f64), ProjectionError> {
        let rel = point - camera;
        let depth = -rel.dot(&self.normal);
        if depth <= 0.0 {
            return Err(ProjectionError::AwayFromWall);
        }
        let radial = rel + self.normal * depth;
        Ok((radial, radial.norm(), depth))
    }

    /// The direction, in air from the projective centre, of the ray that
    /// reaches `point` through the layers, scaled to a unit component
    /// along the inward normal: `u tan(beta_air) - normal`, `u` the radial
    /// unit vector. Collinearity (Eq. 2) needs only the direction; leaving
    /// out the normalisation keeps a square root and a division off the
    /// projection's critical path.
    pub fn air_direction(
        &self,
        camera: &Point3<f64>,
        point: &Point3<f64>,
    ) -> Result<Vector3<f64>, ProjectionError> {
        let (radial, r, depth) = self.polar(camera, point)?;
        // Divided out while the solve runs, off the critical path.
        let inv_r = 1.0 / r;
        let path = self.solve(r, depth);
        if r > 0.0 {
            Ok(radial * (path.tan_air * inv_r) - self.normal)
        } else {
            Ok(-self.normal)
        }
    }

    /// [`MediaGeometry::air_direction`] and its 3x3 Jacobian with respect to `point`.
    pub fn air_direction_with_jacobian(
        &self,
        camera: &Point3<f64>,
        point: &Point3<f64>,
    ) -> Result<(Vector3<f64>, Matrix3<f64>), ProjectionError> {
        let (radial, r, depth) = self.polar(camera, point)?;
        let path = self.solve(r, depth);
        let n = &self.normal;
        let tangential_projector = Matrix3::identity() - n * n.transpose();
        // Below this radial distance the direction of u is numerically
        // meaningless; use the limit r -> 0 (tan_air / r -> tan_air'(q) / f'(q)).
        if r <= 1e-9 * depth {
            let scale = path.d_tan_air_dq / path.d_radial_dq;
            return Ok((radial * scale - n, tangential_projector * scale));
        }
        let u = radial / r;
        let direction = u * path.tan_air - n;
        // Moving the point across u turns the ray's plane (factor tan/r);
        // along u or the normal changes q by (dr - tan_last d depth) / f'(q).
        let turn = (tangential_projector - u * u.transpose()) * (path.tan_air / r);
        let d_direction_dq = u * path.d_tan_air_dq;
        let dq_dpoint = (u + n * path.tan_last).transpose() / path.d_radial_dq;
        Ok((direction, turn + d_direction_dq * dq_dpoint))
    }

    /// Snell's law through every layer (Eq. 13-17): the ray in the object
    /// medium (unit direction) for a `direction` in air from the
    /// projective centre (any length).
    ///
    /// In tangent form, as the forward solve: with `q = tan(beta_air)`,
    /// each layer's `tan(beta_i) = k q / sqrt(1 + (1 - k^2) q^2)`,
    /// `k = n_air / n_i`, and no refraction where the root's argument is
    /// not positive (`n sin(beta) >= 1`: total internal reflection).
    pub fn trace(
        &self,
        camera: &Point3<f64>,
        direction: &Vector3<f64>,
    ) -> Result<Ray, ProjectionError> {
        let n = &self.normal;
        let cos_part = -direction.dot(n);
        // Along the wall, away from it, or NaN: no ray.
        let towards_wall = cos_part > 1e-12 * direction.norm();
        if !towards_wall {
            return Err(ProjectionError::NoRefractedRay);
        }
        // The tangential part over the normal one: the radial unit vector
        // times tan(beta_air).
        let across = (direction + n * cos_part) / cos_part;
        let q_sq = across.norm_squared();
        let n_air = self.layers[0].n;
        // Per layer, tan(beta_i) / q; the air layer's is 1.
        let ratio = |layer: &Layer| -> Result<f64, ProjectionError> {
            let k = n_air / layer.n;
            let root = 1.0 + (1.0 - k * k) * q_sq;
            if root <= 0.0 {
                return Err(ProjectionError::NoRefractedRay);
            }
            Ok(k / root.sqrt())
        };
        let mut origin = *camera;
        let (object, crossed) = self
            .layers
            .split_last()
            .expect("air and object layers exist");
        for layer in crossed {
            origin += (across * ratio(layer)? - n) * (layer.end - layer.start);
        }
        Ok(Ray {
            origin,
            direction: (across * ratio(object)? - n).normalize(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn water_tank(walls: Vec<Wall>, glass: Vector3<f64>) -> Media {
        Media {
            n_air: 1.0,
            walls,
            n_object: 1.33,
            glass_vector: glass,
        }
    }

    /// Independent check of the forward solution: trace the solved air ray
    /// forward with Snell's law and measure how far it passes from the point.
    fn miss_distance(geometry: &MediaGeometry, camera: &Point3<f64>, point: &Point3<f64>) -> f64 {
        let direction = geometry.air_direction(camera, point).unwrap();
        let ray = geometry.trace(camera, &direction).unwrap();
        let rel = point - ray.origin;
        (rel - ray.direction * rel.dot(&ray.direction)).norm()
    }

    #[test]
    fn at_most_max_walls() {
        let camera = Vector3::new(0.0, 0.0, 600.0);
        let walls = |count: usize| {
            let wall = Wall {
                n: 1.49,
                thickness: 5.0,
            };
            water_tank(vec![wall; count], Vector3::new(0.0, 0.0, 100.0))
        };
        assert!(MediaGeometry::new(&walls(MAX_WALLS), &camera).is_ok());
        let error = MediaGeometry::new(&walls(MAX_WALLS + 1), &camera).unwrap_err();
        assert_eq!(error.field, "media.walls");
        assert!(
            error
                .reason
                .contains("9 walls are more than the limit of 8 (MAX_WALLS)"),
            "{error}"
        );
    }

    #[test]
    fn forward_solution_lies_on_the_traced_ray() {
        let camera = Point3::new(120.0, -40.0, 600.0);
        let media = water_tank(
            vec![
                Wall {
                    n: 1.49,
                    thickness: 10.0,
                },
                Wall {
                    n: 1.0,
                    thickness: 3.0,
                },
                Wall {
                    n: 1.52,
                    thickness: 6.0,
                },
            ],
            Vector3::new(8.0, -5.0, 130.0),
        );
        let geometry = MediaGeometry::new(&media, &camera.coords).unwrap().unwrap();
        for &(x, y, z) in &[
            (0.0, 0.0, 0.0),
            (-60.0, 40.0, -30.0),
            (50.0, -50.0, 80.0),
            (120.0, -40.0, -200.0),
        ] {
            let point = Point3::new(x, y, z);
            let miss = miss_distance(&geometry, &camera, &point);
            assert!(miss < 1e-10, "{point}: {miss}");
        }
    }

    #[test]
    fn points_between_camera_and_water_use_the_truncated_path() {
        let camera = Point3::new(0.0, 0.0, 500.0);
        let media = water_tank(
            vec![Wall {
                n: 1.5,
                thickness: 10.0,
            }],
            Vector3::new(0.0, 0.0, 100.0),
        );
        let geometry = MediaGeometry::new(&media, &camera.coords).unwrap().unwrap();
        // In air: a straight line.
        let in_air = Point3::new(30.0, 40.0, 200.0);
        let d = geometry
            .air_direction(&camera, &in_air)
            .unwrap()
            .normalize();
        assert!((d - (in_air - camera).normalize()).norm() < 1e-14);
        // Behind the camera: no ray.
        assert_eq!(
            geometry.air_direction(&camera, &Point3::new(0.0, 0.0, 600.0)),
            Err(ProjectionError::AwayFromWall)
        );
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let camera = Point3::new(-80.0, 30.0, 550.0);
        let media = water_tank(
            vec![
                Wall {
                    n: 1.47,
                    thickness: 12.0,
                },
                Wall {
                    n: 1.6,
                    thickness: 2.0,
                },
            ],
            Vector3::new(3.0, 4.0, 70.0),
        );
        let geometry = MediaGeometry::new(&media, &camera.coords).unwrap().unwrap();
        for point in [
            Point3::new(20.0, -10.0, -15.0),
            Point3::new(-80.0 + 1e-12, 30.0, -15.0),
        ] {
            let (_, jac) = geometry
                .air_direction_with_jacobian(&camera, &point)
                .unwrap();
            let h = 1e-5;
            for k in 0..3 {
                let mut step = Vector3::zeros();
                step[k] = h;
                let plus = geometry.air_direction(&camera, &(point + step)).unwrap();
                let minus = geometry.air_direction(&camera, &(point - step)).unwrap();
                let numeric = (plus - minus) / (2.0 * h);
                assert!(
                    (jac.column(k) - numeric).norm() < 1e-8,
                    "{point} column {k}: {} vs {numeric}",
                    jac.column(k)
                );
            }
        }
    }

    /// From a denser medium into a thinner one, rays beyond the critical
    /// angle are reflected: no ray in the object medium. Rays along the
    /// wall or away from it have none either.
    #[test]
    fn total_internal_reflection_gives_no_ray() {
        let media = Media {
            n_air: 1.33,
            walls: vec![Wall {
                n: 1.5,
                thickness: 5.0,
            }],
            n_object: 1.0,
            glass_vector: Vector3::new(0.0, 0.0, 100.0),
        };
        let camera = Point3::new(0.0, 0.0, 300.0);
        let geometry = MediaGeometry::new(&media, &camera.coords).unwrap().unwrap();
        // sin(beta) in the object: 1.33 sin(beta_air); critical at 48.75 deg.
        for (degrees, refracts) in [(30.0f64, true), (48.0, true), (49.5, false), (80.0, false)] {
            let angle = degrees.to_radians();
            // Any length: the direction's scale does not matter.
            let direction = Vector3::new(angle.sin(), 0.0, -angle.cos()) * 3.0;
            let ray = geometry.trace(&camera, &direction);
            assert_eq!(ray.is_ok(), refracts, "{degrees} deg: {ray:?}");
            if let Ok(ray) = ray {
                let sin_object = ray.direction.x / ray.direction.norm();
                assert!((sin_object - 1.33 * angle.sin()).abs() < 1e-12);
                assert!((ray.direction.norm() - 1.0).abs() < 1e-15);
            }
        }
        for direction in [Vector3::x(), Vector3::new(0.0, 1.0, 0.5)] {
            assert_eq!(
                geometry.trace(&camera, &direction),
                Err(ProjectionError::NoRefractedRay)
            );
        }
    }

    #[test]
    fn camera_inside_the_wall_is_rejected() {
        let media = water_tank(
            vec![Wall {
                n: 1.5,
                thickness: 10.0,
            }],
            Vector3::new(0.0, 0.0, 100.0),
        );
        let err = MediaGeometry::new(&media, &Vector3::new(0.0, 0.0, 105.0)).unwrap_err();
        assert_eq!(err.field, "media.glass_vector");
        let err = MediaGeometry::new(&media, &Vector3::new(0.0, 0.0, -500.0)).unwrap_err();
        assert_eq!(err.field, "media.glass_vector");
    }

    #[test]
    fn homogeneous_media_need_no_geometry() {
        assert_eq!(
            MediaGeometry::new(&Media::air(), &Vector3::new(0.0, 0.0, 1.0)),
            Ok(None)
        );
    }
}
