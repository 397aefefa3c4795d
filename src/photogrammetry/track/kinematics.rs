//! Velocity and acceleration along a trajectory from a local polynomial
//! fit (Lüthi, Tsinober and Kinzelbach 2005, J. Fluid Mech. 528, section
//! 2.3), not from raw differences, which amplify the position noise.
//!
//! Around a point at frame `f0`, the trajectory's `2w + 1` points centred
//! on it (`w` before, `w` after; near its ends the window shifts inward
//! to keep `2w + 1` points, and across a gap it spans more frames) are
//! fitted per axis by
//!
//! ```text
//! x(t) = b0 + b1 t + b2 t² (+ b3 t³),   t = f - f0,
//! ```
//!
//! weighted by each point's `1 / sigma²` from the intersection. Then the
//! velocity is `b1` (mm per frame) and the acceleration `2 b2` (mm per
//! frame²), and their standard deviations come from the coefficients'
//! covariance `(Aᵀ W A)⁻¹`: the particles' sigmas propagated. The order
//! drops to what the window's points determine (two points: a line, no
//! acceleration).
//!
//! For a 5-point window, equal sigmas and order 2, the velocity's standard
//! deviation is `sigma / sqrt(10)` and the acceleration's
//! `2 sigma / sqrt(14)`; raw central differences would give `sigma /
//! sqrt(2)` and `sigma sqrt(6)`.

use nalgebra::{SMatrix, SVector, Vector3};

/// One point of a trajectory for the fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Sample {
    /// Frame number.
    pub frame: i64,
    /// Position (mm).
    pub position: Vector3<f64>,
    /// Standard deviations of the position (mm), each above zero.
    pub sigma: Vector3<f64>,
}

/// The derivatives at one point, with their standard deviations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Derivatives {
    /// Velocity (mm per frame).
    pub velocity: Vector3<f64>,
    /// Its standard deviations.
    pub velocity_sigma: Vector3<f64>,
    /// Acceleration (mm per frame²), where the window has at least three
    /// points.
    pub acceleration: Option<Vector3<f64>>,
    /// Its standard deviations.
    pub acceleration_sigma: Option<Vector3<f64>>,
}

/// The fit at frame `at` of `samples` (the window's points, any order),
/// with a polynomial of at most `order` (1..=3). `None` with fewer than two
/// samples or a singular system (two samples at one frame).
pub(super) fn fit(samples: &[Sample], at: i64, order: usize) -> Option<Derivatives> {
    if samples.len() < 2 {
        return None;
    }
    let order = order.clamp(1, 3).min(samples.len() - 1);
    let mut velocity = Vector3::zeros();
    let mut velocity_sigma = Vector3::zeros();
    let mut acceleration = Vector3::zeros();
    let mut acceleration_sigma = Vector3::zeros();
    for axis in 0..3 {
        // Normal equations of the weighted least squares, per axis (the
        // weights differ per axis), in fixed-size matrices: no allocation.
        let (b1, var1, b2, var2) = match order {
            1 => solve::<2>(samples, at, axis)?,
            2 => solve::<3>(samples, at, axis)?,
            _ => solve::<4>(samples, at, axis)?,
        };
        velocity[axis] = b1;
        velocity_sigma[axis] = var1.max(0.0).sqrt();
        if order >= 2 {
            acceleration[axis] = 2.0 * b2;
            acceleration_sigma[axis] = 2.0 * var2.max(0.0).sqrt();
        }
    }
    Some(Derivatives {
        velocity,
        velocity_sigma,
        acceleration: (order >= 2).then_some(acceleration),
        acceleration_sigma: (order >= 2).then_some(acceleration_sigma),
    })
}

/// One axis's fit with `D` terms: the first- and second-order coefficients
/// and their variances (the second's 0 for a line).
fn solve<const D: usize>(samples: &[Sample], at: i64, axis: usize) -> Option<(f64, f64, f64, f64)> {
    let mut normal = SMatrix::<f64, D, D>::zeros();
    let mut rhs = SVector::<f64, D>::zeros();
    for s in samples {
        let t = (s.frame - at) as f64;
        let w = s.sigma[axis].powi(-2);
        let mut powers = [1.0; D];
        for k in 1..D {
            powers[k] = powers[k - 1] * t;
        }
        for r in 0..D {
            rhs[r] += w * powers[r] * s.position[axis];
            for c in 0..D {
                normal[(r, c)] += w * powers[r] * powers[c];
            }
        }
    }
    let inverse = normal.try_inverse()?;
    let b = inverse * rhs;
    Some(if D > 2 {
        (b[1], inverse[(1, 1)], b[2], inverse[(2, 2)])
    } else {
        (b[1], inverse[(1, 1)], 0.0, 0.0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples(frames: &[i64], f: impl Fn(f64) -> Vector3<f64>, sigma: f64) -> Vec<Sample> {
        frames
            .iter()
            .map(|&frame| Sample {
                frame,
                position: f(frame as f64),
                sigma: Vector3::repeat(sigma),
            })
            .collect()
    }

    #[test]
    fn a_parabola_is_differentiated_exactly() {
        let path = |t: f64| Vector3::new(1.0 + 2.0 * t + 0.5 * t * t, -t, 3.0 - 0.25 * t * t);
        let s = samples(&[8, 9, 10, 11, 12], path, 0.01);
        let d = fit(&s, 10, 2).unwrap();
        assert!((d.velocity - Vector3::new(12.0, -1.0, -5.0)).norm() < 1e-9);
        assert!((d.acceleration.unwrap() - Vector3::new(1.0, 0.0, -0.5)).norm() < 1e-9);
        // sigma / sqrt(10) and 2 sigma / sqrt(14), the module doc's values.
        assert!((d.velocity_sigma.x - 0.01 / 10f64.sqrt()).abs() < 1e-12);
        assert!((d.acceleration_sigma.unwrap().x - 0.02 / 14f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn a_cubic_is_differentiated_exactly_by_order_3() {
        let path = |t: f64| Vector3::new(t * t * t - 2.0 * t, 0.5 * t * t, 1.0);
        for frames in [&[8, 9, 10, 11, 12][..], &[10, 11, 12, 13], &[7, 8, 10, 11]] {
            let d = fit(&samples(frames, path, 0.01), 10, 3).unwrap();
            assert!(
                (d.velocity - Vector3::new(298.0, 10.0, 0.0)).norm() < 1e-6,
                "{frames:?}: {}",
                d.velocity
            );
        }
    }

    #[test]
    fn at_an_end_and_across_a_gap_the_window_is_what_there_is() {
        let path = |t: f64| Vector3::new(t * t, 0.0, 0.0);
        // One-sided at the start, with frame 2 missing.
        let d = fit(&samples(&[0, 1, 3, 4], path, 0.01), 0, 2).unwrap();
        assert!(
            (d.velocity.x - 0.0).abs() < 1e-9 && (d.acceleration.unwrap().x - 2.0).abs() < 1e-9
        );
        // Two points: a line, no acceleration.
        let d = fit(&samples(&[5, 6], path, 0.01), 6, 2).unwrap();
        assert!((d.velocity.x - 11.0).abs() < 1e-9 && d.acceleration.is_none());
        assert!(fit(&samples(&[5], path, 0.01), 5, 2).is_none());
    }
}
