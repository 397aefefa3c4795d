//! OpenLPT's camera files (`Camera::loadParameters`/`saveParameters` of
//! OpenLPT, `src/srcMath/Camera.cpp`), its `PINHOLE` model: OpenCV's
//! camera. One file per camera; lines starting with `#` are comments, values
//! on a line are comma separated:
//!
//! ```text
//! PINHOLE                       the model
//! None                          the camera calibration error (not read)
//! None                          the pose calibration error (not read)
//! n_row,n_col                   the image size: height, width (px)
//! fx,0,cx / 0,fy,cy / 0,0,1     the camera matrix K (px; the skew is not used)
//! k1,k2,p1,p2[,k3[,k4,k5,k6]]   OpenCV's distortion coefficients
//! rx,ry,rz                      the rotation vector (informative, not read)
//! 3 rows                        the rotation matrix R (world to camera)
//! 3 rows                        its inverse
//! tx,ty,tz                      the translation t (mm)
//! 3 numbers                     its inverse, -Rᵀ t: the camera's position
//! ```
//!
//! The model: `Xc = R X + t`, `x = Xc/Zc`, `y = Yc/Zc`, distorted by
//! OpenCV's radial (`k1, k2, k3` and the rational `k4..k6`) and tangential
//! (`p1, p2`) terms, then `u = fx x_d + cx`, `v = fy y_d + cy` (the centre
//! of the top-left pixel at 0). OpenLPT applies the distortion only when a
//! coefficient is above 1e-8 (`is_distorted`): a lens whose coefficients
//! are all negative is projected undistorted, and so does
//! [`OpenlptCamera::project`], to measure a conversion against what OpenLPT
//! computes.
//!
//! What carries over exactly ([`not_carried`]): a camera in air without
//! shear, whose principal point is the sensor's centre if it has
//! distortion (OpenCV distorts about the principal point, ptv about the
//! sensor's centre). ptv's `c` in mm is `fx` times the pixel size, which
//! the file does not hold: a camera comes in with the pixel size the user
//! gives (the images do not depend on it), `pixel_size_y = c / fy`. Brown's
//! terms map as `K1 = k1 c²`, `K2 = k2 c⁴`, `K3 = k3 c⁶`, `P1 = -p2 c`,
//! `P2 = p1 c` (OpenCV's y axis is ptv's reversed). Other cameras go out,
//! and rational or thin-prism lenses and off-centre distorted ones come in,
//! through the best fit ([`super::between::best_fit`]). A camera matrix
//! with `fx` and `fy` of opposite signs and a proper rotation images the
//! world mirrored: no camera of ptv's model does, and it is refused.
//! OpenLPT's `PINPLATE` (a pinhole behind refracting plates) and
//! `POLYNOMIAL` models are refused with a message.

use std::fmt::Write as _;

use nalgebra::{Matrix3, Point2, Point3, Rotation3, Vector3};

use super::between::{flip, flip_rotation, PIXEL_CENTRE};
use super::FormatError;
use crate::photogrammetry::camera::{rotation_angles, rotation_matrix};
use crate::photogrammetry::{CameraParameters, Distortion, Exterior, Interior, Media, Sensor};

/// OpenLPT's threshold below which a coefficient does not count as
/// distortion (`SMALLNUMBER`).
pub const DISTORTION_THRESHOLD: f64 = 1e-8;

/// One OpenLPT pinhole camera, as its file holds it.
#[derive(Clone, Debug, PartialEq)]
pub struct OpenlptCamera {
    /// Image height (px).
    pub n_row: u32,
    /// Image width (px).
    pub n_col: u32,
    /// The camera matrix K.
    pub matrix: Matrix3<f64>,
    /// OpenCV's distortion coefficients: 0, 4, 5 or 8 of them.
    pub distortion: Vec<f64>,
    /// R, world to camera, as written.
    pub rotation: Matrix3<f64>,
    /// t (mm).
    pub translation: Vector3<f64>,
}

impl OpenlptCamera {
    /// Whether OpenLPT applies the distortion (a coefficient above 1e-8).
    pub fn is_distorted(&self) -> bool {
        self.distortion.iter().any(|&k| k > DISTORTION_THRESHOLD)
    }

