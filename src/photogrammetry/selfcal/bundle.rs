//! The bundle adjustment: the cameras' free parameters and the particles'
//! 3D positions adjusted together on the particles' image positions, the
//! refraction inside the model (the collinearity equations with the
//! multimedia module, Eq. 1-12, as the calibration's observation equations,
//! with the object coordinates unknown as in the intersection's Eq. 21-23).
//!
//! * Levenberg-Marquardt (the driver of `levenberg_marquardt.rs`, Nielsen's
//!   damping) on the normal equations reduced to the cameras (the points'
//!   3x3 blocks eliminated by the Schur complement, so a step costs the
//!   cameras' few dozen unknowns, not the thousands of points'); the
//!   damping scales the diagonal of both blocks.
//! * The camera Jacobian is the calibration's numerical one
//!   ([`ParameterModel`]); the point Jacobian is the camera model's
//!   analytical one ([`Camera::project_with_jacobian`]).
//! * The gauge (a similarity, 7 dof, which particles do not fix) is fixed
//!   by 7 linear constraints on the cameras' exterior orientation
//!   (`gauge.rs`), solved as a bordered system (Lagrange multipliers).
//! * Each observation carries a weight (the robust loop's, `mod.rs`).
//! * **Media terms** ([`MediaTerm`]): the glass vector (per wall: the
//!   cameras that share one, OpenPTV's per-camera `.ori` vector grouped),
//!   the walls' and the object medium's refractive indices and the walls'
//!   thickness may be unknowns too, shared by the cameras they belong to
//!   (the design paper's Eq. 6-12 with those quantities free). Their
//!   Jacobian columns are central differences of the full projection
//!   (refraction re-solved), appended after the cameras' columns; every
//!   observation carries its non-zero columns only.

use nalgebra::{
    DMatrix, DVector, Matrix2x3, Matrix3, Point2, Point3, RowVector3, Vector2, Vector3,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::gauge::Gauge;
use crate::photogrammetry::calibrate::adjustment::{from_vector, to_vector, ParameterModel};
use crate::photogrammetry::calibrate::ParameterSet;
use crate::photogrammetry::camera::{Camera, CameraParameters};
use crate::photogrammetry::levenberg_marquardt::{minimise, LeastSquares, Settings, Trial};

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
    /// The media unknowns (after the cameras' columns).
    pub media: Vec<MediaUnknown>,
}

/// A term of the optical media that self-calibration can adjust.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MediaTerm {
    /// The glass vector (3 components, mm) of each wall: the wall's
    /// normal and distance.
    Glass,
    /// The walls' refractive index (one, shared by all walls).
    WallIndex,
    /// The object medium's refractive index.
    ObjectIndex,
    /// The walls' thickness (mm, shared by all walls).
    WallThickness,
}

impl MediaTerm {
    /// Every term.
    pub const ALL: [MediaTerm; 4] = [
        MediaTerm::Glass,
        MediaTerm::WallIndex,
        MediaTerm::ObjectIndex,
        MediaTerm::WallThickness,
    ];

    /// The name on the command line (`--free glass,n_wall,n_object,thickness`).
    pub fn name(self) -> &'static str {
        match self {
            MediaTerm::Glass => "glass",
            MediaTerm::WallIndex => "n_wall",
            MediaTerm::ObjectIndex => "n_object",
            MediaTerm::WallThickness => "thickness",
        }
    }

    /// The term of a command-line name.
    pub fn from_name(name: &str) -> Option<MediaTerm> {
        MediaTerm::ALL.into_iter().find(|t| t.name() == name)
    }
}

/// One scalar media unknown and the cameras it acts on.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct MediaUnknown {
    pub term: MediaTerm,
    /// For the glass vector: its component (0, 1, 2 = x, y, z).
    pub axis: usize,
    /// The cameras that share it (0-based).
    pub cameras: Vec<usize>,
}

impl MediaUnknown {
    /// Its name in the report: `glass_x` etc., or the term's name.
    pub fn name(&self) -> String {
        match self.term {
            MediaTerm::Glass => format!("glass_{}", ["x", "y", "z"][self.axis.min(2)]),
            t => t.name().into(),
        }
    }

    /// Its value in camera `p`.
    pub fn value(&self, p: &CameraParameters) -> f64 {
        match self.term {
            MediaTerm::Glass => p.media.glass_vector[self.axis],
            MediaTerm::WallIndex => p.media.walls.first().map_or(0.0, |w| w.n),
            MediaTerm::ObjectIndex => p.media.n_object,
            MediaTerm::WallThickness => p.media.walls.first().map_or(0.0, |w| w.thickness),
        }
    }

    /// Adds `delta` to it in camera `p`.
    pub fn apply(&self, p: &mut CameraParameters, delta: f64) {
        match self.term {
            MediaTerm::Glass => p.media.glass_vector[self.axis] += delta,
            MediaTerm::WallIndex => p.media.walls.iter_mut().for_each(|w| w.n += delta),
            MediaTerm::ObjectIndex => p.media.n_object += delta,
            MediaTerm::WallThickness => p.media.walls.iter_mut().for_each(|w| w.thickness += delta),
        }
    }

