//! The bundle adjustment: the cameras' free parameters and the particles'
//! 3D positions adjusted together on the particles' image positions, the
//! refraction inside the model (the collinearity equations with the
//! multimedia module, Eq. 1-12, as the calibration's observation equations,
//! with the object coordinates unknown as in the intersection's Eq. 21-23).
//!
//! * Levenberg-Marquardt on the normal equations reduced to the cameras
//!   (the points' 3x3 blocks eliminated by the Schur complement, so a step
//!   costs the cameras' few dozen unknowns, not the thousands of points').
//! * The camera Jacobian is the calibration's numerical one
//!   ([`ParameterModel`]); the point Jacobian is the camera model's
//!   analytical one ([`Camera::project_with_jacobian`]).
//! * The gauge (a similarity, 7 dof, which particles do not fix) is fixed
//!   by 7 linear constraints on the cameras' exterior orientation
//!   (`gauge.rs`), solved as a bordered system (Lagrange multipliers).
//! * Each observation carries a weight (the robust loop's, `mod.rs`).

use nalgebra::{DMatrix, DVector, Matrix2x3, Matrix3, Point2, Point3, Vector2, Vector3};
use rayon::prelude::*;

use super::gauge::Gauge;
use crate::photogrammetry::calibrate::adjustment::{from_vector, to_vector, ParameterModel};
use crate::photogrammetry::calibrate::ParameterSet;
use crate::photogrammetry::camera::{Camera, CameraParameters};

/// One particle: its observations (camera, pixel, weight) and its position.
#[derive(Clone, Debug)]
pub(super) struct Track {
    /// Per observing camera: the camera, the measured pixel, the weight.
    pub observations: Vec<(usize, Point2<f64>, f64)>,
    /// The current position (mm).
    pub point: Point3<f64>,
}

/// The state of the adjustment.
pub(super) struct Bundle<'a> {
    /// The cameras as they are now.
    pub cameras: Vec<CameraParameters>,
    /// Per camera the parameters being estimated.
    pub free: Vec<ParameterSet>,
    /// The particles.
    pub tracks: Vec<Track>,
    /// The gauge's constraints (from the starting rig).
    pub gauge: &'a Gauge,
}

/// One observation's linearisation.
struct Linear {
    camera: usize,
    /// d pixel / d camera's free parameters (2 x u_c).
    jc: DMatrix<f64>,
    /// d pixel / d point (2 x 3).
    jp: Matrix2x3<f64>,
    /// Observed minus computed (px).
    r: Vector2<f64>,
    w: f64,
}

/// The system at one state.
pub(super) struct Normal {
    /// Per track its observations' linearisation.
    lin: Vec<Vec<Linear>>,
    /// Column offset of each camera's parameters.
    pub offsets: Vec<usize>,
    /// Total camera unknowns.
    pub unknowns: usize,
    /// The camera block of the normal matrix (block diagonal, undamped).
    u: DMatrix<f64>,
    /// Right-hand side of the camera parameters.
    gc: DVector<f64>,
}

/// What a converged adjustment gives for the statistics.
pub(super) struct Solution {
    /// The reduced normal matrix (points eliminated, undamped), in
    /// parameter units.
    pub reduced: DMatrix<f64>,
    /// The cofactor matrix of the camera parameters under the gauge
    /// constraints (parameter units), if the system is regular.
    pub cofactor: Option<DMatrix<f64>>,
    /// Column offsets per camera.
    pub offsets: Vec<usize>,
    /// Weighted sum of squared residuals (px²).
    pub cost: f64,
    /// Redundancy: observations' coordinates minus unknowns plus
    /// constraints.
    pub redundancy: usize,
    /// Levenberg-Marquardt iterations.
    pub iterations: usize,
}