    /// The image of a point as OpenLPT's `project` computes it, in ptv's
    /// pixel convention; `None` behind the camera.
    pub fn project(&self, point: &Point3<f64>) -> Option<Point2<f64>> {
        let c = self.rotation * point.coords + self.translation;
        if c.z.is_nan() || c.z <= 0.0 {
            return None;
        }
        let (x, y) = (c.x / c.z, c.y / c.z);
        let (xd, yd) = if self.is_distorted() {
            let k = |i: usize| self.distortion.get(i).copied().unwrap_or(0.0);
            let r2 = x * x + y * y;
            let radial = (1.0 + k(0) * r2 + k(1) * r2 * r2 + k(4) * r2 * r2 * r2)
                / (1.0 + k(5) * r2 + k(6) * r2 * r2 + k(7) * r2 * r2 * r2);
            (
                x * radial + 2.0 * k(2) * x * y + k(3) * (r2 + 2.0 * x * x),
                y * radial + k(2) * (r2 + 2.0 * y * y) + 2.0 * k(3) * x * y,
            )
        } else {
            (x, y)
        };
        let m = &self.matrix;
        let pixel = Point2::new(
            xd * m[(0, 0)] + m[(0, 2)] + PIXEL_CENTRE,
            yd * m[(1, 1)] + m[(1, 2)] + PIXEL_CENTRE,
        );
        (pixel.x.is_finite() && pixel.y.is_finite()).then_some(pixel)
    }
}

/// Reads an OpenLPT camera file (the `PINHOLE` model). Errors name the
/// source and the line.
pub fn parse(text: &str, source: &str) -> Result<OpenlptCamera, FormatError> {
    let mut file = CameraFile::new(text, source);
    let (line, model) = file.next("the camera model")?;
    file.check_model(line, model)?;
    file.next("the camera calibration error")?;
    file.next("the pose calibration error")?;
    let (n_row, n_col) = file.image_size()?;
    let (matrix, _) = file.matrix("a row of the camera matrix")?;
    let distortion = file.distortion()?;
    file.next("the rotation vector")?;
    let (rotation, rotation_line) = file.matrix("a row of the rotation matrix")?;
    let (inverse, _) = file.matrix("a row of the inverse rotation matrix")?;
    let translation_line = file.next("the translation vector")?;
    let translation =
        Vector3::from_vec(file.numbers(translation_line, Some(3), "the translation vector")?);
    let position_line = file.next("the inverse translation vector")?;
    let position = Vector3::from_vec(file.numbers(
        position_line,
        Some(3),
        "the inverse translation vector",
    )?);
    file.check_pose(
        (&rotation, rotation_line),
        &inverse,
        &translation,
        (&position, position_line.0),
    )?;
    if let Ok((line, extra)) = file.next("nothing") {
        return Err(file.at(
            line,
            format!("unexpected `{extra}` after the inverse translation vector"),
        ));
    }
    Ok(OpenlptCamera {
        n_row,
        n_col,
        matrix,
        distortion,
        rotation,
        translation,
    })
}

/// An OpenLPT camera file's lines, read in order: the non-empty ones that
/// are not comments, each with its line number for errors.
struct CameraFile<'a> {
    source: &'a str,
    lines: Vec<(usize, &'a str)>,
    cursor: usize,
    last_line: usize,
}

impl<'a> CameraFile<'a> {
    fn new(text: &'a str, source: &'a str) -> Self {
        CameraFile {
            source,
            lines: text
                .lines()
                .enumerate()
                .map(|(i, l)| (i + 1, l.trim()))
                .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
                .collect(),
            cursor: 0,
            last_line: text.lines().count().max(1),
        }
    }

    /// The next line, where `what` is expected.
    fn next(&mut self, what: &str) -> Result<(usize, &'a str), FormatError> {
        let line = self.lines.get(self.cursor).copied().ok_or_else(|| {
            FormatError::invalid(
                self.source,
                format!("line {}", self.last_line),
                format!("the file ends where {what} was expected"),
            )
        });
        self.cursor += 1;
        line
    }

    /// The error at `line`.
    fn at(&self, line: usize, reason: String) -> FormatError {
        FormatError::invalid(self.source, format!("line {line}"), reason)
    }

