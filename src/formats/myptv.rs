//! MyPTV's camera files (its Tsai model, `myptv/TsaiModel/camera.py`),
//! read and written from the format as MyPTV's `save` writes it and its
//! `load` reads it: one file per camera, named after the camera, lines
//!
//! ```text
//! Tsai model camera
//! NAME
//! W H                  resolution (px)
//! O1 O2 O3             the imaging centre (lab units: mm here)
//! t1 t2 t3             rotation angles (rad), R = Rx(t1) Ry(t2) Rz(t3)
//! f                    the principal distance in pixels
//! xh yh                the principal point's offset from the image centre (px)
//! E row 1 (5 numbers)  the correction polynomial's coefficients
//! E row 2
//! E row 3
//! ```
//!
//! The model: with `v = R (X - O)`, the uncorrected image is `eta_ = f
//! v1/v3 + W/2 + xh`, `zeta_ = f v2/v3 + H/2 + yh` (pixels, columns and
//! rows, the centre of the top-left pixel at 0); the measured image `(eta,
//! zeta)` satisfies `eta_ = eta + e1(eta, zeta)`, `zeta_ = zeta + e2(eta,
//! zeta)` with `e = E (eta, zeta, eta², zeta², eta zeta)` (its third row
//! adds to `f` along a pixel's ray, which MyPTV's projection ignores).
//! MyPTV projects by one linearised step of that inverse ([`MyptvCamera::project`]
//! does the same, so that a conversion is measured against what MyPTV
//! computes).
//!
//! What carries over exactly (see [`from_parameters`]): a camera in air
//! (MyPTV has no refraction), without Brown distortion and shear, with
//! square pixels. `f` is in pixels, ptv's `c` in mm: `f = scx c /
//! pixel_size` (the "f in thousands against tens" of MyPTV issue 4), so a
//! MyPTV camera comes in with the pixel size the user gives. The Tsai
//! model's correction `E` has no counterpart in ptv's model (a quadratic in
//! absolute pixel coordinates, against Brown's radial and decentering
//! terms about the sensor centre): a camera with `E ≠ 0` comes in, and a
//! distorted or refracting ptv camera goes out, through the best fit
//! ([`super::between::best_fit`]), measured by reprojection.
//!
//! MyPTV's own `load` drops the last two characters of the `f` line (it
//! expects a trailing space, which its `save` does not write after `f`), so
//! `f = 6123.456` reads back as `6123.4`; this writer puts a space after
//! every number, so MyPTV reads back what was written.

use std::fmt::Write as _;

use nalgebra::{Matrix3, Point2, Point3, Vector3};

use super::between::{flip, flip_rotation, PIXEL_CENTRE};
use super::FormatError;
use crate::photogrammetry::camera::{rotation_angles, rotation_matrix};
use crate::photogrammetry::{CameraParameters, Distortion, Exterior, Interior, Media, Sensor};

/// The first line of a Tsai model camera file.
pub const TSAI_HEADER: &str = "Tsai model camera";

/// One MyPTV Tsai camera, as its file holds it.
#[derive(Clone, Debug, PartialEq)]
pub struct MyptvCamera {
    /// The camera's name (the file's name in MyPTV).
    pub name: String,
    /// Width and height (px).
    pub resolution: [u32; 2],
    /// The imaging centre `O` (mm).
    pub position: [f64; 3],
    /// The angles `theta` (rad).
    pub theta: [f64; 3],
    /// The principal distance (px).
    pub f: f64,
    /// The principal point's offset (px).
    pub xh: f64,
    /// The principal point's offset (px).
    pub yh: f64,
    /// The correction polynomial `E` (3 x 5).
    pub correction: [[f64; 5]; 3],
}

impl MyptvCamera {
    /// MyPTV's rotation `Rx Ry Rz` of `theta` (world to camera).
    pub fn rotation(&self) -> Matrix3<f64> {
        rotation_matrix(self.theta[0], self.theta[1], self.theta[2])
    }

