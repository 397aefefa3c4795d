//! The camera model: the collinearity condition with 16 parameters per camera.
//!
//! Implements the design paper's Eq. (1)-(2) (collinearity), Eq. (3) (Brown
//! lens distortion) and the two-parameter affine term of Eq. (5) in OpenPTV
//! 0.3's form, together with the multimedia module of [`super::media`]
//! (Eq. 6-12). Conventions follow OpenPTV exactly, so that calibrations move
//! between the two systems unchanged:
//!
//! * rotation `R = Rx(omega) * Ry(phi) * Rz(kappa)` ([`rotation_matrix`]); the
//!   camera looks along its own `-z` axis and `x = -c (Rᵀ d)_x / (Rᵀ d)_z`,
//!   `y = -c (Rᵀ d)_y / (Rᵀ d)_z`, with `d` the direction of the ray in air;
//! * "flat" image coordinates are ideal (undistorted) and relative to the
//!   principal point; distortion runs from ideal to distorted and is applied
//!   to coordinates relative to the sensor centre ([`Distortion::apply`]);
//! * metric image coordinates (mm, y up, origin at the sensor centre) map to
//!   pixels by `x_px = x / pix_x + width / 2`, `y_px = height / 2 - y / pix_y`,
//!   so the centre of the top-left pixel is at (0.5, 0.5).
//!
//! A [`CameraParameters`] value is plain data as it is stored in files; a
//! [`Camera`] is a validated one with its rotation and wall geometry
//! precomputed, and is what every computation takes.

use nalgebra::{Matrix2, Matrix2x3, Matrix3, Point2, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::media::{Media, MediaGeometry};
use super::volume::Volume;

/// The widest or tallest sensor a camera may have (px): 16,384 = 2^14.
///
/// The largest sensors in scientific and high-speed cameras are about
/// 8,000 px on a side (a 47 Mpx 8,192 x 5,760 CMOS); twice that leaves
/// margin for stitched or line-scan sensors. A sensor this wide is at most
/// 4,096 px tall, by [`MAX_SENSOR_PIXELS`].
pub const MAX_SENSOR_SIDE: u32 = 16_384;

/// The most pixels a sensor may have: 64 Mpx (2^26).
///
/// Today's largest PTV and high-speed cameras have 25..47 Mpx; 64 Mpx
/// leaves margin and bounds one decoded image at 64 MiB (8-bit) or
/// 128 MiB (16-bit), so that memory per frame is the cameras times that
/// (see `formats::image`, which refuses larger images before decoding).
pub const MAX_SENSOR_PIXELS: u64 = 1 << 26;

/// The longest camera name, in characters.
///
/// Names label cameras for people and name files (OpenPTV export writes
/// `NAME.ori`): 64 characters are plenty for `cam1` or
/// `left_top.serial-1234`, and far below any file system's 255.
pub const MAX_CAMERA_NAME_LEN: usize = 64;

/// Checks a camera name: 1..=[`MAX_CAMERA_NAME_LEN`] characters, each an
/// ASCII letter or digit, `.`, `_` or `-`, not starting with `.`. Names
/// become file names (`NAME.ori`), so path separators, `..`, NUL, spaces
/// and control characters are refused rather than escaped.
pub fn check_camera_name(name: &str) -> Result<(), InvalidCamera> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-');
    let shown = || {
        let mut s: String = name.chars().take(MAX_CAMERA_NAME_LEN).collect();
        if name.chars().count() > MAX_CAMERA_NAME_LEN {
            s.push_str("...");
        }
        format!("{s:?}")
    };
    let problem = if name.is_empty() {
        Some("is empty".to_owned())
    } else if name.len() > MAX_CAMERA_NAME_LEN {
        Some(format!(
            "is {} bytes long, more than the limit of {MAX_CAMERA_NAME_LEN}",
            name.len()
        ))
    } else if let Some(c) = name.chars().find(|&c| !allowed(c)) {
        Some(format!("contains the character {c:?}"))
    } else if name.starts_with('.') {
        Some("starts with `.`".to_owned())
    } else {
        None
    };
    match problem {
        None => Ok(()),
        Some(problem) => Err(InvalidCamera::new(
            "name",
            format!(
                "the camera name {} {problem}; a camera name is 1 to {MAX_CAMERA_NAME_LEN} \
                 characters of letters, digits, `.`, `_` and `-`, not starting with `.` \
                 (it names files), so rename the camera, e.g. `cam1`",
                shown()
            ),
        )),
    }
}

/// The image sensor: its size and pixel pitch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sensor {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Pixel pitch along x (mm).
    pub pixel_size_x: f64,
    /// Pixel pitch along y (mm).
    pub pixel_size_y: f64,
}

impl Sensor {
    /// Checks the size against the limits: each side 1..=[`MAX_SENSOR_SIDE`]
    /// pixels, and at most [`MAX_SENSOR_PIXELS`] in all.
    pub fn check_size(&self) -> Result<(), InvalidCamera> {
        for (field, side) in [
            ("image_size[0]", self.width),
            ("image_size[1]", self.height),
        ] {
            if side == 0 {
                return Err(InvalidCamera::new(field, "must be positive, got 0"));
            }
            if side > MAX_SENSOR_SIDE {
                return Err(InvalidCamera::new(
                    field,
                    format!(
                        "{side} px is more than the limit of {MAX_SENSOR_SIDE} px per sensor \
                         side (MAX_SENSOR_SIDE); give the sensor's size in pixels"
                    ),
                ));
            }
        }
        let pixels = u64::from(self.width) * u64::from(self.height);
        if pixels > MAX_SENSOR_PIXELS {
            return Err(InvalidCamera::new(
                "image_size",
                format!(
                    "a {}x{} sensor has {pixels} pixels, more than the limit of \
                     {MAX_SENSOR_PIXELS} (64 Mpx, MAX_SENSOR_PIXELS); give the sensor's size \
                     in pixels",
                    self.width, self.height
                ),
            ));
        }
        Ok(())
    }

    /// Metric image coordinates (mm, y up, origin at the sensor centre) to pixels.
    pub fn metric_to_pixel(&self, metric: Vector2<f64>) -> Point2<f64> {
        Point2::new(
            metric.x / self.pixel_size_x + f64::from(self.width) / 2.0,
            f64::from(self.height) / 2.0 - metric.y / self.pixel_size_y,
        )
    }