    /// A line's numbers (`count` of them where given).
    fn numbers(
        &self,
        (line, text): (usize, &str),
        count: Option<usize>,
        what: &str,
    ) -> Result<Vec<f64>, FormatError> {
        let values = fields(text);
        if let Some(count) = count {
            if values.len() != count {
                return Err(self.at(
                    line,
                    format!("expected {what}: {count} numbers, found {}", values.len()),
                ));
            }
        }
        values
            .iter()
            .map(|v| super::openptv::finite_number(v, self.source, line, what))
            .collect()
    }

    /// A 3x3 matrix from the next three lines, and its first line.
    fn matrix(&mut self, what: &str) -> Result<(Matrix3<f64>, usize), FormatError> {
        let read = [self.next(what)?, self.next(what)?, self.next(what)?];
        let mut m = Matrix3::zeros();
        for (r, line) in read.into_iter().enumerate() {
            let row = self.numbers(line, Some(3), what)?;
            for c in 0..3 {
                m[(r, c)] = row[c];
            }
        }
        Ok((m, read[0].0))
    }

    /// The camera model must be `PINHOLE`; the others are told apart.
    fn check_model(&self, line: usize, model: &str) -> Result<(), FormatError> {
        match model {
            "PINHOLE" => Ok(()),
            "PINPLATE" => Err(self.at(
                line,
                "OpenLPT's PINPLATE model (a pinhole behind refracting plates) is not read yet; \
                 export the calibration from ptv instead, or give OpenLPT's PINHOLE camera"
                    .to_owned(),
            )),
            "POLYNOMIAL" => Err(self.at(
                line,
                "OpenLPT's POLYNOMIAL model maps world to image by polynomials, not a physical \
                 camera; ptv's model cannot take it"
                    .to_owned(),
            )),
            other => Err(self.at(
                line,
                format!("expected the camera model PINHOLE, got `{other}`"),
            )),
        }
    }

    /// The image size line, `n_row,n_col`.
    fn image_size(&mut self) -> Result<(u32, u32), FormatError> {
        let size_line = self.next("the image size `n_row,n_col`")?;
        let size = fields(size_line.1);
        let side = |t: &String| t.parse::<u32>().ok().filter(|&v| v > 0);
        match size.as_slice() {
            [r, c] => match (side(r), side(c)) {
                (Some(r), Some(c)) => Ok((r, c)),
                _ => Err(self.at(
                    size_line.0,
                    format!(
                        "the image size must be two positive whole numbers n_row,n_col, got `{}`",
                        size_line.1
                    ),
                )),
            },
            _ => Err(self.at(
                size_line.0,
                format!(
                    "expected the image size `n_row,n_col`, got `{}`",
                    size_line.1
                ),
            )),
        }
    }

    /// The distortion coefficients: 4, 5 or 8 of OpenCV's (or none).
    fn distortion(&mut self) -> Result<Vec<f64>, FormatError> {
        let distortion_line = self.next("the distortion coefficients")?;
        let distortion = self.numbers(distortion_line, None, "a distortion coefficient")?;
        match distortion.len() {
            0 | 4 | 5 | 8 => Ok(distortion),
            12 | 14 => Err(self.at(
                distortion_line.0,
                format!(
                    "{} distortion coefficients: OpenCV's thin-prism terms, which neither OpenLPT \
                     nor ptv applies; give 4, 5 or 8",
                    distortion.len()
                ),
            )),
            n => Err(self.at(
                distortion_line.0,
                format!("expected 4, 5 or 8 distortion coefficients, found {n}"),
            )),
        }
    }

    /// The rotation must be one, and the inverse rotation and the
    /// position (the inverse translation) must agree with it and the
    /// translation, to the precision they are written with.
    fn check_pose(
        &self,
        (rotation, rotation_line): (&Matrix3<f64>, usize),
        inverse: &Matrix3<f64>,
        translation: &Vector3<f64>,
        (position, position_line): (&Vector3<f64>, usize),
    ) -> Result<(), FormatError> {
        // The example files print 6 digits: 1e-5 leaves a margin of 10.
        let rotation_error = (rotation * rotation.transpose() - Matrix3::identity())
            .abs()
            .max();
        if rotation_error > 1e-5 || rotation.determinant() < 0.0 {
            return Err(self.at(
                rotation_line,
                format!(
                    "the rotation matrix is not a rotation (R Rᵀ differs from the identity by \
                     {rotation_error:.1e}, determinant {:.6})",
                    rotation.determinant()
                ),
            ));
        }
        // OpenLPT uses the inverses for the lines of sight. To the written
        // precision: 1e-5 relative.
        let inverse_error = (inverse - rotation.transpose()).abs().max();
        let expected_position = -(rotation.transpose() * translation);
        let position_error = (position - expected_position).norm();
        if inverse_error > 1e-5 || position_error > 1e-5 * expected_position.norm().max(1.0) {
            return Err(self.at(
                position_line,
                format!(
                    "the inverse rotation and translation do not match R and t (off by \
                     {inverse_error:.1e} and {position_error:.1e} mm); OpenLPT would project and \
                     trace rays with different cameras"
                ),
            ));
        }
        Ok(())
    }
}

