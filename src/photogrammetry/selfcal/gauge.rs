//! The gauge: particles fix a rig only up to a similarity transform (3
//! translations, 3 rotations, a scale: 7 degrees of freedom; Wieneke 2008,
//! section 2). It is fixed from the starting calibration by the inner
//! constraints of a free network: the change of the cameras' exterior
//! orientation from the start has no component along any of the 7
//! similarity motions of the rig,
//!
//! ```text
//! Σ_c g_r,cᵀ M (x_c - x0_c) = 0,   r = 1..7,
//! ```
//!
//! where `g_r,c` is how motion `r` moves camera c's position and angles
//! (translations along X, Y, Z; rotations about the cameras' centroid;
//! a scaling about it) and `M = diag(1, 1, 1, L², L², L²)` weighs an angle
//! change as the displacement it causes at `L`, the cameras' mean distance
//! from the particles' centroid. Among all rigs the particles cannot tell
//! apart, this picks the one with the least change of the camera positions
//! and orientations in that metric (to first order); the scale row keeps
//! the sum of squared distances of the cameras from their centroid, and so
//! the RMS of the original baselines, to first order.
//!
//! With refraction the gauge is not exactly free (the walls stay where the
//! calibration put them), but only weakly determined; the constraints
//! decide it. When the user fixes exterior parameters, those fix the gauge
//! instead and no constraint is added.

use nalgebra::{DMatrix, DVector, Point3, Rotation3, Vector3};

use crate::photogrammetry::calibrate::adjustment::to_vector;
use crate::photogrammetry::calibrate::{Parameter, ParameterSet};
use crate::photogrammetry::camera::{rotation_angles, rotation_matrix, CameraParameters};

/// The 7 constraints, linearised at the starting rig.
pub(super) struct Gauge {
    /// Per camera per motion, the change of (X0, Y0, Z0, omega, phi, kappa)
    /// per unit of the motion, already weighted by `M`.
    rows: Vec<[[f64; 6]; 7]>,
    /// The starting exterior orientation per camera.
    start: Vec<[f64; 6]>,
    /// Whether the constraints apply (no exterior parameter fixed).
    pub constrained: bool,
    /// `L` (mm).
    pub length: f64,
}

/// The exterior orientation (X0, Y0, Z0, omega, phi, kappa): the first six
/// of the calibration's parameter vector.
fn exterior(p: &CameraParameters) -> [f64; 6] {
    let v = to_vector(p);
    std::array::from_fn(|k| v[k])
}

/// The difference of two angles in (-pi, pi].
fn angle_difference(a: f64, b: f64) -> f64 {
    let d = (a - b) % std::f64::consts::TAU;
    if d > std::f64::consts::PI {
        d - std::f64::consts::TAU
    } else if d <= -std::f64::consts::PI {
        d + std::f64::consts::TAU
    } else {
        d
    }
}

impl Gauge {
    /// The constraints at the starting rig `start`, whose particles lie
    /// around `centre`; `fixed`: the parameters the user fixed.
    pub fn new(start: &[CameraParameters], centre: &Point3<f64>, fixed: ParameterSet) -> Gauge {
        let n = start.len().max(1) as f64;
        let centroid = start
            .iter()
            .map(|p| p.exterior.position)
            .sum::<Vector3<f64>>()
            / n;
        let length = start
            .iter()
            .map(|p| (p.exterior.position - centre.coords).norm())
            .sum::<f64>()
            / n;
        let m = [
            1.0,
            1.0,
            1.0,
            length * length,
            length * length,
            length * length,
        ];
        let rows = start
            .iter()
            .map(|p| {
                let e = &p.exterior;
                let r = rotation_matrix(e.omega, e.phi, e.kappa);
                let arm = e.position - centroid;
                let mut g = [[0.0; 6]; 7];
                for (k, row) in g.iter_mut().take(3).enumerate() {
                    row[k] = 1.0;
                }
                for k in 0..3 {
                    let axis = Vector3::ith(k, 1.0);
                    let dp = axis.cross(&arm);
                    // The angles of the rotated camera, by central
                    // differences of a small world rotation.
                    let h = 1e-6;
                    let turned = |t: f64| {
                        let q = Rotation3::from_axis_angle(&nalgebra::Unit::new_unchecked(axis), t);
                        rotation_angles(&(q.matrix() * r))
                    };
                    let (a, b) = (turned(h), turned(-h));
                    let row = &mut g[3 + k];
                    row[0] = dp.x;
                    row[1] = dp.y;
                    row[2] = dp.z;
                    row[3] = angle_difference(a.0, b.0) / (2.0 * h);
                    row[4] = angle_difference(a.1, b.1) / (2.0 * h);
                    row[5] = angle_difference(a.2, b.2) / (2.0 * h);
                }
                g[6][0] = arm.x;
                g[6][1] = arm.y;
                g[6][2] = arm.z;
                for row in &mut g {
                    for (v, w) in row.iter_mut().zip(m) {
                        *v *= w;
                    }
                }
                g
            })
            .collect();
        Gauge {
            rows,
            start: start.iter().map(exterior).collect(),
            constrained: (ParameterSet::exterior() - fixed).len() == 6,
            length,
        }
    }