    /// Pixels to metric image coordinates; the inverse of [`Sensor::metric_to_pixel`].
    pub fn pixel_to_metric(&self, pixel: Point2<f64>) -> Vector2<f64> {
        Vector2::new(
            (pixel.x - f64::from(self.width) / 2.0) * self.pixel_size_x,
            (f64::from(self.height) / 2.0 - pixel.y) * self.pixel_size_y,
        )
    }

    /// Whether a pixel position lies on the sensor.
    pub fn contains(&self, pixel: Point2<f64>) -> bool {
        pixel.x >= 0.0
            && pixel.y >= 0.0
            && pixel.x <= f64::from(self.width)
            && pixel.y <= f64::from(self.height)
    }
}

/// Exterior orientation: projective centre and rotation angles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Exterior {
    /// Projective centre X0, Y0, Z0 (mm).
    pub position: Vector3<f64>,
    /// Rotation about the x axis (rad).
    pub omega: f64,
    /// Rotation about the y axis (rad).
    pub phi: f64,
    /// Rotation about the z axis (rad).
    pub kappa: f64,
}

/// Interior orientation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Interior {
    /// Principal distance c (mm).
    pub c: f64,
    /// Principal point x (mm, relative to the sensor centre).
    pub xh: f64,
    /// Principal point y (mm, relative to the sensor centre).
    pub yh: f64,
}

/// Brown lens distortion and the affine terms (OpenPTV's `ap_52`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    /// Radial distortion, r^2 term (mm^-2).
    pub k1: f64,
    /// Radial distortion, r^4 term (mm^-4).
    pub k2: f64,
    /// Radial distortion, r^6 term (mm^-6).
    pub k3: f64,
    /// Decentering distortion (mm^-1).
    pub p1: f64,
    /// Decentering distortion (mm^-1).
    pub p2: f64,
    /// Scale of the x image coordinate (1 = none).
    pub scx: f64,
    /// Shear of the image axes (rad, 0 = none).
    pub shear: f64,
}

impl Default for Distortion {
    fn default() -> Self {
        Distortion {
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            p1: 0.0,
            p2: 0.0,
            scx: 1.0,
            shear: 0.0,
        }
    }
}

/// Largest number of Newton steps when inverting the distortion.
const MAX_UNDISTORT_ITERATIONS: usize = 30;

impl Distortion {
    /// Whether this is the identity (no distortion, no affine term).
    pub fn is_identity(&self) -> bool {
        *self == Distortion::default()
    }

    /// Ideal -> distorted, both relative to the sensor centre (mm).
    ///
    /// Eq. (3) followed by the affine term in the form of OpenPTV 0.3
    /// (`distort_brown_affin` of optv 0.3.2, pinned by the rig_a golden
    /// values to 1e-15 mm): with `(x', y')` the Brown-distorted coordinates,
    /// `x'' = scx (x' - sin(she) y')` and `y'' = scx cos(she) y'`, i.e. `scx`
    /// scales both axes and `she` shears y into x.
    pub fn apply(&self, ideal: Vector2<f64>) -> Vector2<f64> {
        self.apply_with_jacobian(ideal).0
    }

    /// [`Distortion::apply`] and its 2x2 Jacobian with respect to `ideal`.
    pub fn apply_with_jacobian(&self, ideal: Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        self.distort(ideal, self.shear.sin_cos())
    }

    /// The distortion and its Jacobian, with sin and cos of the shear given
    /// (a [`Camera`] keeps them). Inlined, so callers that drop the Jacobian
    /// do not compute it.
    #[inline]
    fn distort(
        &self,
        ideal: Vector2<f64>,
        (sin_she, cos_she): (f64, f64),
    ) -> (Vector2<f64>, Matrix2<f64>) {
        let (x, y) = (ideal.x, ideal.y);
        let r2 = x * x + y * y;
        let radial = self.k1 * r2 + self.k2 * r2 * r2 + self.k3 * r2 * r2 * r2;
        // d(radial)/d(x) = radial_prime * x, likewise for y.
        let radial_prime = 2.0 * self.k1 + 4.0 * self.k2 * r2 + 6.0 * self.k3 * r2 * r2;

        let xd = x * (1.0 + radial) + self.p1 * (r2 + 2.0 * x * x) + 2.0 * self.p2 * x * y;
        let dxd_dx = 1.0 + radial + radial_prime * x * x + 6.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dxd_dy = radial_prime * x * y + 2.0 * self.p1 * y + 2.0 * self.p2 * x;

        let yd = y * (1.0 + radial) + self.p2 * (r2 + 2.0 * y * y) + 2.0 * self.p1 * x * y;
        let dyd_dx = radial_prime * x * y + 2.0 * self.p2 * x + 2.0 * self.p1 * y;
        let dyd_dy = 1.0 + radial + radial_prime * y * y + 6.0 * self.p2 * y + 2.0 * self.p1 * x;

        let out = Vector2::new(self.scx * (xd - sin_she * yd), self.scx * cos_she * yd);
        let jacobian = Matrix2::new(
            self.scx * (dxd_dx - sin_she * dyd_dx),
            self.scx * (dxd_dy - sin_she * dyd_dy),
            self.scx * cos_she * dyd_dx,
            self.scx * cos_she * dyd_dy,
        );
        (out, jacobian)
    }

    /// Distorted -> ideal, both relative to the sensor centre (mm): the exact
    /// inverse of [`Distortion::apply`], solved by Newton's method to 1e-12 mm.
    ///
    /// Returns `None` where the distortion polynomial folds over (no unique
    /// inverse near the point), which happens only far outside any sensor.
    pub fn remove(&self, distorted: Vector2<f64>) -> Option<Vector2<f64>> {
        if self.is_identity() {
            return Some(distorted);
        }
        self.undistort(distorted, self.shear.sin_cos())
    }

    fn undistort(
        &self,
        distorted: Vector2<f64>,
        (sin_she, cos_she): (f64, f64),
    ) -> Option<Vector2<f64>> {
        // Start from the inverse of the affine term alone.
        let y0 = distorted.y / (self.scx * cos_she);
        let mut ideal = Vector2::new(distorted.x / self.scx + sin_she * y0, y0);
        for _ in 0..MAX_UNDISTORT_ITERATIONS {
            let (value, jacobian) = self.distort(ideal, (sin_she, cos_she));
            let step = jacobian.try_inverse()? * (distorted - value);
            ideal += step;
            if !ideal.x.is_finite() || !ideal.y.is_finite() {
                return None;
            }
            // Newton converges quadratically (the distortion is a small
            // perturbation of the affine map): the error left after a step
            // is about C step^2, with C = 3 k1 r < 0.1/mm on any real lens,
            // so after a step below 1e-5 mm it is below 1e-11 mm; tests
            // check the inverse to 1e-9 mm.
            if step.norm() <= 1e-5 {
                return Some(ideal);
            }
        }
        None
    }
}

