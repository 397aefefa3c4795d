//! Analytic flows for simulated sequences: particles advected through a
//! known velocity field, with their exact velocities and accelerations, the
//! ground truth for tracking (Malik, Dracos, Papantoniou 1993, Part II).
//!
//! Units are those of the tracker: positions in mm, time in frames,
//! velocities in mm per frame, accelerations in mm per frame². Every flow
//! is scaled to the observation volume (extents `Lx, Ly, Lz`, centre `c`)
//! and to a speed `S` (mm per frame), the `--displacement` of `ptv
//! simulate`; [`Flow::speed_bound`] bounds the speed anywhere in the volume
//! (the `--max-velocity` to track with).
//!
//! The acceleration is the material derivative, what a particle feels:
//!
//! ```text
//! a = Du/Dt = ∂u/∂t + (u·∇)u
//! ```
//!
//! # Burgers vortex ([`FlowKind::Burgers`])
//!
//! A vortex on the axis `x = c_x, y = c_y` (along z), stretched by an axial
//! strain `α`, with core radius `r_c` (Burgers 1948). With `d = p - c`,
//! `r² = d_x² + d_y²` and `s = r²/r_c²`:
//!
//! ```text
//! u_r = -α r / 2,   u_z = α d_z,   u_θ = K r_c² (1 - e^(-s)) / r = r ω(r)
//! ω(r) = K g(s),    g(s) = (1 - e^(-s)) / s       (ω → K on the axis)
//! u = -α/2 d_x - ω d_y,   v = -α/2 d_y + ω d_x,   w = α d_z
//! ```
//!
//! The vorticity is `(1/r) d(r u_θ)/dr = 2 K e^(-s)`, `K` the core's angular
//! velocity. The flow is steady, so `a = (u·∇)u`; in cylindrical
//! components `a_r = u_r du_r/dr - u_θ²/r = (α²/4 - ω²) r`,
//! `a_θ = u_r (du_θ/dr + u_θ/r) = u_r · 2K e^(-s)`, `a_z = α² d_z`:
//!
//! ```text
//! a_x = (α²/4 - ω²) d_x + α K e^(-s) d_y
//! a_y = (α²/4 - ω²) d_y - α K e^(-s) d_x
//! a_z = α² d_z
//! ```
//!
//! Divergence `-α/2 - α/2 + α = 0` (the swirl is divergence-free by
//! itself). Scaled: `r_c = min(Lx, Ly)/8`; the largest swirl `u_θ` is
//! `G K r_c` at `r = 1.121 r_c` (`G = max √s g(s) = 0.638 17`), set to `S`;
//! `α = S / (2 Lz)`, so the axial speed at the volume's z faces is `S/4`.
//! Particles flow in through the side faces and out through the z faces.
//!
//! # Taylor-Green vortex ([`FlowKind::TaylorGreen`])
//!
//! The three-dimensional Taylor-Green field (Taylor and Green 1937), with
//! `x' = x - min_x`, `y' = y - min_y`, `z' = z - c_z` and wavenumbers
//! `k_x = 2π/Lx`, `k_y = 2π/Ly`, `k_z = π/Lz` (two cells across x and y,
//! one across z), decaying viscously:
//!
//! ```text
//! u =  A(t) sin(k_x x') cos(k_y y') cos(k_z z')
//! v = -A(t) b cos(k_x x') sin(k_y y') cos(k_z z')
//! w = 0,      b = k_x / k_y,      A(t) = U e^(-t/τ)
//! ```
//!
//! `∇·u = A (k_x - b k_y) cos cos cos = 0` (`b` keeps it so in a box that
//! is not square). With `sx = sin(k_x x')`, `cx = cos(k_x x')` and so on:
//!
//! ```text
//! ∂u/∂t = -u/τ
//! (u·∇)u_x = A² k_x sx cx cz²
//! (u·∇)u_y = A² b k_x sy cy cz²
//! a = (-u/τ + A² k_x sx cx cz²,  -v/τ + A² b k_x sy cy cz²,  0)
//! ```
//!
//! The normal velocity vanishes on every face (`sin` at `x'`, `y'` = 0 and
//! L; `w = 0`), so no particle leaves. `U max(1, b) = S` (the largest speed
//! at frame 0); `τ = 100/(3 k_x U)` frames, the Stokes decay `e^(-3νk²t)`
//! of the vortex at a Reynolds number `U/(νk)` of 100: 33 turnover times
//! `1/(k_x U)`, so a sequence of 30 frames at the default speeds keeps
//! over 80% of its speed while `∂u/∂t` is still part of the truth.
//!
//! # Uniform shear ([`FlowKind::Shear`])
//!
//! ```text
//! u = γ (y - c_y),   v = w = 0,   a = 0,   ∇·u = 0
//! ```
//!
//! `γ = 2S/Ly`: the speed is `S` at the y faces. Particles flow in and out
//! through the x faces.
//!
//! # Advection and particles that leave
//!
//! Positions are integrated by classical fourth-order Runge-Kutta with
//! [`Flow::substeps`] steps a frame, chosen so that a step turns the flow
//! by at most [`MAX_STEP_RATE`] (the largest velocity gradient times the
//! step): the truncation error then lies orders of magnitude below a
//! pixel's worth of position (`tests::halving_the_step_changes_nothing_visible`).
//!
//! A particle that leaves the volume ends its trajectory for good and a new
//! particle with a new id takes its place ([`Seeding::advance`]): ids are
//! never reused, so a true trajectory is one particle inside the volume,
//! as in a lab, where particles leave and enter the illuminated volume.
//! The newcomer enters where the flow enters: a point on the volume's
//! boundary drawn with probability proportional to the inflow `-u·n`
//! through it, advected from a uniformly random instant within the frame.
//! For a steady incompressible flow that is exactly the distribution of the
//! particles that entered during the frame, so the volume stays uniformly
//! seeded (`tests::shear_keeps_the_volume_uniformly_seeded`). A flow
//! without inflow (Taylor-Green) loses no particles; should one leave by
//! round-off, its successor is drawn uniformly in the volume.