    /// The central-difference step: 0.01 mm, or 1e-5 for an index (a
    /// change of about 1e-3 px in the images, well above rounding).
    fn step(&self) -> f64 {
        match self.term {
            MediaTerm::Glass | MediaTerm::WallThickness => 1e-2,
            MediaTerm::WallIndex | MediaTerm::ObjectIndex => 1e-5,
        }
    }
}

/// The scalar unknowns of `terms` for the rig `cameras`: the glass vector
/// per wall (cameras whose glass vectors agree to 1 um share one), the
/// indices and thickness shared by every camera that refracts (walls'
/// terms by those with walls).
pub(super) fn media_unknowns(
    cameras: &[CameraParameters],
    terms: &[MediaTerm],
) -> Vec<MediaUnknown> {
    let refracting: Vec<usize> = (0..cameras.len())
        .filter(|&c| !cameras[c].media.is_homogeneous())
        .collect();
    let walled: Vec<usize> = refracting
        .iter()
        .copied()
        .filter(|&c| !cameras[c].media.walls.is_empty())
        .collect();
    let mut out = Vec::new();
    for term in MediaTerm::ALL {
        if !terms.contains(&term) {
            continue;
        }
        match term {
            MediaTerm::Glass => {
                let mut groups: Vec<Vec<usize>> = Vec::new();
                for &c in &refracting {
                    let g = cameras[c].media.glass_vector;
                    match groups
                        .iter_mut()
                        .find(|grp| (cameras[grp[0]].media.glass_vector - g).norm() < 1e-3)
                    {
                        Some(grp) => grp.push(c),
                        None => groups.push(vec![c]),
                    }
                }
                for grp in groups {
                    for axis in 0..3 {
                        out.push(MediaUnknown {
                            term,
                            axis,
                            cameras: grp.clone(),
                        });
                    }
                }
            }
            MediaTerm::WallIndex | MediaTerm::WallThickness if !walled.is_empty() => {
                out.push(MediaUnknown {
                    term,
                    axis: 0,
                    cameras: walled.clone(),
                })
            }
            MediaTerm::ObjectIndex if !refracting.is_empty() => out.push(MediaUnknown {
                term,
                axis: 0,
                cameras: refracting.clone(),
            }),
            _ => {}
        }
    }
    out
}

/// A camera with one media unknown moved by `+step` and `-step`.
type Shifted = (f64, Camera, Camera);