/// The rotation matrix of OpenPTV's `rotation_matrix()`: `Rx(omega) Ry(phi) Rz(kappa)`.
pub fn rotation_matrix(omega: f64, phi: f64, kappa: f64) -> Matrix3<f64> {
    let (so, co) = omega.sin_cos();
    let (sp, cp) = phi.sin_cos();
    let (sk, ck) = kappa.sin_cos();
    Matrix3::new(
        cp * ck,
        -cp * sk,
        sp,
        co * sk + so * sp * ck,
        co * ck - so * sp * sk,
        -so * cp,
        so * sk - co * sp * ck,
        so * ck + co * sp * sk,
        co * cp,
    )
}

/// The angles (omega, phi, kappa) of a rotation matrix; the inverse of
/// [`rotation_matrix`] with phi in [-pi/2, pi/2].
pub fn rotation_angles(rotation: &Matrix3<f64>) -> (f64, f64, f64) {
    let phi = rotation[(0, 2)].clamp(-1.0, 1.0).asin();
    let omega = (-rotation[(1, 2)]).atan2(rotation[(2, 2)]);
    let kappa = (-rotation[(0, 1)]).atan2(rotation[(0, 0)]);
    (omega, phi, kappa)
}

/// One camera's full model as plain data: the 16 parameters, its sensor and
/// the media its rays pass.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraParameters {
    /// A name for people (e.g. "cam1").
    pub name: String,
    /// Image size and pixel pitch.
    pub sensor: Sensor,
    /// Position and angles.
    pub exterior: Exterior,
    /// Principal distance and principal point.
    pub interior: Interior,
    /// Lens distortion and affine terms.
    pub distortion: Distortion,
    /// Air, walls and object medium between the camera and the particles.
    pub media: Media,
}

/// The principal distances a camera may have (mm): 0.1 to 10,000. The
/// shortest lenses made (fisheyes and endoscope optics for small sensors)
/// are about 1 mm, the longest (super-telephoto and catadioptric lenses)
/// about 5,000 mm; a decade of margin below and a factor of 2 above. A
/// value outside is a unit mistake (metres or pixels for mm) or garbage.
pub const PRINCIPAL_DISTANCE_RANGE: (f64, f64) = (0.1, 10_000.0);

/// The pixel pitches a sensor may have (mm): 0.1 µm to 1 mm. The smallest
/// pixels made are about 0.6 µm (phone sensors), the largest about 0.1 mm
/// (X-ray and thermal detectors); scientific cameras have 3..25 µm.
pub const PIXEL_SIZE_RANGE: (f64, f64) = (1e-4, 1.0);

/// The largest magnitude of an angle (rad): 100 turns. Rotations repeat
/// every turn, and solvers wander by whole turns (OpenPTV's test_cavity
/// has omega -56.5 rad, 9 turns), so angles are not normalised; beyond
/// 100 turns an angle is garbage (at 10^16 rad a double cannot tell one
/// turn from the next).
pub const MAX_ANGLE: f64 = 200.0 * std::f64::consts::PI;

/// The largest magnitude of a coordinate of a camera's position or glass
/// vector (mm): 10^9, 1,000 km. No rig is that large (even coordinates
/// of a geodetic frame in mm fit), and a double still resolves 10^-7 mm
/// there.
pub const MAX_COORDINATE: f64 = 1e9;

/// The refractive indices a medium may have: 1 (vacuum) to 5. Air is
/// 1.0003, water 1.33, glasses 1.45..2.0, the densest optical crystals
/// 2.4 (diamond) to 4.0 (germanium, in the infrared).
pub const REFRACTIVE_INDEX_RANGE: (f64, f64) = (1.0, 5.0);

/// The thickest wall (mm): 10 m. Tank walls are millimetres to a few
/// centimetres, the thickest windows (large aquariums) about 0.6 m.
pub const MAX_WALL_THICKNESS: f64 = 10_000.0;

/// The scales of the x image coordinate (`scx`) a camera may have: 0.5 to
/// 2. Real sensors' scale differs from 1 by under 1%.
pub const AFFINE_SCALE_RANGE: (f64, f64) = (0.5, 2.0);

/// The smallest and largest values of `a0 + a1 u + a2 u² + a3 u³` over `0
/// <= u <= end`: at the ends and where the derivative vanishes.
fn cubic_range(a: [f64; 4], end: f64) -> (f64, f64) {
    let value = |u: f64| a[0] + u * (a[1] + u * (a[2] + u * a[3]));
    let mut points = vec![0.0, end];
    // The derivative a1 + 2 a2 u + 3 a3 u².
    let (qa, qb, qc) = (3.0 * a[3], 2.0 * a[2], a[1]);
    if qa == 0.0 {
        if qb != 0.0 {
            points.push(-qc / qb);
        }
    } else {
        let discriminant = qb * qb - 4.0 * qa * qc;
        if discriminant >= 0.0 {
            let root = discriminant.sqrt();
            points.push((-qb + root) / (2.0 * qa));
            points.push((-qb - root) / (2.0 * qa));
        }
    }
    points
        .into_iter()
        .filter(|u| u.is_finite() && (0.0..=end).contains(u))
        .map(value)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        })
}

impl CameraParameters {
    /// Checks the values against the ranges real cameras have: the
    /// principal distance ([`PRINCIPAL_DISTANCE_RANGE`]), the pixel pitch
    /// ([`PIXEL_SIZE_RANGE`]), the principal point (within one sensor
    /// diagonal of the sensor's centre), the angles ([`MAX_ANGLE`]), the
    /// position and glass vector ([`MAX_COORDINATE`]), the refractive
    /// indices ([`REFRACTIVE_INDEX_RANGE`]), the walls
    /// ([`MAX_WALL_THICKNESS`]), the affine scale
    /// ([`AFFINE_SCALE_RANGE`]) and the distortion over the sensor (to its
    /// half-diagonal `R` from the centre: the radial model moving no point
    /// by more than its distance from the centre, `|k1 r² + k2 r⁴ + k3 r⁶|
    /// <= 1`, which refuses absurd terms such as `k1 = 1e10`; it is not
    /// required to stay monotonic to the corners, since a polynomial
    /// fitted to marks that do not reach them may turn there, as `ptv
    /// calibrate`'s fits of a shallow target do);
    /// the decentering terms likewise, `3 (|p1| + |p2|) R <= 1`. Real
    /// lenses stay far inside: 1..10% at the corner).
    ///
    /// [`Camera::new`] checks only what the model needs to compute
    /// (finite values, positive scales), as the solvers try values on the
    /// way; this is for the edges that read calibrations
    /// (`formats::calibration`, the OpenPTV import). The error names the
    /// field, the value and the range.
    pub fn check_physical(&self) -> Result<(), InvalidCamera> {
        self.check_interior()?;
        self.check_exterior()?;
        self.check_distortion()?;
        self.check_media()
    }