use nalgebra::{Point3, Vector3};
use rand::Rng;

use crate::photogrammetry::volume::Volume;

/// The largest velocity gradient times the RK4 step (a dimensionless turn
/// per step): local errors of RK4 are `O(h⁵)` of this, about `3e-9` of the
/// flow's length scale per step.
pub const MAX_STEP_RATE: f64 = 0.05;

/// `max_s √s (1 - e^(-s)) / s` over `s > 0`, at `s = 1.256 43`: the peak of
/// the Burgers vortex's swirl in units of `K r_c`.
const BURGERS_PEAK: f64 = 0.638_172_7;

/// Which flow.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlowKind {
    /// A Burgers vortex along z through the volume's centre.
    Burgers,
    /// The 3D Taylor-Green vortex, decaying.
    TaylorGreen,
    /// Uniform shear: `u = γ (y - c_y)`.
    Shear,
}

/// Why a flow cannot be built.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FlowError {
    /// The speed is not a positive number.
    #[error("the flow's speed must be a positive number of mm per frame, got {0}")]
    Speed(f64),
    /// The speed would carry particles across much of the volume in one
    /// frame.
    #[error(
        "a speed of {speed} mm per frame crosses more than a quarter of the volume's \
         shortest side ({limit} mm) in one frame; give at most {limit}"
    )]
    TooFast {
        /// The speed asked for.
        speed: f64,
        /// A quarter of the shortest side.
        limit: f64,
    },
    /// The volume has no finite, positive extent.
    #[error("the volume must have a finite, positive extent along every axis")]
    Volume,
}

#[derive(Clone, Debug, PartialEq)]
enum Field {
    Burgers {
        centre: Point3<f64>,
        alpha: f64,
        /// Core angular velocity `K` (rad per frame).
        k: f64,
        /// `r_c²`.
        rc2: f64,
    },
    TaylorGreen {
        /// `(min_x, min_y, c_z)`.
        origin: Point3<f64>,
        wavenumber: Vector3<f64>,
        amplitude: f64,
        b: f64,
        decay: f64,
    },
    Shear {
        y0: f64,
        rate: f64,
    },
}

/// An analytic velocity field scaled to a volume: velocity, acceleration
/// and advection (see the module's documentation for the equations).
#[derive(Clone, Debug, PartialEq)]
pub struct Flow {
    kind: FlowKind,
    field: Field,
    volume: Volume,
    speed: f64,
}