    /// The image of a point as MyPTV's `projection` computes it (with its
    /// correction), in ptv's pixel convention; `None` behind the camera.
    pub fn project(&self, point: &Point3<f64>) -> Option<Point2<f64>> {
        let v = self.rotation() * (point - Vector3::from(self.position));
        let a = v.z / self.f;
        if a.is_nan() || a <= 0.0 {
            return None;
        }
        let eta_ = v.x / a + f64::from(self.resolution[0]) / 2.0 + self.xh;
        let zeta_ = v.y / a + f64::from(self.resolution[1]) / 2.0 + self.yh;
        let z = [eta_, zeta_, eta_ * eta_, zeta_ * zeta_, eta_ * zeta_];
        let e = |row: usize| -> (f64, f64, f64) {
            let [a, b, c, d, ee] = self.correction[row];
            let value: f64 = self.correction[row].iter().zip(z).map(|(k, t)| k * t).sum();
            (
                value,
                a + 2.0 * c * eta_ + ee * zeta_,
                b + 2.0 * d * zeta_ + ee * eta_,
            )
        };
        let (e0, e0_eta, e0_zeta) = e(0);
        let (e1, e1_eta, e1_zeta) = e(1);
        let (a11, a12, a21, a22) = (1.0 + e0_eta, e0_zeta, e1_eta, 1.0 + e1_zeta);
        let rhs1 = eta_ * (1.0 + e0_eta) + zeta_ * e0_zeta - e0;
        let rhs2 = zeta_ * (1.0 + e1_zeta) + eta_ * e1_eta - e1;
        let det = a11 * a22 - a12 * a21;
        let eta = (a22 * rhs1 - a12 * rhs2) / det;
        let zeta = (-a21 * rhs1 + a11 * rhs2) / det;
        let pixel = Point2::new(eta + PIXEL_CENTRE, zeta + PIXEL_CENTRE);
        (pixel.x.is_finite() && pixel.y.is_finite()).then_some(pixel)
    }

    /// Whether the correction polynomial is zero (a pure pinhole).
    pub fn is_pinhole(&self) -> bool {
        self.correction.iter().flatten().all(|&k| k == 0.0)
    }
}

/// Reads a MyPTV camera file. Errors name the source and the line.
pub fn parse(text: &str, source: &str) -> Result<MyptvCamera, FormatError> {
    let lines: Vec<&str> = text.lines().collect();
    let at =
        |line: usize, reason: String| FormatError::invalid(source, format!("line {line}"), reason);
    let header = lines.first().map_or("", |l| l.trim());
    if header != TSAI_HEADER {
        let reason = if header.starts_with("extendedZolof") {
            "an extendedZolof model camera: a polynomial fit of lab to image coordinates, not a \
             physical camera, which ptv's model cannot take; calibrate the Tsai model in MyPTV \
             and import that"
                .to_owned()
        } else {
            format!(
                "expected `{TSAI_HEADER}` (MyPTV's Tsai model camera file), found `{header}`; a \
                 file from before MyPTV's model choice (name on the first line, no \
                 resolution) needs the header line and the `W H` line added"
            )
        };
        return Err(at(1, reason));
    }
    let line = |index: usize, what: &str| -> Result<&str, FormatError> {
        lines
            .get(index)
            .map(|l| l.trim())
            .filter(|l| !l.is_empty())
            .ok_or_else(|| {
                at(
                    index + 1,
                    format!("expected {what}, found the end of the file or an empty line"),
                )
            })
    };
    let numbers = |index: usize, count: usize, what: &str| -> Result<Vec<f64>, FormatError> {
        let text = line(index, what)?;
        let values: Vec<&str> = text.split_whitespace().collect();
        if values.len() != count {
            return Err(at(
                index + 1,
                format!("expected {what}: {count} numbers, found {}", values.len()),
            ));
        }
        values
            .iter()
            .map(|v| super::openptv::finite_number(v, source, index + 1, what))
            .collect()
    };
    let name = line(1, "the camera's name")?.to_owned();
    let size_text = line(2, "the resolution `W H`")?;
    let size: Vec<&str> = size_text.split_whitespace().collect();
    let side = |t: &str| t.parse::<u32>().ok().filter(|&v| v > 0);
    let resolution = match size.as_slice() {
        [w, h] => match (side(w), side(h)) {
            (Some(w), Some(h)) => [w, h],
            _ => {
                return Err(at(
                    3,
                    format!("the resolution must be two positive whole numbers, got `{size_text}`"),
                ))
            }
        },
        _ => {
            return Err(at(
                3,
                format!("expected the resolution `W H`, got `{size_text}`"),
            ))
        }
    };
    let position = numbers(3, 3, "the imaging centre O")?;
    let theta = numbers(4, 3, "the angles theta")?;
    let f = numbers(5, 1, "the principal distance f")?[0];
    if f == 0.0 {
        return Err(at(6, "the principal distance f must not be 0".to_owned()));
    }
    let offset = numbers(6, 2, "the principal point offset xh yh")?;
    let mut correction = [[0.0; 5]; 3];
    for (row, values) in correction.iter_mut().enumerate() {
        let read = numbers(7 + row, 5, "a row of the correction matrix E")?;
        values.copy_from_slice(&read);
    }
    if let Some((index, extra)) = lines
        .iter()
        .enumerate()
        .skip(10)
        .find(|(_, l)| !l.trim().is_empty())
    {
        return Err(at(
            index + 1,
            format!("unexpected `{}` after the correction matrix", extra.trim()),
        ));
    }
    Ok(MyptvCamera {
        name,
        resolution,
        position: [position[0], position[1], position[2]],
        theta: [theta[0], theta[1], theta[2]],
        f,
        xh: offset[0],
        yh: offset[1],
        correction,
    })
}