impl Bundle<'_> {
    fn models(&self) -> Option<Vec<(Camera, ParameterModel)>> {
        self.cameras
            .iter()
            .zip(&self.free)
            .map(|(p, &free)| Some((Camera::new(p.clone()).ok()?, ParameterModel::new(p, free)?)))
            .collect()
    }

    fn offsets(&self) -> (Vec<usize>, usize) {
        let mut offsets = Vec::with_capacity(self.free.len());
        let mut total = 0;
        for f in &self.free {
            offsets.push(total);
            total += f.len();
        }
        (offsets, total)
    }

    /// Linearises every observation at the current state.
    fn linearise(&self) -> Option<Normal> {
        let models = self.models()?;
        let (offsets, unknowns) = self.offsets();
        let lin: Option<Vec<Vec<Linear>>> = self
            .tracks
            .par_iter()
            .map(|track| {
                track
                    .observations
                    .iter()
                    .map(|&(c, pixel, w)| {
                        let (camera, model) = &models[c];
                        let (computed, jc) = model.project(&track.point)?;
                        let (_, jp) = camera.project_with_jacobian(&track.point).ok()?;
                        Some(Linear {
                            camera: c,
                            jc,
                            jp,
                            r: pixel - computed,
                            w,
                        })
                    })
                    .collect()
            })
            .collect();
        let lin = lin?;
        let mut u = DMatrix::zeros(unknowns, unknowns);
        let mut gc = DVector::zeros(unknowns);
        for track in &lin {
            for o in track {
                let off = offsets[o.camera];
                let n = o.jc.ncols();
                let jt = o.jc.transpose();
                let block = &jt * &o.jc * o.w;
                let mut view = u.view_mut((off, off), (n, n));
                view += block;
                let g = &jt * o.r * o.w;
                let mut gv = gc.rows_mut(off, n);
                gv += g;
            }
        }
        Some(Normal {
            lin,
            offsets,
            unknowns,
            u,
            gc,
        })
    }

    /// The reduced system with damping `lambda` (relative to the
    /// diagonal): `S` and `b`, and per track `(V⁻¹, g_p)` for the back
    /// substitution.
    fn reduce(normal: &Normal, lambda: f64) -> Option<ReducedSystem> {
        let n = normal.unknowns;
        let per_track: Vec<Option<(Matrix3<f64>, Vector3<f64>)>> = normal
            .lin
            .par_iter()
            .map(|track| {
                let mut v = Matrix3::zeros();
                let mut gp = Vector3::zeros();
                for o in track {
                    v += o.jp.transpose() * o.jp * o.w;
                    gp += o.jp.transpose() * o.r * o.w;
                }
                for k in 0..3 {
                    v[(k, k)] *= 1.0 + lambda;
                }
                Some((v.try_inverse()?, gp))
            })
            .collect();
        let per_track: Option<Vec<(Matrix3<f64>, Vector3<f64>)>> = per_track.into_iter().collect();
        let per_track = per_track?;
        let (s, b) = normal
            .lin
            .par_iter()
            .zip(&per_track)
            .fold(
                || (DMatrix::<f64>::zeros(n, n), DVector::<f64>::zeros(n)),
                |(mut s, mut b), (track, (vinv, gp))| {
                    // W_a = w Jcᵀ Jp (u_a x 3); S -= W_a V⁻¹ W_bᵀ.
                    let ws: Vec<DMatrix<f64>> = track
                        .iter()
                        .map(|o| {
                            let jp = DMatrix::from_column_slice(2, 3, o.jp.as_slice());
                            o.jc.transpose() * jp * o.w
                        })
                        .collect();
                    let vinv = DMatrix::from_column_slice(3, 3, vinv.as_slice());
                    let gp = DVector::from_column_slice(gp.as_slice());
                    for (a, oa) in track.iter().enumerate() {
                        let ya = &ws[a] * &vinv;
                        let offa = normal.offsets[oa.camera];
                        let mut bv = b.rows_mut(offa, ws[a].nrows());
                        bv -= &ya * &gp;
                        for (bi, ob) in track.iter().enumerate() {
                            let offb = normal.offsets[ob.camera];
                            let block = &ya * ws[bi].transpose();
                            let mut view = s.view_mut((offa, offb), (block.nrows(), block.ncols()));
                            view -= block;
                        }
                    }
                    (s, b)
                },
            )
            .reduce(
                || (DMatrix::<f64>::zeros(n, n), DVector::<f64>::zeros(n)),
                |(s1, b1), (s2, b2)| (s1 + s2, b1 + b2),
            );
        let mut s = s + &normal.u;
        for k in 0..n {
            s[(k, k)] += lambda * normal.u[(k, k)];
        }
        Some(ReducedSystem {
            s,
            b: b + &normal.gc,
            per_track,
        })
    }

    /// Weighted sum of squared residuals, or `None` where a point does not
    /// image.
    pub fn cost(&self) -> Option<f64> {
        cost_of(&self.cameras, &self.tracks)
    }

    /// Levenberg-Marquardt to convergence (at most `max_iterations`).
    pub fn adjust(&mut self, max_iterations: usize) -> Option<Solution> {
        let mut current = self.cost()?;
        let mut lambda = 1e-4;
        let mut nu = 2.0;
        let mut iterations = 0;
        while iterations < max_iterations {
            iterations += 1;
            let normal = self.linearise()?;
            let mut accepted = false;
            let mut small = false;
            for _ in 0..30 {
                let Some(reduced) = Self::reduce(&normal, lambda) else {
                    lambda *= nu;
                    nu *= 2.0;
                    continue;
                };
                let Some(step) = self.solve(&normal, &reduced) else {
                    lambda *= nu;
                    nu *= 2.0;
                    continue;
                };
                let (cameras, tracks) = self.stepped(&normal, &reduced, &step);
                match cost_of(&cameras, &tracks) {
                    Some(c) if c <= current => {
                        let relative = (current - c) / current.max(1e-300);
                        small = relative < 1e-9;
                        self.cameras = cameras;
                        self.tracks = tracks;
                        current = c;
                        lambda = (lambda / 3.0).max(1e-12);
                        nu = 2.0;
                        accepted = true;
                        break;
                    }
                    _ => {
                        lambda *= nu;
                        nu *= 2.0;
                    }
                }
            }
            if !accepted || small {
                // No descent left, or none worth taking: at the minimum
                // (to rounding).
                break;
            }
        }
        let normal = self.linearise()?;
        let reduced = Self::reduce(&normal, 0.0)?;
        let cofactor = self.cofactor(&normal, &reduced);
        let observations: usize = self.tracks.iter().map(|t| t.observations.len()).sum();
        let unknowns = normal.unknowns + 3 * self.tracks.len();
        let redundancy = (2 * observations + self.gauge.rows()).saturating_sub(unknowns);
        Some(Solution {
            reduced: reduced.s,
            cofactor,
            offsets: normal.offsets,
            cost: current,
            redundancy,
            iterations,
        })
    }

    /// The reduced system `s` bordered by the gauge's constraints, columns
    /// scaled by `scale` (to unit diagonal): the bordered matrix and the
    /// constraints' right-hand side.
    fn bordered(
        &self,
        normal: &Normal,
        s: &DMatrix<f64>,
        scale: &DVector<f64>,
    ) -> (DMatrix<f64>, DVector<f64>) {
        let n = normal.unknowns;
        let (c, h) = self
            .gauge
            .constraints(&self.cameras, &self.free, &normal.offsets);
        let m = c.nrows();
        let mut a = DMatrix::zeros(n + m, n + m);
        for i in 0..n {
            for j in 0..n {
                a[(i, j)] = s[(i, j)] * scale[i] * scale[j];
            }
        }
        for r in 0..m {
            for j in 0..n {
                let v = c[(r, j)] * scale[j];
                a[(n + r, j)] = v;
                a[(j, n + r)] = v;
            }
        }
        (a, h)
    }

    /// The camera step: the reduced system bordered by the gauge's
    /// constraints, columns scaled to unit diagonal.
    fn solve(&self, normal: &Normal, reduced: &ReducedSystem) -> Option<DVector<f64>> {
        let n = normal.unknowns;
        let scale = unit_diagonal(n, |k| normal.u[(k, k)]);
        let (a, h) = self.bordered(normal, &reduced.s, &scale);
        let m = h.len();
        let mut rhs = DVector::zeros(n + m);
        for i in 0..n {
            rhs[i] = reduced.b[i] * scale[i];
        }
        for r in 0..m {
            rhs[n + r] = h[r];
        }
        let x = a
            .clone()
            .lu()
            .solve(&rhs)
            .filter(|x| x.iter().all(|v| v.is_finite()))
            .or_else(|| {
                nalgebra::SVD::try_new(a, true, true, f64::EPSILON, 10_000)?
                    .solve(&rhs, 1e-12)
                    .ok()
            })?;
        let step = DVector::from_fn(n, |k, _| x[k] * scale[k]);
        step.iter().all(|v| v.is_finite()).then_some(step)
    }

    /// The cameras and points after the camera `step` (points by back
    /// substitution).
    fn stepped(
        &self,
        normal: &Normal,
        reduced: &ReducedSystem,
        step: &DVector<f64>,
    ) -> (Vec<CameraParameters>, Vec<Track>) {
        let cameras = self
            .cameras
            .iter()
            .zip(&self.free)
            .zip(&normal.offsets)
            .map(|((p, free), &off)| {
                let mut v = to_vector(p);
                for (k, q) in free.iter().enumerate() {
                    v[q.index()] += step[off + k];
                }
                from_vector(p, &v)
            })
            .collect();
        let tracks = self
            .tracks
            .iter()
            .zip(&normal.lin)
            .zip(&reduced.per_track)
            .map(|((track, lin), (vinv, gp))| {
                let mut rhs = *gp;
                for o in lin {
                    let off = normal.offsets[o.camera];
                    let d = step.rows(off, o.jc.ncols());
                    let jd = &o.jc * d;
                    rhs -= o.jp.transpose() * Vector2::new(jd[0], jd[1]) * o.w;
                }
                let mut t = track.clone();
                t.point += vinv * rhs;
                t
            })
            .collect();
        (cameras, tracks)
    }

    /// The camera parameters' cofactor matrix under the gauge constraints:
    /// the top-left block of the bordered system's inverse.
    fn cofactor(&self, normal: &Normal, reduced: &ReducedSystem) -> Option<DMatrix<f64>> {
        let n = normal.unknowns;
        let scale = unit_diagonal(n, |k| reduced.s[(k, k)]);
        let (a, _) = self.bordered(normal, &reduced.s, &scale);
        let inverse = a.try_inverse()?;
        let q = DMatrix::from_fn(n, n, |i, j| inverse[(i, j)] * scale[i] * scale[j]);
        // A regular system gives a positive diagonal.
        (q.diagonal().iter().all(|d| d.is_finite() && *d >= 0.0)).then_some(q)
    }
}