impl Flow {
    /// The flow `kind` in `volume`, with speed scale `speed` (mm per
    /// frame; at most a quarter of the volume's shortest side).
    pub fn new(kind: FlowKind, volume: &Volume, speed: f64) -> Result<Flow, FlowError> {
        let extent = volume.max - volume.min;
        if !extent.iter().all(|e| e.is_finite() && *e > 0.0) {
            return Err(FlowError::Volume);
        }
        if !(speed.is_finite() && speed > 0.0) {
            return Err(FlowError::Speed(speed));
        }
        let limit = extent.min() / 4.0;
        if speed > limit {
            return Err(FlowError::TooFast { speed, limit });
        }
        let centre = volume.centre();
        let field = match kind {
            FlowKind::Burgers => {
                let rc = extent.x.min(extent.y) / 8.0;
                Field::Burgers {
                    centre,
                    alpha: speed / (2.0 * extent.z),
                    k: speed / (BURGERS_PEAK * rc),
                    rc2: rc * rc,
                }
            }
            FlowKind::TaylorGreen => {
                let wavenumber = Vector3::new(
                    2.0 * std::f64::consts::PI / extent.x,
                    2.0 * std::f64::consts::PI / extent.y,
                    std::f64::consts::PI / extent.z,
                );
                let b = wavenumber.x / wavenumber.y;
                let amplitude = speed / b.max(1.0);
                Field::TaylorGreen {
                    origin: Point3::new(volume.min.x, volume.min.y, centre.z),
                    wavenumber,
                    amplitude,
                    b,
                    decay: 100.0 / (3.0 * wavenumber.x * amplitude),
                }
            }
            FlowKind::Shear => Field::Shear {
                y0: centre.y,
                rate: 2.0 * speed / extent.y,
            },
        };
        Ok(Flow {
            kind,
            field,
            volume: *volume,
            speed,
        })
    }

    /// Which flow this is.
    pub fn kind(&self) -> FlowKind {
        self.kind
    }

    /// The volume it is scaled to.
    pub fn volume(&self) -> &Volume {
        &self.volume
    }

    /// The speed scale it was built with (mm per frame).
    pub fn speed(&self) -> f64 {
        self.speed
    }

    /// An upper bound of the speed anywhere in the volume at any time (mm
    /// per frame).
    pub fn speed_bound(&self) -> f64 {
        match &self.field {
            Field::Burgers { alpha, .. } => {
                let half = (self.volume.max - self.volume.min) / 2.0;
                let radial = alpha / 2.0 * half.x.hypot(half.y);
                (self.speed + radial).hypot(alpha * half.z)
            }
            Field::TaylorGreen { .. } | Field::Shear { .. } => self.speed,
        }
    }

    /// An upper bound of the velocity gradient's largest entry (per frame):
    /// how fast the flow turns or strains a particle's neighbourhood.
    pub fn rate(&self) -> f64 {
        match &self.field {
            // The core's vorticity 2K bounds the swirl's gradients.
            Field::Burgers { alpha, k, .. } => (2.0 * k).max(*alpha),
            Field::TaylorGreen {
                wavenumber,
                amplitude,
                b,
                ..
            } => amplitude * b.max(1.0) * wavenumber.max(),
            Field::Shear { rate, .. } => *rate,
        }
    }

    /// RK4 steps per frame: enough that a step's [`Flow::rate`] times its
    /// length is at most [`MAX_STEP_RATE`].
    pub fn substeps(&self) -> usize {
        ((self.rate() / MAX_STEP_RATE).ceil() as usize).max(1)
    }

    /// The velocity at `p` at time `t` (frames).
    pub fn velocity(&self, p: &Point3<f64>, t: f64) -> Vector3<f64> {
        match &self.field {
            Field::Burgers {
                centre,
                alpha,
                k,
                rc2,
            } => {
                let d = p - centre;
                let s = (d.x * d.x + d.y * d.y) / rc2;
                let omega = k * burgers_g(s);
                Vector3::new(
                    -alpha / 2.0 * d.x - omega * d.y,
                    -alpha / 2.0 * d.y + omega * d.x,
                    alpha * d.z,
                )
            }
            Field::TaylorGreen {
                origin,
                wavenumber,
                amplitude,
                b,
                decay,
            } => {
                let a = amplitude * (-t / decay).exp();
                let (sx, cx, sy, cy, cz) = taylor_green_terms(p, origin, wavenumber);
                Vector3::new(a * sx * cy * cz, -a * b * cx * sy * cz, 0.0)
            }
            Field::Shear { y0, rate } => Vector3::new(rate * (p.y - y0), 0.0, 0.0),
        }
    }