/// The file's text as MyPTV's `save` writes it (every number in its
/// shortest exact form, a space after each).
pub fn format(camera: &MyptvCamera) -> String {
    let mut text = format!(
        "{TSAI_HEADER}\n{}\n{} {} \n",
        camera.name, camera.resolution[0], camera.resolution[1]
    );
    let mut row = |values: &[f64]| {
        for v in values {
            let _ = write!(text, "{v:?} ");
        }
        text.push('\n');
    };
    row(&camera.position);
    row(&camera.theta);
    row(&[camera.f]);
    row(&[camera.xh, camera.yh]);
    for values in &camera.correction {
        row(values);
    }
    text
}

/// Why a ptv camera cannot be written exactly as a Tsai camera, or `None`.
pub fn not_carried(p: &CameraParameters) -> Option<String> {
    let d = &p.distortion;
    let mut reasons = Vec::new();
    if !p.media.is_homogeneous() {
        reasons.push("refraction (MyPTV has no multimedia model)");
    }
    if [d.k1, d.k2, d.k3, d.p1, d.p2].iter().any(|&k| k != 0.0) {
        reasons.push("Brown distortion (MyPTV's correction is a quadratic in pixels)");
    }
    if d.shear != 0.0 {
        reasons.push("shear");
    }
    if p.sensor.pixel_size_x != p.sensor.pixel_size_y {
        reasons.push("non-square pixels (one f for both axes)");
    }
    (!reasons.is_empty()).then(|| reasons.join(", "))
}

/// The Tsai camera of a ptv camera that [`not_carried`] passes: exact
/// (`f = scx c / p`, the principal point in pixels from the image centre,
/// `theta` of `F Rᵀ`, `E = 0`).
pub fn from_parameters(p: &CameraParameters) -> Result<MyptvCamera, String> {
    if let Some(reason) = not_carried(p) {
        return Err(reason);
    }
    let pixel = p.sensor.pixel_size_x;
    let scx = p.distortion.scx;
    let r = rotation_matrix(p.exterior.omega, p.exterior.phi, p.exterior.kappa);
    let (t1, t2, t3) = rotation_angles(&flip_rotation(&r));
    Ok(MyptvCamera {
        name: p.name.clone(),
        resolution: [p.sensor.width, p.sensor.height],
        position: p.exterior.position.into(),
        theta: [t1, t2, t3],
        f: scx * p.interior.c / pixel,
        xh: scx * p.interior.xh / pixel - PIXEL_CENTRE,
        yh: -scx * p.interior.yh / pixel - PIXEL_CENTRE,
        correction: [[0.0; 5]; 3],
    })
}

