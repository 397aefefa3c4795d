//! What the conversions to and from other tools' camera files share
//! ([`super::myptv`], [`super::openlpt`]): the flip between ptv's camera
//! axes and theirs, the measure of how exact a conversion is (by
//! reprojection over a grid of points through the observation volume), and
//! the best fit of a camera the other model cannot carry exactly.
//!
//! **Axes.** ptv's camera looks along its own `-z` axis, with image `y`
//! up (OpenPTV's convention, [`crate::photogrammetry::camera`]); MyPTV's
//! Tsai camera and OpenLPT's pinhole (OpenCV's) look along `+z` with image
//! `y` down (rows). The same camera has `R_theirs = F Rᵀ` with `F =
//! diag(1, -1, -1)` (a half turn about x), `R` ptv's camera-to-world
//! rotation ([`flip_rotation`]).
//!
//! **Pixels.** ptv puts the centre of the top-left pixel at (0.5, 0.5);
//! MyPTV (numpy's centre of mass over pixel indices) and OpenLPT (OpenCV's
//! `cx = (width - 1) / 2`) put it at (0, 0): theirs + [`PIXEL_CENTRE`] =
//! ptv's.
//!
//! **How exact.** [`reprojection_difference`] projects a grid of
//! [`GRID_NODES`]³ points filling the volume with both models and reports the
//! largest and the RMS distance of the images in pixels, over the points
//! both see on the sensor.
//!
//! **Best fit.** Where the other model cannot carry ptv's (refraction,
//! distortion in MyPTV's form, ...), [`best_fit`] adjusts a camera of the
//! carried form to the images the source camera gives of the grid, with the
//! project's resection ([`calibrate::calibrate`]: one way to adjust a
//! camera), the parameters the target model lacks held.

use nalgebra::{Matrix3, Point2, Point3};

use crate::photogrammetry::calibrate::{
    self, CalibrationOptions, ControlPoint, MarkObservation, Parameter,
};
use crate::photogrammetry::{Camera, CameraParameters, Volume};

/// The grid's nodes along each axis of the volume: 11³ = 1,331 points, every
/// tenth of each side, corners included.
pub const GRID_NODES: usize = 11;

/// Their pixel coordinate of a pixel's centre is ours minus this.
pub const PIXEL_CENTRE: f64 = 0.5;

/// `F = diag(1, -1, -1)`: ptv's camera axes to MyPTV's and OpenLPT's.
pub fn flip() -> Matrix3<f64> {
    Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, -1.0, -1.0))
}

/// ptv's camera-to-world rotation to theirs (world to camera, `+z` ahead,
/// `y` down), and back: the map is its own inverse up to transposition
/// (`R = (F R_theirs)ᵀ`).
pub fn flip_rotation(rotation: &Matrix3<f64>) -> Matrix3<f64> {
    flip() * rotation.transpose()
}

/// How far two cameras' images of the volume's grid differ.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Difference {
    /// The largest distance (px).
    pub max_px: f64,
    /// The RMS distance (px).
    pub rms_px: f64,
    /// The grid points both cameras image on the sensor.
    pub points: usize,
}

/// The grid of [`GRID_NODES`]³ points filling `volume` (finite bounds).
pub fn grid(volume: &Volume) -> Vec<Point3<f64>> {
    let step = (volume.max - volume.min) / (GRID_NODES - 1) as f64;
    let mut points = Vec::with_capacity(GRID_NODES.pow(3));
    for i in 0..GRID_NODES {
        for j in 0..GRID_NODES {
            for k in 0..GRID_NODES {
                points.push(Point3::new(
                    volume.min.x + step.x * i as f64,
                    volume.min.y + step.y * j as f64,
                    volume.min.z + step.z * k as f64,
                ));
            }
        }
    }
    points
}

/// Projects the grid with both (ptv's pixel convention), over the points
/// the `reference` camera images on its sensor.
pub fn reprojection_difference(
    reference: &Camera,
    other: &dyn Fn(&Point3<f64>) -> Option<Point2<f64>>,
    volume: &Volume,
) -> Difference {
    let (mut max, mut sum, mut count) = (0.0_f64, 0.0, 0);
    for point in grid(volume) {
        let Ok(a) = reference.project(&point) else {
            continue;
        };
        if !reference.sensor().contains(a) {
            continue;
        }
        let d = match other(&point) {
            Some(b) => (a - b).norm(),
            None => f64::INFINITY,
        };
        max = max.max(d);
        sum += d * d;
        count += 1;
    }
    Difference {
        max_px: max,
        rms_px: if count == 0 {
            0.0
        } else {
            (sum / count as f64).sqrt()
        },
        points: count,
    }
}

/// The camera of `start`'s form (its sensor, media and values of the
/// `fixed` parameters) that best reproduces `source`'s images of the
/// volume's grid, by the project's resection. The fit uses every grid
/// point `source` images on its sensor; the data snooping is off (its
/// level at the smallest double), since the residuals are the models'
/// difference, not gross errors. Fails with the resection's error, or
/// when fewer than 20 grid points are seen.
pub fn best_fit(
    start: &CameraParameters,
    source: &dyn Fn(&Point3<f64>) -> Option<Point2<f64>>,
    fixed: &[Parameter],
    volume: &Volume,
) -> Result<CameraParameters, String> {
    let mut control = Vec::new();
    let mut observed = Vec::new();
    for (id, point) in grid(volume).into_iter().enumerate() {
        let Some(pixel) = source(&point) else {
            continue;
        };
        if !start.sensor.contains(pixel) {
            continue;
        }
        control.push(ControlPoint {
            id: id as u64,
            position: point,
        });
        observed.push(MarkObservation {
            id: id as u64,
            pixel,
        });
    }
    if control.len() < 20 {
        return Err(format!(
            "only {} of the volume's {} grid points are imaged on the sensor; give --volume \
             where the camera looks",
            control.len(),
            GRID_NODES.pow(3)
        ));
    }
    let options = CalibrationOptions {
        fixed: fixed.to_vec(),
        snooping_alpha: f64::MIN_POSITIVE,
        ..CalibrationOptions::default()
    };
    let fitted = calibrate::calibrate(std::slice::from_ref(start), &control, &[observed], &options)
        .map_err(|e| format!("the best fit failed: {e}"))?;
    Ok(fitted
        .cameras
        .into_iter()
        .next()
        .expect("one camera in, one out"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::camera::rotation_matrix;

    #[test]
    fn the_flip_is_a_rotation_and_its_own_inverse() {
        let r = rotation_matrix(0.3, -0.2, 1.1);
        let theirs = flip_rotation(&r);
        assert!((theirs.determinant() - 1.0).abs() < 1e-14);
        assert!(((flip() * theirs).transpose() - r).abs().max() < 1e-15);
    }

    #[test]
    fn the_grid_fills_the_volume_corners_included() {
        let volume = Volume {
            min: Point3::new(-10.0, -5.0, 0.0),
            max: Point3::new(10.0, 5.0, 4.0),
        };
        let points = grid(&volume);
        assert_eq!(points.len(), GRID_NODES.pow(3));
        assert_eq!(points[0], volume.min);
        assert_eq!(*points.last().unwrap(), volume.max);
        assert!(points.iter().all(|p| volume.contains(p)));
    }
}