    /// The material acceleration `Du/Dt = ∂u/∂t + (u·∇)u` at `p` at time
    /// `t`.
    pub fn acceleration(&self, p: &Point3<f64>, t: f64) -> Vector3<f64> {
        match &self.field {
            Field::Burgers {
                centre,
                alpha,
                k,
                rc2,
            } => {
                let d = p - centre;
                let s = (d.x * d.x + d.y * d.y) / rc2;
                let omega = k * burgers_g(s);
                let radial = alpha * alpha / 4.0 - omega * omega;
                let azimuthal = alpha * k * (-s).exp();
                Vector3::new(
                    radial * d.x + azimuthal * d.y,
                    radial * d.y - azimuthal * d.x,
                    alpha * alpha * d.z,
                )
            }
            Field::TaylorGreen {
                origin,
                wavenumber,
                amplitude,
                b,
                decay,
            } => {
                let a = amplitude * (-t / decay).exp();
                let (sx, cx, sy, cy, cz) = taylor_green_terms(p, origin, wavenumber);
                let u = a * sx * cy * cz;
                let v = -a * b * cx * sy * cz;
                let convective = a * a * wavenumber.x * cz * cz;
                Vector3::new(
                    -u / decay + convective * sx * cx,
                    -v / decay + convective * b * sy * cy,
                    0.0,
                )
            }
            Field::Shear { .. } => Vector3::zeros(),
        }
    }

    /// The position at time `t + dt` of the particle at `p` at time `t`,
    /// by RK4 in [`Flow::substeps`] steps a frame (at least one).
    pub fn advance(&self, p: &Point3<f64>, t: f64, dt: f64) -> Point3<f64> {
        let steps = ((dt.abs() * self.substeps() as f64).ceil() as usize).max(1);
        self.advance_in_steps(p, t, dt, steps)
    }

    /// [`Flow::advance`] in exactly `steps` RK4 steps.
    pub fn advance_in_steps(&self, p: &Point3<f64>, t: f64, dt: f64, steps: usize) -> Point3<f64> {
        let steps = steps.max(1);
        let h = dt / steps as f64;
        let mut q = *p;
        for i in 0..steps {
            let ti = t + h * i as f64;
            let k1 = self.velocity(&q, ti);
            let k2 = self.velocity(&(q + k1 * (h / 2.0)), ti + h / 2.0);
            let k3 = self.velocity(&(q + k2 * (h / 2.0)), ti + h / 2.0);
            let k4 = self.velocity(&(q + k3 * h), ti + h);
            q += (k1 + (k2 + k3) * 2.0 + k4) * (h / 6.0);
        }
        q
    }

    /// A point where the flow enters the volume at time `t`, drawn with
    /// probability proportional to the inflow `-u·n` (rejection sampling
    /// over the faces by area); `None` if none was found (no inflow).
    fn inflow_point(&self, t: f64, rng: &mut impl Rng) -> Option<Point3<f64>> {
        let (min, max) = (self.volume.min, self.volume.max);
        let extent = max - min;
        let areas = [
            extent.y * extent.z,
            extent.x * extent.z,
            extent.x * extent.y,
        ];
        let total = 2.0 * areas.iter().sum::<f64>();
        let bound = self.speed_bound();
        for _ in 0..10_000 {
            // A face by area: axis, then side.
            let mut pick = rng.random_range(0.0..total);
            let mut axis = 0;
            while axis < 2 && pick >= 2.0 * areas[axis] {
                pick -= 2.0 * areas[axis];
                axis += 1;
            }
            let high = pick >= areas[axis];
            let mut point =
                Point3::from(Vector3::from_fn(|i, _| rng.random_range(min[i]..=max[i])));
            point[axis] = if high { max[axis] } else { min[axis] };
            let outward = if high { 1.0 } else { -1.0 };
            let inflow = -outward * self.velocity(&point, t)[axis];
            if rng.random_range(0.0..bound) < inflow {
                return Some(point);
            }
        }
        None
    }
}

/// `(1 - e^(-s)) / s`, exact near 0.
fn burgers_g(s: f64) -> f64 {
    if s < 1e-8 {
        1.0 - s / 2.0
    } else {
        -(-s).exp_m1() / s
    }
}

