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
}

/// A camera's refracting geometry, precomputed from its [`Media`] and position.
#[derive(Clone, Debug, PartialEq)]
pub struct MediaGeometry {
    /// Unit normal of the walls, from the object medium towards the camera.
    normal: Vector3<f64>,
    /// Layers from the camera outward: air, walls (outermost first), object.
    layers: Vec<Layer>,
}

/// Largest number of Newton steps of the refraction solve; a safeguard only
/// (it converges in 3..6).
const MAX_REFRACTION_ITERATIONS: usize = 100;

/// The solved ray through the layers for one object point.
#[derive(Clone, Copy, Debug)]
struct RefractedPath {
    /// sin and cos of the angle of the ray in air to the wall normal.
    sin_air: f64,
    cos_air: f64,
    /// d(beta_air)/dq, with q = tan(beta_ref).
    d_beta_air_dq: f64,
    /// d(sum h_i tan beta_i)/dq at the solution.
    d_radial_dq: f64,
    /// tan of the angle in the layer that contains the point.
    tan_last: f64,
    /// n_ref / n_air.
    ref_over_air: f64,
}

impl MediaGeometry {
    /// Validates the media for a camera at `camera` and precomputes its
    /// layers; `Ok(None)` when all indices are equal (straight rays).
    pub fn new(media: &Media, camera: &Vector3<f64>) -> Result<Option<MediaGeometry>, InvalidCamera> {
        let positive = |field: String, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(InvalidCamera::new(field, format!("must be positive, got {value}")))
            }
        };
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
        layers.push(Layer {
            n: media.n_air,
            start: 0.0,
            end: air_height,
        });
        let mut start = air_height;
        // A wall of zero thickness (OpenPTV's way to say "no wall") bends no ray.
        for wall in media.walls.iter().rev().filter(|w| w.thickness > 0.0) {
            layers.push(Layer {
                n: wall.n,
                start,
                end: start + wall.thickness,
            });
            start += wall.thickness;
        }
        layers.push(Layer {
            n: media.n_object,
            start: camera_height,
            end: f64::INFINITY,
        });
        Ok(Some(MediaGeometry { normal, layers }))
    }

    /// Unit normal of the walls, from the object medium towards the camera.
    pub fn normal(&self) -> &Vector3<f64> {
        &self.normal
    }

    /// Solves `sum_i h_i tan(beta_i) = radial` for the layers up to `depth`
    /// (distance of the point from the camera along the inward normal).
    fn solve(&self, radial: f64, depth: f64) -> RefractedPath {
        let layers = self.layers_to(depth);
        // Reference layer: the lowest index on the path; every other layer's
        // tan(beta) stays bounded as q grows.
        let n_ref = layers
            .clone()
            .map(|(layer, _)| layer.n)
            .fold(f64::INFINITY, f64::min);
        let n_air = self.layers[0].n;
        let ref_over_air = n_ref / n_air;

        // sum h_i tan(beta_i(q)) and its derivative, with sin(beta_i) =
        // (n_ref / n_i) sin(beta_ref), q = tan(beta_ref).
        let radial_of = |q: f64| {
            let inv = 1.0 / (1.0 + q * q).sqrt();
            let sin_ref = q * inv;
            let cos3_ref = inv * inv * inv;
            let mut value = 0.0;
            let mut slope = 0.0;
            let mut tan_last = 0.0;
            for (layer, height) in layers.clone() {
                let k = n_ref / layer.n;
                let s = k * sin_ref;
                let cos2 = 1.0 - s * s;
                let cos = cos2.sqrt();
                tan_last = s / cos;
                value += height * tan_last;
                slope += height * k * cos3_ref / (cos2 * cos);
            }
            (value, slope, tan_last)
        };

        let mut q = 0.0;
        let (mut value, mut slope, mut tan_last) = radial_of(0.0);
        if radial > 0.0 {
            // Paraxial solution: tan(beta_i) <= (n_ref/n_i) q for n_i >= n_ref,
            // so it never overshoots and brackets the root from below.
            let mut lo = radial / slope;
            // Layers of the reference index alone reach `radial` at this q.
            let ref_height: f64 = layers
                .clone()
                .filter(|(layer, _)| layer.n == n_ref)
                .map(|(_, h)| h)
                .sum();
            let mut hi = radial / ref_height;
            q = lo;
            for _ in 0..MAX_REFRACTION_ITERATIONS {
                (value, slope, tan_last) = radial_of(q);
                let residual = value - radial;
                if residual > 0.0 {
                    hi = q;
                } else {
                    lo = q;
                }
                let mut next = q - residual / slope;
                if !(next > lo && next < hi) {
                    next = 0.5 * (lo + hi);
                }
                let step = next - q;
                q = next;
                if step.abs() <= 1e-15 * q || hi - lo <= 1e-15 * hi {
                    (value, slope, tan_last) = radial_of(q);
                    break;
                }
            }
        }
        let _ = value;
        let inv = 1.0 / (1.0 + q * q).sqrt();
        let sin_air = ref_over_air * q * inv;
        let cos_air = (1.0 - sin_air * sin_air).sqrt();
        RefractedPath {
            sin_air,
            cos_air,
            d_beta_air_dq: ref_over_air * inv * inv * inv / cos_air,
            d_radial_dq: slope,
            tan_last,
            ref_over_air,
        }
    }

    /// The layers between the camera and a point at `depth`, with the height
    /// of the path in each.
    fn layers_to(&self, depth: f64) -> impl Iterator<Item = (&Layer, f64)> + Clone {
        self.layers
            .iter()
            .take_while(move |layer| layer.start < depth)
            .map(move |layer| (layer, depth.min(layer.end) - layer.start))
    }

    /// The radial unit vector and distance of a point from the camera's
    /// nadir line, and its depth along the inward normal.
    fn polar(&self, camera: &Point3<f64>, point: &Point3<f64>) -> Result<(Vector3<f64>, f64, f64), ProjectionError> {
        let rel = point - camera;
        let depth = -rel.dot(&self.normal);
        if depth <= 0.0 {
            return Err(ProjectionError::AwayFromWall);
        }
        let radial = rel + self.normal * depth;
        Ok((radial, radial.norm(), depth))
    }

    /// Unit direction, in air from the projective centre, of the ray that
    /// reaches `point` through the layers.
    pub fn air_direction(&self, camera: &Point3<f64>, point: &Point3<f64>) -> Result<Vector3<f64>, ProjectionError> {
        let (radial, r, depth) = self.polar(camera, point)?;
        let path = self.solve(r, depth);
        if r > 0.0 {
            Ok(radial * (path.sin_air / r) - self.normal * path.cos_air)
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
        // meaningless; use the limit r -> 0 (sin_air / r -> k / f'(0)).
        if r <= 1e-9 * depth {
            let scale = path.ref_over_air / path.d_radial_dq;
            let direction = radial * scale - n * path.cos_air;
            return Ok(((direction).normalize(), tangential_projector * scale));
        }
        let u = radial / r;
        let direction = u * path.sin_air - n * path.cos_air;
        // Moving the point across u turns the ray's plane (factor sin/r);
        // along u or the normal changes q by (dr - tan_last d depth) / f'(q).
        let turn = (tangential_projector - u * u.transpose()) * (path.sin_air / r);
        let d_direction_dq = (u * path.cos_air + n * path.sin_air) * path.d_beta_air_dq;
        let dq_dpoint = (u + n * path.tan_last).transpose() / path.d_radial_dq;
        Ok((direction, turn + d_direction_dq * dq_dpoint))
    }

    /// Snell's law through every layer (Eq. 13-17): the ray in the object
    /// medium for a unit `direction` in air from the projective centre.
    pub fn trace(&self, camera: &Point3<f64>, direction: &Vector3<f64>) -> Result<Ray, ProjectionError> {
        let n = &self.normal;
        let cos_air = -direction.dot(n);
        if cos_air <= 1e-12 {
            return Err(ProjectionError::NoRefractedRay);
        }
        let tangential = direction + n * cos_air;
        let sin_air = tangential.norm();
        let u = if sin_air > 0.0 { tangential / sin_air } else { Vector3::zeros() };
        // Snell's invariant n sin(beta), Eq. (7).
        let invariant = self.layers[0].n * sin_air;
        let mut origin = *camera;
        let (object, crossed) = self.layers.split_last().expect("air and object layers exist");
        for layer in crossed {
            let s = invariant / layer.n;
            if s >= 1.0 {
                return Err(ProjectionError::NoRefractedRay);
            }
            let tan = s / (1.0 - s * s).sqrt();
            origin += (u * tan - n) * (layer.end - layer.start);
        }
        let s = invariant / object.n;
        if s >= 1.0 {
            return Err(ProjectionError::NoRefractedRay);
        }
        Ok(Ray {
            origin,
            direction: u * s - n * (1.0 - s * s).sqrt(),
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
    fn forward_solution_lies_on_the_traced_ray() {
        let camera = Point3::new(120.0, -40.0, 600.0);
        let media = water_tank(
            vec![
                Wall { n: 1.49, thickness: 10.0 },
                Wall { n: 1.0, thickness: 3.0 },
                Wall { n: 1.52, thickness: 6.0 },
            ],
            Vector3::new(8.0, -5.0, 130.0),
        );
        let geometry = MediaGeometry::new(&media, &camera.coords).unwrap().unwrap();
        for &(x, y, z) in &[(0.0, 0.0, 0.0), (-60.0, 40.0, -30.0), (50.0, -50.0, 80.0), (120.0, -40.0, -200.0)] {
            let point = Point3::new(x, y, z);
            let miss = miss_distance(&geometry, &camera, &point);
            assert!(miss < 1e-10, "{point}: {miss}");
        }
    }

    #[test]
    fn points_between_camera_and_water_use_the_truncated_path() {
        let camera = Point3::new(0.0, 0.0, 500.0);
        let media = water_tank(vec![Wall { n: 1.5, thickness: 10.0 }], Vector3::new(0.0, 0.0, 100.0));
        let geometry = MediaGeometry::new(&media, &camera.coords).unwrap().unwrap();
        // In air: a straight line.
        let in_air = Point3::new(30.0, 40.0, 200.0);
        let d = geometry.air_direction(&camera, &in_air).unwrap();
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
            vec![Wall { n: 1.47, thickness: 12.0 }, Wall { n: 1.6, thickness: 2.0 }],
            Vector3::new(3.0, 4.0, 70.0),
        );
        let geometry = MediaGeometry::new(&media, &camera.coords).unwrap().unwrap();
        for point in [Point3::new(20.0, -10.0, -15.0), Point3::new(-80.0 + 1e-12, 30.0, -15.0)] {
            let (_, jac) = geometry.air_direction_with_jacobian(&camera, &point).unwrap();
            let h = 1e-5;
            for k in 0..3 {
                let mut step = Vector3::zeros();
                step[k] = h;
                let plus = geometry.air_direction(&camera, &(point + step)).unwrap();
                let minus = geometry.air_direction(&camera, &(point - step)).unwrap();
                let numeric = (plus - minus) / (2.0 * h);
                assert!((jac.column(k) - numeric).norm() < 1e-8, "{point} column {k}: {} vs {numeric}", jac.column(k));
            }
        }
    }

    #[test]
    fn camera_inside_the_wall_is_rejected() {
        let media = water_tank(vec![Wall { n: 1.5, thickness: 10.0 }], Vector3::new(0.0, 0.0, 100.0));
        let err = MediaGeometry::new(&media, &Vector3::new(0.0, 0.0, 105.0)).unwrap_err();
        assert_eq!(err.field, "media.glass_vector");
        let err = MediaGeometry::new(&media, &Vector3::new(0.0, 0.0, -500.0)).unwrap_err();
        assert_eq!(err.field, "media.glass_vector");
    }

    #[test]
    fn homogeneous_media_need_no_geometry() {
        assert_eq!(MediaGeometry::new(&Media::air(), &Vector3::new(0.0, 0.0, 1.0)), Ok(None));
    }
}