    /// The half-diagonal of the sensor (mm), to which the distortion is
    /// held and around whose centre the principal point must lie (within
    /// twice it).
    fn half_diagonal(&self) -> f64 {
        let s = &self.sensor;
        (f64::from(s.width) * s.pixel_size_x).hypot(f64::from(s.height) * s.pixel_size_y) / 2.0
    }

    /// The pixel pitch, the principal distance and the principal point.
    fn check_interior(&self) -> Result<(), InvalidCamera> {
        let s = &self.sensor;
        for (field, value) in [
            ("pixel_size[0]", s.pixel_size_x),
            ("pixel_size[1]", s.pixel_size_y),
        ] {
            within(
                field,
                value,
                PIXEL_SIZE_RANGE,
                " mm",
                "(0.1 µm to 1 mm: real sensors have 0.6 µm to 0.1 mm pixels; give the pitch in mm)",
            )?;
        }
        within(
            "principal_distance",
            self.interior.c,
            PRINCIPAL_DISTANCE_RANGE,
            " mm",
            "(real lenses have about 1 to 5,000 mm; give c in mm)",
        )?;
        let diagonal = 2.0 * self.half_diagonal();
        for (field, value) in [
            ("principal_point[0]", self.interior.xh),
            ("principal_point[1]", self.interior.yh),
        ] {
            within(
                field,
                value,
                (-diagonal, diagonal),
                " mm",
                "(within one sensor diagonal of the sensor's centre)",
            )?;
        }
        Ok(())
    }

    /// The angles and the position.
    fn check_exterior(&self) -> Result<(), InvalidCamera> {
        let e = &self.exterior;
        for (field, value) in [
            ("angles[0]", e.omega),
            ("angles[1]", e.phi),
            ("angles[2]", e.kappa),
        ] {
            within(
                field,
                value,
                (-MAX_ANGLE, MAX_ANGLE),
                " rad",
                "(100 turns either way)",
            )?;
        }
        for (i, value) in e.position.iter().enumerate() {
            within(
                &format!("position[{i}]"),
                *value,
                (-MAX_COORDINATE, MAX_COORDINATE),
                " mm",
                "(1,000 km either way)",
            )?;
        }
        Ok(())
    }

    /// The affine scale, and the radial and decentering distortion over
    /// the sensor.
    fn check_distortion(&self) -> Result<(), InvalidCamera> {
        let d = &self.distortion;
        within(
            "affine[0]",
            d.scx,
            AFFINE_SCALE_RANGE,
            "",
            "(the x scale of a real sensor differs from 1 by under 1%)",
        )?;
        let half = self.half_diagonal();
        let end = half * half;
        if [d.k1, d.k2, d.k3].iter().all(|k| k.is_finite()) {
            let (low, high) = cubic_range([0.0, d.k1, d.k2, d.k3], end);
            if !(low >= -1.0 && high <= 1.0) {
                return Err(InvalidCamera::new(
                    "radial",
                    format!(
                        "[{}, {}, {}] is outside the range of real lenses: over the sensor (to \
                         its half-diagonal, {half:.3} mm) the radial distortion must move no \
                         point by more than its distance from the centre (|k1 r² + k2 r⁴ + k3 \
                         r⁶| <= 1); real lenses move the corners by 1 to 10%",
                        readable(d.k1),
                        readable(d.k2),
                        readable(d.k3)
                    ),
                ));
            }
        } else {
            return Err(InvalidCamera::new(
                "radial",
                format!("must be finite numbers, got [{}, {}, {}]", d.k1, d.k2, d.k3),
            ));
        }
        let decentering = 3.0 * (d.p1.abs() + d.p2.abs()) * half;
        if decentering.is_nan() || decentering > 1.0 {
            return Err(InvalidCamera::new(
                "decentering",
                format!(
                    "[{}, {}] is outside the range of real lenses: over the sensor (to its \
                     half-diagonal, {half:.3} mm) the decentering distortion must move no point \
                     by more than its distance from the centre (3 (|p1| + |p2|) R <= 1, got \
                     {}); real lenses move the corners by under 1%",
                    readable(d.p1),
                    readable(d.p2),
                    readable(decentering)
                ),
            ));
        }
        Ok(())
    }

    /// The refractive indices, the walls' thicknesses and the glass vector.
    fn check_media(&self) -> Result<(), InvalidCamera> {
        let m = &self.media;
        let index = |field: &str, value: f64| {
            within(
                field,
                value,
                REFRACTIVE_INDEX_RANGE,
                "",
                "(air 1.0003, water 1.33, glass 1.45 to 2, the densest crystals 4)",
            )
        };
        index("media.n_air", m.n_air)?;
        index("media.n_object", m.n_object)?;
        for (i, wall) in m.walls.iter().enumerate() {
            index(&format!("media.walls[{i}].n"), wall.n)?;
            within(
                &format!("media.walls[{i}].thickness"),
                wall.thickness,
                (0.0, MAX_WALL_THICKNESS),
                " mm",
                "(the thickest windows are about 600 mm)",
            )?;
        }
        for (i, value) in m.glass_vector.iter().enumerate() {
            within(
                &format!("media.glass_vector[{i}]"),
                *value,
                (-MAX_COORDINATE, MAX_COORDINATE),
                " mm",
                "(1,000 km either way)",
            )?;
        }
        Ok(())
    }
}

/// `Ok` where `value` is finite and within `low..=high`; else the error
/// that names the field, the value and the range in `unit`, and `why`.
fn within(
    field: &str,
    value: f64,
    (low, high): (f64, f64),
    unit: &str,
    why: &str,
) -> Result<(), InvalidCamera> {
    if value.is_finite() && (low..=high).contains(&value) {
        Ok(())
    } else {
        Err(InvalidCamera::new(
            field,
            format!(
                "{} is outside the range {low}..{high}{unit} {why}",
                readable(value)
            ),
        ))
    }
}