/// A line's fields, split at commas, spaces and tabs.
fn fields(text: &str) -> Vec<String> {
    text.split([',', ' ', '\t'])
        .filter(|t| !t.is_empty())
        .map(str::to_owned)
        .collect()
}

/// The file's text as OpenLPT's `saveParameters` writes it (numbers in
/// their shortest exact form).
pub fn format(camera: &OpenlptCamera) -> String {
    let row = |values: &[f64]| {
        values
            .iter()
            .map(|v| format!("{v:?}"))
            .collect::<Vec<_>>()
            .join(",")
    };
    let matrix = |m: &Matrix3<f64>| {
        (0..3)
            .map(|r| row(&[m[(r, 0)], m[(r, 1)], m[(r, 2)]]) + "\n")
            .collect::<String>()
    };
    let rotation = Rotation3::from_matrix_unchecked(camera.rotation);
    let vector = rotation.scaled_axis();
    let position = -(camera.rotation.transpose() * camera.translation);
    let mut text = String::new();
    let _ = write!(
        text,
        "# Camera Model: (PINHOLE/POLYNOMIAL)\nPINHOLE\n# Camera Calibration Error: \nNone\n\
         # Pose Calibration Error: \nNone\n# Image Size: (n_row,n_col)\n{},{}\n\
         # Camera Matrix: \n{}# Distortion Coefficients: \n{}\n# Rotation Vector: \n{}\n\
         # Rotation Matrix: \n{}# Inverse of Rotation Matrix: \n{}# Translation Vector: \n{}\n\
         # Inverse of Translation Vector: \n{}\n",
        camera.n_row,
        camera.n_col,
        matrix(&camera.matrix),
        row(&camera.distortion),
        row(vector.as_slice()),
        matrix(&camera.rotation),
        matrix(&camera.rotation.transpose()),
        row(camera.translation.as_slice()),
        row(position.as_slice()),
    );
    text
}

/// Why a ptv camera cannot be written exactly as an OpenLPT pinhole, or
/// `None`.
pub fn not_carried(p: &CameraParameters) -> Option<String> {
    let d = &p.distortion;
    let mut reasons = Vec::new();
    if !p.media.is_homogeneous() {
        reasons.push("refraction (OpenLPT's PINHOLE has none)");
    }
    if d.shear != 0.0 {
        reasons.push("shear (OpenLPT does not use the skew)");
    }
    let distorted = [d.k1, d.k2, d.k3, d.p1, d.p2].iter().any(|&k| k != 0.0);
    if distorted && (p.interior.xh != 0.0 || p.interior.yh != 0.0) {
        reasons.push(
            "distortion about the sensor's centre with the principal point off it (OpenCV \
             distorts about the principal point)",
        );
    }
    (!reasons.is_empty()).then(|| reasons.join(", "))
}

/// The OpenLPT pinhole of a ptv camera that [`not_carried`] passes: exact.
pub fn from_parameters(p: &CameraParameters) -> Result<OpenlptCamera, String> {
    if let Some(reason) = not_carried(p) {
        return Err(reason);
    }
    let s = &p.sensor;
    let (c, scx) = (p.interior.c, p.distortion.scx);
    let d = &p.distortion;
    let r = rotation_matrix(p.exterior.omega, p.exterior.phi, p.exterior.kappa);
    let rotation = flip_rotation(&r);
    let translation = -(rotation * p.exterior.position);
    let fx = scx * c / s.pixel_size_x;
    let fy = scx * c / s.pixel_size_y;
    let cx = f64::from(s.width) / 2.0 - PIXEL_CENTRE + scx * p.interior.xh / s.pixel_size_x;
    let cy = f64::from(s.height) / 2.0 - PIXEL_CENTRE - scx * p.interior.yh / s.pixel_size_y;
    Ok(OpenlptCamera {
        n_row: s.height,
        n_col: s.width,
        matrix: Matrix3::new(fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0),
        distortion: vec![
            d.k1 * c * c,
            d.k2 * c.powi(4),
            -d.p2 * c,
            d.p1 * c,
            d.k3 * c.powi(6),
        ],
        rotation,
        translation,
    })
}