    /// How many constraints: 7, or 0 where fixed parameters hold the gauge.
    pub fn rows(&self) -> usize {
        if self.constrained {
            7
        } else {
            0
        }
    }

    /// The constraints on a step of the free parameters (columns at
    /// `offsets`): `C step = h`, with `h` taking back any drift of the
    /// cameras `current` from the constraints.
    pub fn constraints(
        &self,
        current: &[CameraParameters],
        free: &[ParameterSet],
        offsets: &[usize],
    ) -> (DMatrix<f64>, DVector<f64>) {
        let n: usize = free.iter().map(|f| f.len()).sum();
        let m = self.rows();
        let mut c = DMatrix::zeros(m, n);
        let mut h = DVector::zeros(m);
        for (cam, (camera, set)) in current.iter().zip(free).enumerate() {
            let now = exterior(camera);
            for r in 0..m {
                // The exterior is the first six of `Parameter::ALL`.
                for (k, &p) in Parameter::ALL[..6].iter().enumerate() {
                    let g = self.rows[cam][r][k];
                    let change = if k < 3 {
                        now[k] - self.start[cam][k]
                    } else {
                        angle_difference(now[k], self.start[cam][k])
                    };
                    h[r] -= g * change;
                    if let Some(col) = set.iter().position(|q| q == p) {
                        c[(r, offsets[cam] + col)] = g;
                    }
                }
            }
        }
        (c, h)
    }
}

/// RMS distance of the cameras' projective centres from their centroid
/// (mm): the scale of the baselines.
pub(super) fn baseline_scale(cameras: &[CameraParameters]) -> f64 {
    let n = cameras.len().max(1) as f64;
    let centroid = cameras
        .iter()
        .map(|p| p.exterior.position)
        .sum::<Vector3<f64>>()
        / n;
    (cameras
        .iter()
        .map(|p| (p.exterior.position - centroid).norm_squared())
        .sum::<f64>()
        / n)
        .sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::RigSpec;

    #[test]
    fn a_similarity_of_the_rig_violates_the_constraints_and_a_local_change_does_not() {
        let start: Vec<CameraParameters> = RigSpec::convergent(4)
            .build()
            .unwrap()
            .iter()
            .map(|c| c.parameters().clone())
            .collect();
        let gauge = Gauge::new(&start, &Point3::origin(), ParameterSet::empty());
        let free = vec![ParameterSet::exterior(); 4];
        let offsets = [0, 6, 12, 18];
        // The whole rig shifted by 1 mm along X: the translation row sees
        // it, so h (what a step must take back) is about -4 mm x weight.
        let mut shifted = start.clone();
        for p in &mut shifted {
            p.exterior.position.x += 1.0;
        }
        let (c, h) = gauge.constraints(&shifted, &free, &offsets);
        assert_eq!((c.nrows(), c.ncols()), (7, 24));
        assert!((h[0] + 4.0).abs() < 1e-9, "{h}");
        // One camera moved along a direction orthogonal to all 7 motions
        // leaves them satisfied only if its change is not a similarity:
        // moving camera 0 by +1 mm and camera 1 by -1 mm along X keeps the
        // translation row at 0.
        let mut local = start.clone();
        local[0].exterior.position.x += 1.0;
        local[1].exterior.position.x -= 1.0;
        let (_, h) = gauge.constraints(&local, &free, &offsets);
        assert!(h[0].abs() < 1e-9, "{h}");
    }
}