/// The column scales that give a matrix of diagonal `diagonal(k)` a unit
/// diagonal (1 where it is not positive).
fn unit_diagonal(n: usize, diagonal: impl Fn(usize) -> f64) -> DVector<f64> {
    DVector::from_fn(n, |k, _| {
        let d = diagonal(k);
        if d > 0.0 {
            1.0 / d.sqrt()
        } else {
            1.0
        }
    })
}

/// The reduced system at one damping.
struct ReducedSystem {
    s: DMatrix<f64>,
    b: DVector<f64>,
    per_track: Vec<(Matrix3<f64>, Vector3<f64>)>,
}

/// Weighted sum of squared residuals of `tracks` seen by `cameras`.
pub(super) fn cost_of(cameras: &[CameraParameters], tracks: &[Track]) -> Option<f64> {
    let models: Option<Vec<Camera>> = cameras
        .iter()
        .map(|p| Camera::new(p.clone()).ok())
        .collect();
    let models = models?;
    tracks
        .par_iter()
        .map(|t| {
            t.observations.iter().try_fold(0.0, |sum, &(c, pixel, w)| {
                let p = models[c].project(&t.point).ok()?;
                Some(sum + w * (pixel - p).norm_squared())
            })
        })
        .try_reduce(|| 0.0, |a, b| Some(a + b))
}

/// Each observation's residual (observed minus computed, px) at the current
/// state; `None` where one does not image.
pub(super) fn residuals(cameras: &[Camera], tracks: &[Track]) -> Vec<Vec<Option<Vector2<f64>>>> {
    tracks
        .par_iter()
        .map(|t| {
            t.observations
                .iter()
                .map(|&(c, pixel, _)| cameras[c].project(&t.point).ok().map(|p| pixel - p))
                .collect()
        })
        .collect()
}