/// The ptv camera of an OpenLPT pinhole, with pixels `pixel_size` mm wide,
/// in air, named `name`; and whether it is exact (its distortion is about
/// the principal point, ptv's about the sensor's centre, so it is exact
/// when either is nothing or the two coincide, and the lens is not
/// rational). The rotation written is taken to the nearest rotation.
pub fn to_parameters(
    camera: &OpenlptCamera,
    pixel_size: f64,
    name: &str,
) -> Result<(CameraParameters, bool), String> {
    let m = &camera.matrix;
    let (mut fx, mut fy) = (m[(0, 0)], m[(1, 1)]);
    let mut rotation = nearest_rotation(&camera.rotation);
    let mut translation = camera.translation;
    if fx == 0.0 || fy == 0.0 {
        return Err("the camera matrix has a zero focal length".to_owned());
    }
    if (fx < 0.0) != (fy < 0.0) {
        return Err(format!(
            "fx = {fx} and fy = {fy} have opposite signs with a proper rotation: the camera \
             images the world mirrored (e.g. image rows counted from the bottom), which no \
             camera of ptv's model does"
        ));
    }
    if fx < 0.0 {
        // The same camera turned half about its axis.
        let half_turn = Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0));
        rotation = half_turn * rotation;
        translation = half_turn * translation;
        (fx, fy) = (-fx, -fy);
    }
    let position = -(rotation.transpose() * translation);
    let r = (flip() * rotation).transpose();
    let (omega, phi, kappa) = rotation_angles(&r);
    let c = fx * pixel_size;
    let pixel_size_y = c / fy;
    let (width, height) = (camera.n_col, camera.n_row);
    let xh = (m[(0, 2)] + PIXEL_CENTRE - f64::from(width) / 2.0) * pixel_size;
    let yh = -(m[(1, 2)] + PIXEL_CENTRE - f64::from(height) / 2.0) * pixel_size_y;
    let k = |i: usize| {
        if camera.is_distorted() {
            camera.distortion.get(i).copied().unwrap_or(0.0)
        } else {
            0.0
        }
    };
    let distortion = Distortion {
        k1: k(0) / (c * c),
        k2: k(1) / c.powi(4),
        k3: k(4) / c.powi(6),
        p1: k(3) / c,
        p2: -k(2) / c,
        ..Distortion::default()
    };
    let rational = (5..8).any(|i| k(i) != 0.0);
    let exact = !rational && (distortion.is_identity() || (xh == 0.0 && yh == 0.0));
    Ok((
        CameraParameters {
            name: name.to_owned(),
            sensor: Sensor {
                width,
                height,
                pixel_size_x: pixel_size,
                pixel_size_y,
            },
            exterior: Exterior {
                position,
                omega,
                phi,
                kappa,
            },
            interior: Interior { c, xh, yh },
            distortion,
            media: Media::air(),
        },
        exact,
    ))
}