/// A number for a message: as it is, or in exponent form when huge or
/// tiny.
fn readable(value: f64) -> String {
    if value == 0.0 || (1e-4..1e7).contains(&value.abs()) || !value.is_finite() {
        format!("{value}")
    } else {
        format!("{value:e}")
    }
}

/// A parameter that cannot describe a real camera.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct InvalidCamera {
    /// The field, named as in the calibration JSON (e.g. `pixel_size[0]`).
    pub field: String,
    /// What is wrong with it and what is expected.
    pub reason: String,
}

impl InvalidCamera {
    pub(crate) fn new(field: impl Into<String>, reason: impl Into<String>) -> Self {
        InvalidCamera {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

/// Why a point has no image, or a pixel no ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ProjectionError {
    /// The point lies behind the camera (or in its projective centre's plane).
    #[error("the point lies behind the camera")]
    BehindCamera,
    /// The point lies on the far side of the camera from its wall: no ray
    /// through the media reaches it.
    #[error("the point lies on the far side of the camera from its wall")]
    AwayFromWall,
    /// The ray from this pixel does not reach the wall, or is totally reflected.
    #[error("the ray from this pixel does not enter the object medium")]
    NoRefractedRay,
    /// The lens distortion cannot be inverted at this image position.
    #[error("the lens distortion cannot be inverted at this image position")]
    Undistortable,
    /// A coordinate of the point is NaN or infinite.
    #[error("the point's coordinates are not all finite numbers")]
    NotFinite,
}

/// Only finite points have an image (a NaN would otherwise pass every
/// comparison of the refraction solve and come out as some pixel).
fn finite(point: &Point3<f64>) -> Result<(), ProjectionError> {
    if point.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(ProjectionError::NotFinite)
    }
}

/// A ray in the object medium: where it enters the medium and its direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Where the ray enters the object medium (for a camera without
    /// refraction, the projective centre).
    pub origin: Point3<f64>,
    /// Unit direction of the ray inside the object medium.
    pub direction: Vector3<f64>,
}

impl Ray {
    /// The point at distance `t` (mm) along the ray from its origin.
    pub fn at(&self, t: f64) -> Point3<f64> {
        self.origin + self.direction * t
    }

    /// The point of the ray with world coordinate Z = `z` (OpenPTV's
    /// `move_along_ray`); `None` if the ray runs parallel to that plane.
    pub fn at_z(&self, z: f64) -> Option<Point3<f64>> {
        if self.direction.z.abs() < 1e-15 {
            return None;
        }
        Some(self.at((z - self.origin.z) / self.direction.z))
    }
}

/// A validated camera with its rotation and wall geometry precomputed.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    parameters: CameraParameters,
    /// `R` of Eq. (1), from camera to world axes.
    rotation: Matrix3<f64>,
    /// The refracting geometry, or `None` when all media share one index.
    geometry: Option<MediaGeometry>,
    /// sin and cos of the shear; `None` when there is no distortion at all.
    distortion_terms: Option<(f64, f64)>,
}

fn check_finite(field: &str, value: f64) -> Result<(), InvalidCamera> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(InvalidCamera::new(
            field,
            format!("must be a finite number, got {value}"),
        ))
    }
}

fn check_positive(field: &str, value: f64) -> Result<(), InvalidCamera> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(InvalidCamera::new(
            field,
            format!("must be positive, got {value}"),
        ))
    }
}

impl Camera {
    /// Validates the parameters and precomputes what projection needs.
    pub fn new(parameters: CameraParameters) -> Result<Camera, InvalidCamera> {
        let p = &parameters;
        check_camera_name(&p.name)?;
        p.sensor.check_size()?;
        check_positive("pixel_size[0]", p.sensor.pixel_size_x)?;
        check_positive("pixel_size[1]", p.sensor.pixel_size_y)?;
        for (i, v) in p.exterior.position.iter().enumerate() {
            check_finite(&format!("position[{i}]"), *v)?;
        }
        check_finite("angles[0]", p.exterior.omega)?;
        check_finite("angles[1]", p.exterior.phi)?;
        check_finite("angles[2]", p.exterior.kappa)?;
        check_positive("principal_distance", p.interior.c)?;
        check_finite("principal_point[0]", p.interior.xh)?;
        check_finite("principal_point[1]", p.interior.yh)?;
        let d = &p.distortion;
        for (field, v) in [
            ("radial[0]", d.k1),
            ("radial[1]", d.k2),
            ("radial[2]", d.k3),
            ("decentering[0]", d.p1),
            ("decentering[1]", d.p2),
        ] {
            check_finite(field, v)?;
        }
        check_positive("affine[0]", d.scx)?;
        check_finite("affine[1]", d.shear)?;
        if d.shear.abs() >= std::f64::consts::FRAC_PI_4 {
            return Err(InvalidCamera::new(
                "affine[1]",
                format!(
                    "the shear must be below pi/4 rad in magnitude, got {}",
                    d.shear
                ),
            ));
        }
        let geometry = MediaGeometry::new(&p.media, &p.exterior.position)?;
        let rotation = rotation_matrix(p.exterior.omega, p.exterior.phi, p.exterior.kappa);
        let distortion_terms = (!d.is_identity()).then(|| d.shear.sin_cos());
        Ok(Camera {
            parameters,
            rotation,
            geometry,
            distortion_terms,
        })
    }

    /// The same camera with the refraction solve tabulated over `volume`,
    /// the optional accelerator of [`super::media`]: projection of points in
    /// the volume gets about twice as fast, and results stay within 1e-11 mm
    /// of the exact solution (the table only starts a Newton step).
    pub fn with_refraction_table(mut self, volume: &Volume) -> Camera {
        let position = self.position();
        self.geometry = self.geometry.map(|g| g.with_table(&position, volume));
        self
    }

    /// The parameters this camera was built from.
    pub fn parameters(&self) -> &CameraParameters {
        &self.parameters
    }

    /// The camera's name.
    pub fn name(&self) -> &str {
        &self.parameters.name
    }

    /// The sensor.
    pub fn sensor(&self) -> &Sensor {
        &self.parameters.sensor
    }

    /// The rotation matrix `R` (camera axes to world axes).
    pub fn rotation(&self) -> &Matrix3<f64> {
        &self.rotation
    }

    /// The projective centre (mm).
    pub fn position(&self) -> Point3<f64> {
        Point3::from(self.parameters.exterior.position)
    }

    /// The refracting geometry, `None` for a camera whose media share one index.
    pub fn media_geometry(&self) -> Option<&MediaGeometry> {
        self.geometry.as_ref()
    }