fn taylor_green_terms(
    p: &Point3<f64>,
    origin: &Point3<f64>,
    wavenumber: &Vector3<f64>,
) -> (f64, f64, f64, f64, f64) {
    let phase = (p - origin).component_mul(wavenumber);
    let (sx, cx) = phase.x.sin_cos();
    let (sy, cy) = phase.y.sin_cos();
    (sx, cx, sy, cy, phase.z.cos())
}

/// A simulated particle: its id and position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tracer {
    /// Unique for the sequence: a particle that leaves is never seen again.
    pub id: u64,
    /// Position (mm).
    pub position: Point3<f64>,
}

/// A particle's true state at a frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TracerState {
    /// The particle's id.
    pub id: u64,
    /// Position (mm).
    pub position: Point3<f64>,
    /// Velocity (mm per frame).
    pub velocity: Vector3<f64>,
    /// Material acceleration (mm per frame²).
    pub acceleration: Vector3<f64>,
}

/// Particles in a flow, frame after frame; a constant count in the volume
/// (see the module's documentation for particles that leave).
#[derive(Clone, Debug)]
pub struct Seeding {
    flow: Flow,
    tracers: Vec<Tracer>,
    next_id: u64,
    frame: u64,
}

impl Seeding {
    /// `count` particles drawn uniformly in the flow's volume at frame 0,
    /// ids `0..count`.
    pub fn new(flow: Flow, count: usize, rng: &mut impl Rng) -> Seeding {
        let tracers = super::particles(flow.volume(), count, rng)
            .into_iter()
            .enumerate()
            .map(|(id, position)| Tracer {
                id: id as u64,
                position,
            })
            .collect();
        Seeding {
            flow,
            tracers,
            next_id: count as u64,
            frame: 0,
        }
    }

    /// The flow.
    pub fn flow(&self) -> &Flow {
        &self.flow
    }

    /// The current frame (0 at the start).
    pub fn frame(&self) -> u64 {
        self.frame
    }

    /// The particles at the current frame.
    pub fn tracers(&self) -> &[Tracer] {
        &self.tracers
    }

    /// Their positions, in the order of [`Seeding::tracers`].
    pub fn positions(&self) -> Vec<Point3<f64>> {
        self.tracers.iter().map(|t| t.position).collect()
    }

    /// Every particle's true state at the current frame.
    pub fn states(&self) -> Vec<TracerState> {
        let t = self.frame as f64;
        self.tracers
            .iter()
            .map(|tracer| TracerState {
                id: tracer.id,
                position: tracer.position,
                velocity: self.flow.velocity(&tracer.position, t),
                acceleration: self.flow.acceleration(&tracer.position, t),
            })
            .collect()
    }

    /// Moves every particle on by one frame; each that left the volume is
    /// replaced, in its place in the list, by a new one (a new id) that
    /// entered with the flow during the frame. Returns how many were
    /// replaced.
    pub fn advance(&mut self, rng: &mut impl Rng) -> usize {
        let t = self.frame as f64;
        let mut replaced = 0;
        for i in 0..self.tracers.len() {
            let moved = self.flow.advance(&self.tracers[i].position, t, 1.0);
            if self.flow.volume().contains(&moved) {
                self.tracers[i].position = moved;
            } else {
                replaced += 1;
                self.tracers[i] = Tracer {
                    id: self.next_id,
                    position: self.newcomer(t, rng),
                };
                self.next_id += 1;
            }
        }
        self.frame += 1;
        replaced
    }