/// The ptv camera of a Tsai camera's pinhole part (its correction `E` is
/// not carried: see [`MyptvCamera::is_pinhole`]), with square pixels of
/// `pixel_size` mm, in air.
pub fn to_parameters(camera: &MyptvCamera, pixel_size: f64) -> CameraParameters {
    // A negative f is the same camera turned half about its axis.
    let (rotation, f) = if camera.f < 0.0 {
        let half_turn = Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0));
        (half_turn * camera.rotation(), -camera.f)
    } else {
        (camera.rotation(), camera.f)
    };
    let r = (flip() * rotation).transpose();
    let (omega, phi, kappa) = rotation_angles(&r);
    CameraParameters {
        name: camera.name.clone(),
        sensor: Sensor {
            width: camera.resolution[0],
            height: camera.resolution[1],
            pixel_size_x: pixel_size,
            pixel_size_y: pixel_size,
        },
        exterior: Exterior {
            position: Vector3::from(camera.position),
            omega,
            phi,
            kappa,
        },
        interior: Interior {
            c: f * pixel_size,
            xh: (camera.xh + PIXEL_CENTRE) * pixel_size,
            yh: -(camera.yh + PIXEL_CENTRE) * pixel_size,
        },
        distortion: Distortion::default(),
        media: Media::air(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::RigSpec;
    use crate::photogrammetry::Camera;

    /// MyPTV's example camera (`example/cam1` of MyPTV, its numbers).
    const EXAMPLE: &str = "Tsai model camera\ncam1\n1280 1024 \n48.73038302024274 79.46129924162 528.6859917157037 \n0.10910456391903589 3.1785203890640865 3.147388938688586 \n6000.0\n-63.30118337912904 154.99034464209836 \n0.003556956442108972 -0.0019549895512605544 -3.820515541830847e-06 -7.887148518614566e-07 2.38001899111735e-06 \n0.0002655406503517725 -3.369134091006496e-06 -3.8933620095087364e-08 2.3975469366980597e-06 -2.4011826938097713e-06 \n0.0 0.0 0.0 0.0 0.0 \n";

    #[test]
    fn reads_myptvs_example_and_writes_it_back() {
        let camera = parse(EXAMPLE, "cam1").unwrap();
        assert_eq!(camera.resolution, [1280, 1024]);
        assert_eq!(camera.f, 6000.0);
        assert_eq!(camera.correction[1][4], -2.4011826938097713e-06);
        assert!(!camera.is_pinhole());
        assert_eq!(parse(&format(&camera), "again").unwrap(), camera);
    }

    /// A pinhole in air goes to MyPTV and back exactly: the images agree
    /// to 1e-9 px (each number is written in its shortest exact form, so
    /// only the conversions' arithmetic, ~1e-16 relative of ~1000 px, is
    /// left), and the camera re-imported equals the original.
    #[test]
    fn a_pinhole_in_air_round_trips_exactly() {
        let spec = RigSpec {
            tank: None,
            ..RigSpec::convergent(3)
        };
        for camera in spec.build().unwrap() {
            let mut p = camera.parameters().clone();
            p.distortion = Distortion::default();
            p.interior.xh = 0.12;
            p.interior.yh = -0.07;
            p.distortion.scx = 1.0005;
            let camera = Camera::new(p.clone()).unwrap();
            let tsai = from_parameters(&p).unwrap();
            let tsai = parse(&format(&tsai), "x").unwrap();
            for point in super::super::between::grid(&spec.volume) {
                let a = camera.project(&point).unwrap();
                let b = tsai.project(&point).unwrap();
                assert!((a - b).norm() < 1e-9, "{a} {b}");
            }
            let back = to_parameters(&tsai, p.sensor.pixel_size_x);
            let again = from_parameters(&back).unwrap();
            assert!((again.f - tsai.f).abs() < 1e-9 * tsai.f);
            let camera_back = Camera::new(back).unwrap();
            for point in super::super::between::grid(&spec.volume) {
                let a = camera.project(&point).unwrap();
                let b = camera_back.project(&point).unwrap();
                assert!((a - b).norm() < 1e-9, "{a} {b}");
            }
        }
    }

    #[test]
    fn a_negative_f_is_the_same_camera_turned() {
        let mut camera = parse(EXAMPLE, "cam1").unwrap();
        camera.correction = [[0.0; 5]; 3];
        let point = Point3::new(10.0, 20.0, 0.0);
        let expected = camera.project(&point).unwrap();
        let p = to_parameters(&camera, 0.01);
        let ours = Camera::new(p).unwrap().project(&point).unwrap();
        assert!((ours - expected).norm() < 1e-9, "{ours} {expected}");
    }

    #[test]
    fn bad_files_name_the_line() {
        let with = |line: usize, value: &str| {
            let mut lines: Vec<&str> = EXAMPLE.lines().collect();
            lines[line - 1] = value;
            lines.join("\n")
        };
        for (text, expected) in [
            (
                with(1, "extendedZolof model camera"),
                "line 1: an extendedZolof",
            ),
            (with(1, "cam1"), "line 1: expected `Tsai model camera`"),
            (with(3, "1280"), "line 3: expected the resolution"),
            (with(3, "1280 -4"), "line 3: the resolution must be"),
            (
                with(4, "1 2"),
                "line 4: expected the imaging centre O: 3 numbers, found 2",
            ),
            (
                with(5, "0.1 NaN 3"),
                "line 5: the angles theta must be a finite number, got `NaN`",
            ),
            (with(6, "six"), "line 6"),
            (
                with(6, "0"),
                "line 6: the principal distance f must not be 0",
            ),
            (
                with(10, ""),
                "line 10: expected a row of the correction matrix E",
            ),
            (format!("{EXAMPLE}5\n"), "line 11: unexpected `5`"),
            (String::new(), "line 1"),
        ] {
            let message = parse(&text, "cam1").unwrap_err().to_string();
            assert!(
                message.starts_with(&format!("cam1: {expected}")),
                "{message}"
            );
        }
    }
}