    /// Flat image coordinates (ideal, relative to the principal point, mm) of
    /// a point in object space: Eq. (2) with the multimedia module.
    pub fn project_flat(&self, point: &Point3<f64>) -> Result<Vector2<f64>, ProjectionError> {
        self.collinearity(&self.air_direction(point)?)
    }

    /// The direction in air from the projective centre of the ray that
    /// reaches `point` (not normalised without refraction): the part of the
    /// projection that depends only on the position of the camera, not on
    /// its angles or interior parameters.
    pub(crate) fn air_direction(
        &self,
        point: &Point3<f64>,
    ) -> Result<Vector3<f64>, ProjectionError> {
        finite(point)?;
        match &self.geometry {
            Some(geometry) => geometry.air_direction(&self.position(), point),
            None => Ok(point - self.position()),
        }
    }

    /// Pixel coordinates of the ray leaving the projective centre along
    /// `direction` in air: the rest of the projection after
    /// [`Camera::air_direction`].
    pub(crate) fn pixel_of_air_direction(
        &self,
        direction: &Vector3<f64>,
    ) -> Result<Point2<f64>, ProjectionError> {
        Ok(self.flat_to_pixel(self.collinearity(direction)?))
    }

    /// Pixel coordinates of a point in object space.
    pub fn project(&self, point: &Point3<f64>) -> Result<Point2<f64>, ProjectionError> {
        let flat = self.project_flat(point)?;
        Ok(self.flat_to_pixel(flat))
    }

    /// Pixel coordinates of a point and their 2x3 Jacobian with respect to
    /// the point (px/mm): the linearised observation equations of a spatial
    /// intersection (Eq. 21-22 with the object coordinates as unknowns).
    pub fn project_with_jacobian(
        &self,
        point: &Point3<f64>,
    ) -> Result<(Point2<f64>, Matrix2x3<f64>), ProjectionError> {
        finite(point)?;
        let (direction, d_direction) = match &self.geometry {
            Some(geometry) => geometry.air_direction_with_jacobian(&self.position(), point)?,
            None => (point - self.position(), Matrix3::identity()),
        };
        let v = self.rotation.tr_mul(&direction);
        if v.z >= 0.0 {
            return Err(ProjectionError::BehindCamera);
        }
        let c = self.parameters.interior.c;
        let flat = Vector2::new(-c * v.x / v.z, -c * v.y / v.z);
        let d_flat_d_v = Matrix2x3::new(
            -c / v.z,
            0.0,
            c * v.x / (v.z * v.z),
            0.0,
            -c / v.z,
            c * v.y / (v.z * v.z),
        );
        let interior = &self.parameters.interior;
        let ideal = flat + Vector2::new(interior.xh, interior.yh);
        let (metric, d_metric) = match self.distortion_terms {
            Some(terms) => self.parameters.distortion.distort(ideal, terms),
            None => (ideal, Matrix2::identity()),
        };
        let sensor = &self.parameters.sensor;
        let d_pixel_d_metric = Matrix2::new(
            1.0 / sensor.pixel_size_x,
            0.0,
            0.0,
            -1.0 / sensor.pixel_size_y,
        );
        let jacobian =
            d_pixel_d_metric * d_metric * d_flat_d_v * self.rotation.transpose() * d_direction;
        Ok((sensor.metric_to_pixel(metric), jacobian))
    }

    /// Eq. (2): flat image coordinates of a direction in air from the
    /// projective centre.
    fn collinearity(&self, direction: &Vector3<f64>) -> Result<Vector2<f64>, ProjectionError> {
        let v = self.rotation.tr_mul(direction);
        if v.z >= 0.0 {
            return Err(ProjectionError::BehindCamera);
        }
        let scale = -self.parameters.interior.c / v.z;
        Ok(Vector2::new(scale * v.x, scale * v.y))
    }

    /// Flat -> metric image coordinates (principal point, distortion, affine).
    pub fn flat_to_metric(&self, flat: Vector2<f64>) -> Vector2<f64> {
        let interior = &self.parameters.interior;
        let ideal = flat + Vector2::new(interior.xh, interior.yh);
        match self.distortion_terms {
            Some(terms) => self.parameters.distortion.distort(ideal, terms).0,
            None => ideal,
        }
    }

    /// Metric -> flat image coordinates; the exact inverse of [`Camera::flat_to_metric`].
    pub fn metric_to_flat(&self, metric: Vector2<f64>) -> Result<Vector2<f64>, ProjectionError> {
        let interior = &self.parameters.interior;
        let ideal = match self.distortion_terms {
            Some(terms) => self
                .parameters
                .distortion
                .undistort(metric, terms)
                .ok_or(ProjectionError::Undistortable)?,
            None => metric,
        };
        Ok(ideal - Vector2::new(interior.xh, interior.yh))
    }

    /// Flat image coordinates -> pixels.
    pub fn flat_to_pixel(&self, flat: Vector2<f64>) -> Point2<f64> {
        self.parameters
            .sensor
            .metric_to_pixel(self.flat_to_metric(flat))
    }

    /// Pixels -> flat image coordinates.
    pub fn pixel_to_flat(&self, pixel: Point2<f64>) -> Result<Vector2<f64>, ProjectionError> {
        self.metric_to_flat(self.parameters.sensor.pixel_to_metric(pixel))
    }

    /// The ray in the object medium that images at this pixel: Eq. (13)-(17),
    /// Snell's law through every wall.
    pub fn ray(&self, pixel: Point2<f64>) -> Result<Ray, ProjectionError> {
        self.ray_from_flat(self.pixel_to_flat(pixel)?)
    }