/// The rotation nearest `m` (its polar factor, by SVD).
fn nearest_rotation(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = m.svd(true, true);
    match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => u * v_t,
        _ => *m,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::between::grid;
    use crate::photogrammetry::simulate::RigSpec;
    use crate::photogrammetry::Camera;

    /// OpenLPT's test camera (`test/inputs/test_Camera/cam1.txt`, its numbers).
    const EXAMPLE: &str = "# Camera Model: (PINHOLE/POLYNOMIAL)\nPINHOLE\n# Camera Calibration Error: \nNone\n# Pose Calibration Error: \nNone\n# Image Size: (n_row,n_col)\n1024,1024\n# Camera Matrix: \n10148.266049999998,0.0,511.5\n0.0,-10148.266049999998,511.5\n0.0,0.0,1.0\n# Distortion Coefficients: \n0.0,0.0,0.0,0.0,0.0\n# Rotation Vector: \n-1.0265010615606807,1.4586113247680201,1.4694400201721682\n# Rotation Matrix: \n-0.344037,-0.938931,-0.006887\n5.8e-05,-0.007356,0.999973\n-0.938956,0.344027,0.002585\n# Inverse of Rotation Matrix: \n-0.34403671713573486,5.782268442092614e-05,-0.9389562839931344\n-0.9389307724768311,-0.00735592541611775,0.34402730215999194\n-0.006887006581923409,0.9999728857268381,0.0025851940994011864\n# Translation Vector: \n0.191323,-0.142328,414.764569\n# Inverse of Translation Vector: \n389.51162880687355,-142.51174360659186,-0.9286051327794733\n";

    #[test]
    fn reads_openlpts_example_and_refuses_its_mirror() {
        let camera = parse(EXAMPLE, "cam1.txt").unwrap();
        assert_eq!((camera.n_row, camera.n_col), (1024, 1024));
        assert_eq!(camera.distortion.len(), 5);
        assert!(!camera.is_distorted());
        // fx > 0, fy < 0, det R = +1: mirrored.
        let error = to_parameters(&camera, 0.01, "cam1").unwrap_err();
        assert!(error.contains("mirrored"), "{error}");
    }

    /// A camera in air, distorted about the sensor's centre, goes to
    /// OpenLPT and back exactly: images within 1e-9 px (numbers written in
    /// their shortest exact form; the arithmetic of the conversions, ~1e-16
    /// relative of ~1000 px, is all that is left).
    #[test]
    fn a_camera_in_air_round_trips_exactly() {
        let spec = RigSpec {
            tank: None,
            ..RigSpec::convergent(3)
        };
        for camera in spec.build().unwrap() {
            let mut p = camera.parameters().clone();
            p.interior.xh = 0.0;
            p.interior.yh = 0.0;
            p.distortion = Distortion {
                k1: 2e-4,
                k2: -3e-7,
                k3: 1e-9,
                p1: 6e-6,
                p2: -8e-6,
                scx: 1.0004,
                shear: 0.0,
            };
            p.sensor.pixel_size_y = 0.0121;
            let camera = Camera::new(p.clone()).unwrap();
            let lpt = from_parameters(&p).unwrap();
            let lpt = parse(&format(&lpt), "x").unwrap();
            assert!(lpt.is_distorted());
            let (back, exact) = to_parameters(&lpt, p.sensor.pixel_size_x, "cam").unwrap();
            assert!(exact);
            let back = Camera::new(back).unwrap();
            for point in grid(&spec.volume) {
                let a = camera.project(&point).unwrap();
                let b = lpt.project(&point).unwrap();
                let c = back.project(&point).unwrap();
                assert!(
                    (a - b).norm() < 1e-9 && (a - c).norm() < 1e-9,
                    "{a} {b} {c}"
                );
            }
        }
    }

    #[test]
    fn bad_files_name_the_line() {
        let with = |line: usize, value: &str| {
            let mut lines: Vec<&str> = EXAMPLE.lines().collect();
            lines[line - 1] = value;
            lines.join("\n")
        };
        for (text, expected) in [
            (with(2, "PINPLATE"), "line 2: OpenLPT's PINPLATE"),
            (with(2, "POLYNOMIAL"), "line 2: OpenLPT's POLYNOMIAL"),
            (with(8, "1024"), "line 8: expected the image size"),
            (
                with(10, "1,2"),
                "line 10: expected a row of the camera matrix: 3 numbers, found 2",
            ),
            (
                with(11, "0.0,x,511.5"),
                "line 11: a row of the camera matrix must be a finite number, got `x`",
            ),
            (
                with(14, "1,2,3"),
                "line 14: expected 4, 5 or 8 distortion coefficients, found 3",
            ),
            (with(18, "NaN,0,0"), "line 18"),
            (with(18, "1,0,0"), "the rotation matrix is not a rotation"),
            (
                with(28, "1,2,3"),
                "line 28: the inverse rotation and translation do not match",
            ),
            (
                EXAMPLE.lines().take(20).collect::<Vec<_>>().join("\n"),
                "the file ends where",
            ),
            (format!("{EXAMPLE}5\n"), "line 29: unexpected `5`"),
        ] {
            let message = parse(&text, "cam1.txt").unwrap_err().to_string();
            assert!(message.contains(expected), "{expected}: {message}");
        }
    }
}