    /// A particle that entered the volume during the frame from `t` to
    /// `t + 1`, at `t + 1`.
    fn newcomer(&self, t: f64, rng: &mut impl Rng) -> Point3<f64> {
        for _ in 0..100 {
            let Some(entry) = self.flow.inflow_point(t, rng) else {
                break;
            };
            // The particle crossed the boundary at a uniformly random
            // instant in the frame (for a steady flow the entry point's
            // distribution does not depend on it).
            let remaining = 1.0 - rng.random_range(0.0..1.0);
            let position = self.flow.advance(&entry, t + 1.0 - remaining, remaining);
            if self.flow.volume().contains(&position) {
                return position;
            }
        }
        super::particles(self.flow.volume(), 1, rng)[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::{self, RigSpec};

    const KINDS: [FlowKind; 3] = [FlowKind::Burgers, FlowKind::TaylorGreen, FlowKind::Shear];

    fn volume() -> Volume {
        RigSpec::convergent(4).volume
    }

    /// Object-space size of a pixel at the volume's centre, for the
    /// simulator's rig (mm per px): the smallest over the cameras of the
    /// displacement that moves an image by one pixel.
    fn pixel_mm() -> f64 {
        let spec = RigSpec::convergent(4);
        let centre = spec.volume.centre();
        spec.build()
            .unwrap()
            .iter()
            .flat_map(|camera| {
                let at = camera.project(&centre).unwrap();
                (0..3).map(move |i| {
                    let mut moved = centre;
                    moved[i] += 0.01;
                    0.01 / (camera.project(&moved).unwrap() - at).norm()
                })
            })
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn burgers_peak_is_the_swirls_maximum() {
        let f = |s: f64| s.sqrt() * burgers_g(s);
        assert!((f(1.256_43) - BURGERS_PEAK).abs() < 1e-7);
        for s in [1.2, 1.25, 1.26, 1.3] {
            assert!(f(s) <= BURGERS_PEAK + 1e-9, "{s}");
        }
        // And the flow reaches S there, not more.
        let flow = Flow::new(FlowKind::Burgers, &volume(), 1.0).unwrap();
        let Field::Burgers { centre, rc2, .. } = flow.field else {
            unreachable!()
        };
        let at = centre + Vector3::new(rc2.sqrt() * 1.256_43f64.sqrt(), 0.0, 0.0);
        assert!((flow.velocity(&at, 0.0).y - 1.0).abs() < 1e-6);
    }

    /// The velocity is the trajectory's derivative and the acceleration its
    /// second, by central differences of the RK4 trajectory over ±h = 1e-3
    /// frame: the differences' truncation errors h²/6 x''' and h²/12 x''''
    /// are below 2e-7 mm per frame (and frame²) here (x''' ~ K³ r ~ 1 mm
    /// per frame³ in the fastest core), the acceleration's round-off
    /// 4 ε |x| / h² about 3e-8 mm per frame², and RK4 over one step of h
    /// is exact to O(h⁵).
    #[test]
    fn velocity_and_acceleration_are_the_trajectorys_derivatives() {
        let mut rng = simulate::rng(11);
        let volume = volume();
        for kind in KINDS {
            for speed in [0.5, 3.0] {
                let flow = Flow::new(kind, &volume, speed).unwrap();
                let scale = flow.rate() * flow.speed_bound();
                for (i, p) in simulate::particles(&volume, 200, &mut rng)
                    .iter()
                    .enumerate()
                {
                    let t = i as f64 * 0.37;
                    let h = 1e-3;
                    let ahead = flow.advance_in_steps(p, t, h, 1);
                    let behind = flow.advance_in_steps(p, t, -h, 1);
                    let velocity = (ahead - behind) / (2.0 * h);
                    let acceleration = (ahead.coords - 2.0 * p.coords + behind.coords) / (h * h);
                    let u = flow.velocity(p, t);
                    let a = flow.acceleration(p, t);
                    assert!(
                        (velocity - u).norm() < 1e-6 * speed,
                        "{kind:?} at {p}: {velocity} vs {u}"
                    );
                    assert!(
                        (acceleration - a).norm() < 1e-5 * scale,
                        "{kind:?} at {p}: {acceleration} vs {a}"
                    );
                }
            }
        }
    }

    /// The acceleration is also ∂u/∂t + (u·∇)u by finite differences of
    /// the velocity field itself (a check independent of the integrator),
    /// and the fields are divergence-free: central differences over 1e-4
    /// mm are exact to 1e-8 of the gradients here.
    #[test]
    fn acceleration_is_the_material_derivative_and_divergence_vanishes() {
        let mut rng = simulate::rng(12);
        let volume = volume();
        for kind in KINDS {
            let flow = Flow::new(kind, &volume, 2.0).unwrap();
            let rate = flow.rate();
            for p in simulate::particles(&volume, 300, &mut rng) {
                let t = 3.7;
                let d = 1e-4;
                let gradient = |i: usize| {
                    let mut e = Vector3::zeros();
                    e[i] = d;
                    (flow.velocity(&(p + e), t) - flow.velocity(&(p - e), t)) / (2.0 * d)
                };
                let columns = [gradient(0), gradient(1), gradient(2)];
                let divergence = columns[0].x + columns[1].y + columns[2].z;
                assert!(
                    divergence.abs() < 1e-7 * rate,
                    "{kind:?} at {p}: {divergence}"
                );
                let u = flow.velocity(&p, t);
                let dt = 1e-4;
                let local = (flow.velocity(&p, t + dt) - flow.velocity(&p, t - dt)) / (2.0 * dt);
                let convective = columns[0] * u.x + columns[1] * u.y + columns[2] * u.z;
                let a = flow.acceleration(&p, t);
                assert!(
                    (local + convective - a).norm() < 1e-7 * rate * flow.speed_bound(),
                    "{kind:?} at {p}: {} vs {a}",
                    local + convective
                );
            }
        }
    }

    #[test]
    fn speed_bound_holds_and_is_reached_closely() {
        let mut rng = simulate::rng(13);
        let volume = volume();
        for kind in KINDS {
            let flow = Flow::new(kind, &volume, 1.5).unwrap();
            let fastest = simulate::particles(&volume, 20_000, &mut rng)
                .iter()
                .map(|p| flow.velocity(p, 0.0).norm())
                .fold(0.0, f64::max);
            assert!(fastest <= flow.speed_bound(), "{kind:?}");
            assert!(fastest >= 0.9 * flow.speed(), "{kind:?}: {fastest}");
        }
    }

    /// At the fastest flow allowed (a quarter of the volume's shortest
    /// side a frame), 30 frames with half the RK4 step move no particle by
    /// more than a thousandth of the 0.1 px the simulator's noise is
    /// (1 px is about 0.1 mm at the volume's centre for the simulator's
    /// rig).
    #[test]
    fn halving_the_step_changes_nothing_visible() {
        let volume = volume();
        let limit = (volume.max - volume.min).min() / 4.0;
        let pixel = pixel_mm();
        let mut rng = simulate::rng(14);
        let starts = simulate::particles(&volume, 100, &mut rng);
        for kind in KINDS {
            let flow = Flow::new(kind, &volume, limit).unwrap();
            let steps = flow.substeps();
            let mut worst: f64 = 0.0;
            for p in &starts {
                let (mut a, mut b) = (*p, *p);
                for frame in 0..30 {
                    let t = frame as f64;
                    a = flow.advance_in_steps(&a, t, 1.0, steps);
                    b = flow.advance_in_steps(&b, t, 1.0, 2 * steps);
                }
                worst = worst.max((a - b).norm());
            }
            let in_px = worst / pixel;
            println!(
                "{kind:?}: {steps} steps a frame, halving moves {worst:.2e} mm = {in_px:.2e} px"
            );
            assert!(in_px < 1e-4, "{kind:?}: {in_px} px");
        }
    }

    #[test]
    fn bad_parameters_are_refused() {
        let volume = volume();
        for speed in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(
                matches!(
                    Flow::new(FlowKind::Shear, &volume, speed),
                    Err(FlowError::Speed(_))
                ),
                "{speed}"
            );
        }
        assert!(matches!(
            Flow::new(FlowKind::Shear, &volume, 10.5),
            Err(FlowError::TooFast { limit, .. }) if limit == 10.0
        ));
        let flat = Volume {
            min: volume.min,
            max: Point3::new(volume.max.x, volume.max.y, volume.min.z),
        };
        assert_eq!(
            Flow::new(FlowKind::Burgers, &flat, 1.0),
            Err(FlowError::Volume)
        );
    }

    /// Taylor-Green's particles never leave; those of the other flows
    /// leave and come back as new ids, never reused, with the count kept.
    #[test]
    fn particles_that_leave_come_back_with_new_ids() {
        let volume = volume();
        for kind in KINDS {
            let flow = Flow::new(kind, &volume, 3.0).unwrap();
            let mut rng = simulate::rng(15);
            let mut seeding = Seeding::new(flow, 500, &mut rng);
            let mut seen = std::collections::HashSet::new();
            let mut replaced = 0;
            for _ in 0..40 {
                let before: std::collections::HashSet<u64> =
                    seeding.tracers().iter().map(|t| t.id).collect();
                seen.extend(before.iter().copied());
                replaced += seeding.advance(&mut rng);
                assert_eq!(seeding.tracers().len(), 500);
                assert!(seeding
                    .tracers()
                    .iter()
                    .all(|t| volume.contains(&t.position)));
                for tracer in seeding.tracers() {
                    // A known id is still the same particle; a new one is new.
                    assert!(before.contains(&tracer.id) || !seen.contains(&tracer.id));
                }
            }
            assert_eq!(seeding.frame(), 40);
            match kind {
                FlowKind::TaylorGreen => assert_eq!(replaced, 0),
                _ => assert!(replaced > 20, "{kind:?}: {replaced}"),
            }
        }
    }

    /// In uniform shear at 4 mm a frame the fast layers (|y - c_y| > 20
    /// mm, 2 to 4 mm a frame) are swept through the 80 mm volume in 20 to
    /// 40 frames. After 60 frames, their particles must still be spread
    /// uniformly along x: each of 8 bins within 5 standard deviations of
    /// its share (binomial). Newcomers drawn uniformly in the volume would
    /// leave the upstream bins nearly empty.
    #[test]
    fn shear_keeps_the_volume_uniformly_seeded() {
        let volume = volume();
        let flow = Flow::new(FlowKind::Shear, &volume, 4.0).unwrap();
        let mut rng = simulate::rng(16);
        let mut seeding = Seeding::new(flow, 8_000, &mut rng);
        for _ in 0..60 {
            seeding.advance(&mut rng);
        }
        let centre = volume.centre();
        let fast: Vec<f64> = seeding
            .tracers()
            .iter()
            .filter(|t| (t.position.y - centre.y).abs() > 20.0)
            .map(|t| t.position.x)
            .collect();
        let n = fast.len() as f64;
        // A uniform seeding puts half the particles in the fast layers.
        assert!(
            (n - 4_000.0).abs() < 5.0 * (8_000.0f64 * 0.25).sqrt(),
            "{n}"
        );
        let mut bins = [0usize; 8];
        for x in fast {
            let bin = ((x - volume.min.x) / (volume.max.x - volume.min.x) * 8.0) as usize;
            bins[bin.min(7)] += 1;
        }
        let expected = n / 8.0;
        let sd = (n * (1.0 / 8.0) * (7.0 / 8.0)).sqrt();
        for (i, &count) in bins.iter().enumerate() {
            assert!(
                (count as f64 - expected).abs() < 5.0 * sd,
                "bin {i}: {count} against {expected:.0} ({bins:?})"
            );
        }
    }

    /// The Burgers vortex at 3 mm a frame empties its volume along z in
    /// about 40 frames (strain 0.0375 per frame); after 60 frames the
    /// 10,000 particles, most of them newcomers through the sides and
    /// through the corners the swirl crosses, must still fill the volume
    /// uniformly: in 3x3x3 cells, each within 5 standard deviations of its
    /// binomial share.
    #[test]
    fn burgers_keeps_the_volume_uniformly_seeded() {
        let volume = volume();
        let flow = Flow::new(FlowKind::Burgers, &volume, 3.0).unwrap();
        let mut rng = simulate::rng(18);
        let count = 10_000;
        let mut seeding = Seeding::new(flow, count, &mut rng);
        let mut replaced = 0;
        for _ in 0..60 {
            replaced += seeding.advance(&mut rng);
        }
        assert!(replaced > count / 2, "{replaced}");
        let mut cells = [0usize; 27];
        let extent = volume.max - volume.min;
        for tracer in seeding.tracers() {
            let cell = (0..3).fold(0, |cell, i| {
                let k = ((tracer.position[i] - volume.min[i]) / extent[i] * 3.0) as usize;
                cell * 3 + k.min(2)
            });
            cells[cell] += 1;
        }
        let share = 1.0 / 27.0;
        let expected = count as f64 * share;
        let sd = (count as f64 * share * (1.0 - share)).sqrt();
        for (i, &n) in cells.iter().enumerate() {
            assert!(
                (n as f64 - expected).abs() < 5.0 * sd,
                "cell {i}: {n} against {expected:.0} ({cells:?})"
            );
        }
    }

    #[test]
    fn states_carry_the_flows_velocity_and_acceleration() {
        let volume = volume();
        let flow = Flow::new(FlowKind::TaylorGreen, &volume, 1.0).unwrap();
        let mut rng = simulate::rng(17);
        let mut seeding = Seeding::new(flow.clone(), 10, &mut rng);
        seeding.advance(&mut rng);
        seeding.advance(&mut rng);
        for (state, tracer) in seeding.states().iter().zip(seeding.tracers()) {
            assert_eq!(state.id, tracer.id);
            assert_eq!(state.velocity, flow.velocity(&tracer.position, 2.0));
            assert_eq!(state.acceleration, flow.acceleration(&tracer.position, 2.0));
        }
    }
}