    /// The ray in the object medium through flat image coordinates.
    pub fn ray_from_flat(&self, flat: Vector2<f64>) -> Result<Ray, ProjectionError> {
        let c = self.parameters.interior.c;
        let direction = self.rotation * Vector3::new(flat.x, flat.y, -c);
        match &self.geometry {
            Some(geometry) => geometry.trace(&self.position(), &direction),
            None => Ok(Ray {
                origin: self.position(),
                direction: direction.normalize(),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn distortion() -> Distortion {
        Distortion {
            k1: 2.4e-4,
            k2: -3e-7,
            k3: 1e-9,
            p1: -6.6e-6,
            p2: 8.7e-6,
            scx: 1.0015,
            shear: -0.0015,
        }
    }

    fn with(f: impl FnOnce(&mut CameraParameters)) -> Result<Camera, InvalidCamera> {
        use crate::photogrammetry::simulate::RigSpec;
        let mut p = RigSpec::convergent(2).build().unwrap()[0]
            .parameters()
            .clone();
        f(&mut p);
        Camera::new(p)
    }

    #[test]
    fn sensor_sides_and_pixels_are_bounded() {
        // At each limit accepted, one past it refused with the limit named.
        assert!(with(|p| (p.sensor.width, p.sensor.height) = (MAX_SENSOR_SIDE, 4096)).is_ok());
        assert_eq!(u64::from(MAX_SENSOR_SIDE) * 4096, MAX_SENSOR_PIXELS);
        assert!(with(|p| (p.sensor.width, p.sensor.height) = (8192, 8192)).is_ok());
        let wide = with(|p| p.sensor.width = MAX_SENSOR_SIDE + 1).unwrap_err();
        assert_eq!(wide.field, "image_size[0]");
        assert!(wide.reason.contains("16385 px") && wide.reason.contains("MAX_SENSOR_SIDE"));
        let tall = with(|p| p.sensor.height = 22_000).unwrap_err();
        assert_eq!(tall.field, "image_size[1]");
        let many = with(|p| (p.sensor.width, p.sensor.height) = (8193, 8192)).unwrap_err();
        assert_eq!(many.field, "image_size");
        assert!(
            many.reason.contains("67117056 pixels") && many.reason.contains("MAX_SENSOR_PIXELS"),
            "{many}"
        );
        assert!(with(|p| p.sensor.width = 0).is_err());
    }

    #[test]
    fn camera_names_are_short_plain_file_names() {
        let longest = "c".repeat(MAX_CAMERA_NAME_LEN);
        for good in [
            "cam1",
            "left_top.serial-1234",
            "C",
            "a..b",
            longest.as_str(),
        ] {
            assert!(check_camera_name(good).is_ok(), "{good}");
            assert!(with(|p| p.name = good.to_owned()).is_ok(), "{good}");
        }
        let too_long = "c".repeat(MAX_CAMERA_NAME_LEN + 1);
        let huge = "x".repeat(1 << 20);
        for (bad, problem) in [
            ("", "is empty"),
            (
                too_long.as_str(),
                "65 bytes long, more than the limit of 64",
            ),
            (huge.as_str(), "1048576 bytes long"),
            ("../../etc/passwd", "character '/'"),
            ("cam\\1", "character '\\\\'"),
            ("cam\0x", "character '\\0'"),
            ("cam 1", "character ' '"),
            ("kamera\u{e9}", "character '\u{e9}'"),
            (".hidden", "starts with `.`"),
            ("..", "starts with `.`"),
        ] {
            let error = with(|p| p.name = bad.to_owned()).unwrap_err();
            assert_eq!(error.field, "name");
            assert!(
                error.reason.contains(problem) && error.reason.contains("1 to 64 characters"),
                "{bad:?}: {error}"
            );
            // The message quotes at most the limit's length of the name.
            assert!(error.reason.len() < 400, "{}", error.reason.len());
        }
    }

    #[test]
    fn rotation_matches_openptv_ori_matrix() {
        // golden/rig_a/cam1.ori lists the matrix OpenPTV computed from its angles (7 decimals).
        let r = rotation_matrix(0.04631075, 0.31469973, 0.12219835);
        let expected = Matrix3::new(
            0.9437986, -0.1159081, 0.3095310, 0.1359864, 0.9897322, -0.0440207, -0.3012504,
            0.0836386, 0.9498699,
        );
        assert!((r - expected).abs().max() < 5e-8, "{r}");
    }

    #[test]
    fn rotation_angles_invert_rotation_matrix() {
        for &(o, p, k) in &[
            (0.1, -0.3, 2.0),
            (-2.5, 1.2, -0.4),
            (0.0, 0.0, 0.0),
            (3.0, -1.5, 3.1),
        ] {
            let r = rotation_matrix(o, p, k);
            let (o2, p2, k2) = rotation_angles(&r);
            assert!((rotation_matrix(o2, p2, k2) - r).abs().max() < 1e-14);
        }
    }

    #[test]
    fn pixel_convention_puts_first_pixel_centre_at_half() {
        let sensor = Sensor {
            width: 1280,
            height: 1024,
            pixel_size_x: 0.012,
            pixel_size_y: 0.01,
        };
        // The top-left corner of the sensor is at metric (-w/2 * px, +h/2 * py).
        let corner = sensor.metric_to_pixel(Vector2::new(-640.0 * 0.012, 512.0 * 0.01));
        assert!((corner - Point2::new(0.0, 0.0)).norm() < 1e-12);
        let back = sensor.pixel_to_metric(Point2::new(0.5, 0.5));
        assert!((back - Vector2::new(-639.5 * 0.012, 511.5 * 0.01)).norm() < 1e-12);
    }

    #[test]
    fn distortion_inverse_is_exact() {
        let d = distortion();
        for i in -10..=10 {
            for j in -10..=10 {
                let ideal = Vector2::new(f64::from(i) * 0.8, f64::from(j) * 0.65);
                let distorted = d.apply(ideal);
                let back = d.remove(distorted).expect("invertible on the sensor");
                assert!((back - ideal).norm() < 1e-9, "{ideal} -> {back}");
            }
        }
    }

    /// A NaN or infinite point has no image, through walls or in air (it
    /// used to come out of the refraction solve as some pixel).
    #[test]
    fn non_finite_points_have_no_image() {
        use crate::photogrammetry::simulate::RigSpec;
        let in_water = RigSpec::convergent(2).build().unwrap();
        let in_air = RigSpec {
            tank: None,
            ..RigSpec::convergent(2)
        }
        .build()
        .unwrap();
        for camera in [&in_water[0], &in_air[0]] {
            for point in [
                Point3::new(f64::NAN, 0.0, 0.0),
                Point3::new(0.0, f64::INFINITY, 0.0),
                Point3::new(0.0, 0.0, f64::NEG_INFINITY),
            ] {
                assert_eq!(camera.project(&point), Err(ProjectionError::NotFinite));
                assert_eq!(
                    camera.project_with_jacobian(&point).map(|(pixel, _)| pixel),
                    Err(ProjectionError::NotFinite)
                );
            }
            assert!(camera.project(&Point3::new(1.0, 2.0, 3.0)).is_ok());
        }
    }

    #[test]
    fn refraction_table_keeps_projection_exact() {
        use crate::photogrammetry::simulate::{self, RigSpec};
        let spec = RigSpec::convergent(4);
        let mut rng = simulate::rng(5);
        // Inside the tabulated volume, and in a larger one around it where
        // the table does not reach and the exact solve takes over.
        let mut points = simulate::particles(&spec.volume, 2000, &mut rng);
        let larger = Volume {
            min: spec.volume.min * 1.5,
            max: spec.volume.max * 1.5,
        };
        points.extend(simulate::particles(&larger, 500, &mut rng));
        for camera in spec.build().unwrap() {
            let tabulated = camera.clone().with_refraction_table(&spec.volume);
            assert_ne!(tabulated, camera);
            for point in &points {
                let exact = camera.project_flat(point).unwrap();
                let fast = tabulated.project_flat(point).unwrap();
                assert!(
                    (exact - fast).norm() < 1e-9,
                    "{point}: {:e} mm",
                    (exact - fast).norm()
                );
                let (_, j_exact) = camera.project_with_jacobian(point).unwrap();
                let (_, j_fast) = tabulated.project_with_jacobian(point).unwrap();
                assert!((j_exact - j_fast).norm() < 1e-6 * j_exact.norm());
            }
        }
    }

    #[test]
    fn distortion_jacobian_matches_finite_differences() {
        let d = distortion();
        let at = Vector2::new(3.1, -2.2);
        let (_, jac) = d.apply_with_jacobian(at);
        let h = 1e-6;
        for k in 0..2 {
            let mut step = Vector2::zeros();
            step[k] = h;
            let numeric = (d.apply(at + step) - d.apply(at - step)) / (2.0 * h);
            assert!((jac.column(k) - numeric).norm() < 1e-8, "column {k}");
        }
    }

    #[test]
    fn physical_ranges_refuse_absurd_values_and_keep_real_ones() {
        use crate::photogrammetry::simulate::RigSpec;
        let real = RigSpec::convergent(4).build().unwrap();
        for camera in &real {
            camera.parameters().check_physical().unwrap();
        }
        let base = real[0].parameters().clone();
        let physical = |f: &dyn Fn(&mut CameraParameters)| {
            let mut p = base.clone();
            f(&mut p);
            p.check_physical()
        };
        // The probe's values, each refused naming the field, the value and
        // the range.
        type Change<'a> = &'a dyn Fn(&mut CameraParameters);
        let cases: Vec<(Change, &str, &str)> = vec![
            (
                &|p| p.interior.c = 1e308,
                "principal_distance",
                "1e308 is outside the range 0.1..10000 mm",
            ),
            (
                &|p| p.interior.c = 0.01,
                "principal_distance",
                "0.01 is outside",
            ),
            (
                &|p| p.sensor.pixel_size_x = 1e-300,
                "pixel_size[0]",
                "1e-300 is outside the range 0.0001..1 mm",
            ),
            (
                &|p| p.sensor.pixel_size_y = 2.0,
                "pixel_size[1]",
                "2 is outside",
            ),
            (&|p| p.distortion.k1 = 1e10, "radial", "[1e10, 0, 0]"),
            (
                &|p| p.exterior.omega = 1e300,
                "angles[0]",
                "1e300 is outside the range",
            ),
            (&|p| p.exterior.kappa = -1e300, "angles[2]", "-1e300"),
            (&|p| p.exterior.position.y = 1e12, "position[1]", "1e12"),
            (
                &|p| p.interior.xh = 1e6,
                "principal_point[0]",
                "1000000 is outside",
            ),
            (&|p| p.distortion.p1 = 1.0, "decentering", "[1, 0]"),
            (
                &|p| p.distortion.scx = 10.0,
                "affine[0]",
                "10 is outside the range 0.5..2",
            ),
            (
                &|p| p.media.n_object = 1e9,
                "media.n_object",
                "1e9 is outside the range 1..5",
            ),
            (&|p| p.media.n_air = 0.5, "media.n_air", "0.5 is outside"),
        ];
        for (change, field, needle) in cases {
            let error = physical(change).unwrap_err();
            assert_eq!(error.field, field, "{error}");
            assert!(error.reason.contains(needle), "{error}");
        }
        // Walls: thickness and index.
        let mut walled = base.clone();
        walled.media = Media {
            n_air: 1.0,
            walls: vec![super::super::Wall {
                n: 1.49,
                thickness: 1e7,
            }],
            n_object: 1.33,
            glass_vector: Vector3::new(0.0, 0.0, 100.0),
        };
        let error = walled.check_physical().unwrap_err();
        assert_eq!(error.field, "media.walls[0].thickness", "{error}");
        // At the ends of the ranges, accepted.
        assert!(physical(&|p| p.interior.c = 10_000.0).is_ok());
        assert!(physical(&|p| p.sensor.pixel_size_x = 1e-4).is_ok());
        assert!(
            physical(&|p| p.exterior.omega = -56.54).is_ok(),
            "test_cavity's omega"
        );
        // Radial distortion: within 100% over the sensor (half-diagonal
        // R); real lenses (1..10% at the corner) pass, and so does a fit
        // that turns before the corner (`ptv calibrate` of a shallow
        // target gave k = [-1.57e-4, 2.16e-5, -8.45e-7] at R = 9.8 mm,
        // which moves the corner by -58%).
        let r2 = {
            let s = &base.sensor;
            let d =
                (f64::from(s.width) * s.pixel_size_x).hypot(f64::from(s.height) * s.pixel_size_y);
            d * d / 4.0
        };
        assert!(physical(&|p| p.distortion.k1 = 0.1 / r2).is_ok());
        assert!(physical(&|p| p.distortion.k1 = -0.1 / r2).is_ok());
        assert!(physical(&|p| {
            p.distortion.k1 = -0.0157 / r2;
            p.distortion.k2 = 0.202 / (r2 * r2);
            p.distortion.k3 = -0.765 / (r2 * r2 * r2);
        })
        .is_ok());
        let error = physical(&|p| p.distortion.k1 = 1.1 / r2).unwrap_err();
        assert!(
            error.reason.contains("by more than its distance"),
            "{error}"
        );
        // Within 100% at the corner (-0.8) but past it inside the sensor:
        // -4x + 3.2x², x = r²/R², reaches -1.25 at x = 0.625.
        assert!(physical(&|p| {
            p.distortion.k1 = -4.0 / r2;
            p.distortion.k2 = 3.2 / (r2 * r2);
        })
        .is_err());
        assert!(
            physical(&|p| p.distortion.k1 = 1e10).is_err(),
            "issue 29's 1e10"
        );
    }
}