/// One observation's linearisation.
struct Linear {
    /// d pixel / d unknown, for the unknowns it depends on (column, 2-vector):
    /// its camera's free parameters and the media terms of its camera.
    cols: Vec<(usize, Vector2<f64>)>,
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
    pub camera_unknowns: usize,
    /// Total unknowns: the cameras', then the media's.
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
    /// Column of the first media unknown.
    pub media_offset: usize,
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
        let (offsets, camera_unknowns) = self.offsets();
        let unknowns = camera_unknowns + self.media.len();
        // Per media unknown, per camera: (step, camera +step, camera -step).
        let shifted: Option<Vec<Vec<Option<Shifted>>>> = self
            .media
            .iter()
            .map(|m| {
                (0..self.cameras.len())
                    .map(|c| {
                        if !m.cameras.contains(&c) {
                            return Some(None);
                        }
                        let h = m.step();
                        let mut plus = self.cameras[c].clone();
                        m.apply(&mut plus, h);
                        let mut minus = self.cameras[c].clone();
                        m.apply(&mut minus, -h);
                        Some(Some((h, Camera::new(plus).ok()?, Camera::new(minus).ok()?)))
                    })
                    .collect()
            })
            .collect();
        let shifted = shifted?;
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
                        let mut cols: Vec<(usize, Vector2<f64>)> = (0..jc.ncols())
                            .map(|k| (offsets[c] + k, Vector2::new(jc[(0, k)], jc[(1, k)])))
                            .collect();
                        for (m, per_camera) in shifted.iter().enumerate() {
                            if let Some((h, plus, minus)) = &per_camera[c] {
                                let d = (plus.project(&track.point).ok()?
                                    - minus.project(&track.point).ok()?)
                                    / (2.0 * h);
                                cols.push((camera_unknowns + m, d));
                            }
                        }
                        Some(Linear {
                            cols,
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
                for &(i, di) in &o.cols {
                    gc[i] += o.w * di.dot(&o.r);
                    for &(j, dj) in &o.cols {
                        u[(i, j)] += o.w * di.dot(&dj);
                    }
                }
            }
        }
        Some(Normal {
            lin,
            offsets,
            camera_unknowns,
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
                    // Per unknown the track touches: y_i = sum over its
                    // observations of w d_iᵀ Jp (1 x 3); S -= y_i V⁻¹ y_jᵀ,
                    // b -= y_i V⁻¹ g_p.
                    let mut ys: Vec<(usize, RowVector3<f64>)> = Vec::new();
                    for o in track {
                        for &(i, d) in &o.cols {
                            let y = d.transpose() * o.jp * o.w;
                            match ys.iter_mut().find(|(k, _)| *k == i) {
                                Some((_, acc)) => *acc += y,
                                None => ys.push((i, y)),
                            }
                        }
                    }
                    for &(i, yi) in &ys {
                        let ya = yi * vinv;
                        b[i] -= (ya * gp)[0];
                        for &(j, yj) in &ys {
                            s[(i, j)] -= ya.dot(&yj);
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

    /// Levenberg-Marquardt to convergence (at most `max_iterations`): the
    /// driver's rules (`levenberg_marquardt.rs`), converged when the
    /// Gauss-Newton step promises to reduce the weighted cost by less than
    /// 1e-9 of it (each parameter then within about 3e-3 of its sigma of
    /// the minimum for a redundancy of 10,000).
    pub fn adjust(&mut self, max_iterations: usize) -> Option<Solution> {
        let settings = Settings {
            lambda: 1e-4,
            max_iterations,
            tolerance: 1e-9,
        };
        let outcome = minimise(self, &settings)?;
        let mut current = outcome.cost;
        let iterations = outcome.iterations;
        // The statistics need the final state's linearisation; where a
        // step left one that cannot be linearised, the state before it.
        let normal = match outcome.normal.or_else(|| self.linearise()) {
            Some(normal) => normal,
            None => {
                let ((cameras, tracks), cost) = outcome.previous?;
                self.cameras = cameras;
                self.tracks = tracks;
                current = cost;
                self.linearise()?
            }
        };
        let reduced = Self::reduce(&normal, 0.0)?;
        let cofactor = self.cofactor(&normal, &reduced);
        let observations: usize = self.tracks.iter().map(|t| t.observations.len()).sum();
        let unknowns = normal.unknowns + 3 * self.tracks.len();
        let redundancy = (2 * observations + self.gauge.rows()).saturating_sub(unknowns);
        Some(Solution {
            reduced: reduced.s,
            cofactor,
            media_offset: normal.camera_unknowns,
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
        // The constraints act on the cameras' columns only.
        for r in 0..m {
            for j in 0..c.ncols().min(n) {
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
    /// substitution), and the linear model's reduction of the weighted
    /// cost, `Σ w (‖r‖² - ‖r - JΔ‖²)` over the observations (the reduction
    /// `Δᵀ(2g - NΔ)` of the full system, the gauge's drift correction
    /// included).
    fn stepped(
        &self,
        normal: &Normal,
        reduced: &ReducedSystem,
        step: &DVector<f64>,
    ) -> (Vec<CameraParameters>, Vec<Track>, f64) {
        let mut cameras: Vec<CameraParameters> = self
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
        for (k, m) in self.media.iter().enumerate() {
            for &c in &m.cameras {
                m.apply(&mut cameras[c], step[normal.camera_unknowns + k]);
            }
        }
        let mut predicted = 0.0;
        let tracks = self
            .tracks
            .iter()
            .zip(&normal.lin)
            .zip(&reduced.per_track)
            .map(|((track, lin), (vinv, gp))| {
                // The camera part of each observation's linear change.
                let camera_change: Vec<Vector2<f64>> = lin
                    .iter()
                    .map(|o| o.cols.iter().map(|&(i, d)| d * step[i]).sum())
                    .collect();
                let mut rhs = *gp;
                for (o, jd) in lin.iter().zip(&camera_change) {
                    rhs -= o.jp.transpose() * jd * o.w;
                }
                let point_step = vinv * rhs;
                for (o, jd) in lin.iter().zip(&camera_change) {
                    let change = jd + o.jp * point_step;
                    predicted += o.w * (2.0 * o.r.dot(&change) - change.norm_squared());
                }
                let mut t = track.clone();
                t.point += point_step;
                t
            })
            .collect();
        (cameras, tracks, predicted)
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

/// The bundle as a least-squares problem for the driver: the cameras, the
/// media terms and the points from the current state, the points
/// eliminated from each damped system.
impl LeastSquares for Bundle<'_> {
    type Normal = Normal;
    type Estimate = (Vec<CameraParameters>, Vec<Track>);

    fn cost(&self) -> Option<f64> {
        Bundle::cost(self)
    }

    fn cost_of(&self, (cameras, tracks): &Self::Estimate) -> Option<f64> {
        cost_of(cameras, tracks)
    }

    fn normal(&self) -> Option<Normal> {
        self.linearise()
    }

    fn trial(&self, normal: &Normal, lambda: f64) -> Option<Trial<Self::Estimate>> {
        let reduced = Self::reduce(normal, lambda)?;
        let step = self.solve(normal, &reduced)?;
        let (cameras, tracks, predicted) = self.stepped(normal, &reduced, &step);
        Some(Trial {
            estimate: (cameras, tracks),
            predicted,
        })
    }

    fn accept(&mut self, (cameras, tracks): Self::Estimate) -> Self::Estimate {
        (
            std::mem::replace(&mut self.cameras, cameras),
            std::mem::replace(&mut self.tracks, tracks),
        )
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
