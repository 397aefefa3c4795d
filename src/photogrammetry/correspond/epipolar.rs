//! The epipolar geometry through the walls (design paper, section 6.2,
//! with the multimedia model of Eq. 6-17): a ray of camera i, cut by the
//! observation volume ([`clip`]), images in camera k as a bent curve. It is
//! traced as a chain of parabolas ([`Parabola`], [`EpipolarCurve`]) within a
//! tenth of the tolerance of the true curve, and a band's test is the exact
//! distance to them ([`Parabola::within`]). Per camera pair, the matcher
//! knows in advance how many parabolas that takes and the pencil the
//! curves' chords form ([`EpipolarGeometry`]).

use nalgebra::{Point2, Vector2};

use super::pencil::Pencil;
use crate::photogrammetry::camera::{Camera, Ray};
use crate::photogrammetry::volume::Volume;

/// How far (in tolerances) an epipolar curve's parabolas may stray from
/// the true curve at the sampled rays: a tenth, less a fifth for what the
/// samples miss. It admits one parabola for every camera pair of the
/// simulator's rigs (0.05 needed more for the pairs at right angles).
pub(super) const PARABOLA_SHARE: f64 = 0.08;

/// The part of a ray inside a box, as ray parameters (the ray starts at
/// its origin: t >= 0).
pub(super) fn clip(ray: &Ray, volume: &Volume) -> Option<(f64, f64)> {
    let (mut near, mut far) = (0.0f64, f64::INFINITY);
    for i in 0..3 {
        let (o, d) = (ray.origin[i], ray.direction[i]);
        if d.abs() < 1e-15 {
            if o < volume.min[i] || o > volume.max[i] {
                return None;
            }
            continue;
        }
        let (a, b) = ((volume.min[i] - o) / d, (volume.max[i] - o) / d);
        near = near.max(a.min(b));
        far = far.min(a.max(b));
    }
    (near < far && far.is_finite()).then_some((near, far))
}

/// Where two rays pass closest: the parameter along `a` of its point
/// nearest to `b`; `None` for (nearly) parallel rays.
#[inline]
pub(super) fn closest_approach(a: &Ray, b: &Ray) -> Option<f64> {
    let w = a.origin - b.origin;
    let cos = a.direction.dot(&b.direction);
    let denominator = 1.0 - cos * cos;
    if denominator < 1e-12 {
        return None;
    }
    let (d, e) = (a.direction.dot(&w), b.direction.dot(&w));
    Some((cos * e - d) / denominator)
}

/// A parabola `P(u) = a + b u + c u^2`, u in [0, 1] (pixels).
#[derive(Clone, Copy, Debug)]
pub(super) struct Parabola {
    a: Vector2<f64>,
    b: Vector2<f64>,
    c: Vector2<f64>,
    /// The chord `P(1) - P(0) = b + c` over its squared length (zero for
    /// a point): projections on the chord without a division.
    chord_scaled: Vector2<f64>,
}

impl Parabola {
    /// The parabola through `p0`, `pm`, `p1` at u = 0, 1/2, 1.
    fn through(p0: Point2<f64>, pm: Point2<f64>, p1: Point2<f64>) -> Parabola {
        let c = (p0.coords + p1.coords - pm.coords * 2.0) * 2.0;
        let chord = p1 - p0;
        let length_sq = chord.norm_squared();
        Parabola {
            a: p0.coords,
            b: chord - c,
            c,
            chord_scaled: if length_sq > 0.0 {
                chord / length_sq
            } else {
                Vector2::zeros()
            },
        }
    }

    #[inline]
    pub(super) fn at(&self, u: f64) -> Point2<f64> {
        Point2::from(self.a + (self.b + self.c * u) * u)
    }

    /// The length of the chord from `P(0)` to `P(1)`.
    #[inline]
    pub(super) fn chord_length(&self) -> f64 {
        (self.b + self.c).norm()
    }

    /// How far the parabola strays from the chord of a span `du` long in
    /// u: `|c| du^2 / 4`.
    #[inline]
    pub(super) fn deviation(&self, du: f64) -> f64 {
        self.c.norm() * du * du / 4.0
    }

    /// Whether `p` lies within `sqrt(limit_sq)` of the parabola: Newton's
    /// method on the foot point, `(P(u) - p) . P'(u) = 0`, from the
    /// projection on the chord, u kept in [0, 1], stopped as soon as the
    /// answer is certain (or, failing that, once a step moves the foot
    /// point by less than 1e-6 px).
    ///
    /// Yes, once a curve point is within the limit. No, once a lower bound
    /// on the distance exceeds it: expanding `D(u) = |P(u) - p|^2` about an
    /// iterate u, with `q = P(u) - p` and `T = P'(u)`, gives exactly
    /// `D(u + s) = D + 2 (q.T) s + (|T|^2 + 2 q.c) s^2 + 2 (T.c) s^3 +
    /// |c|^2 s^4`, so for |s| <= 1 (both in [0, 1])
    /// `D(u + s) >= D + 2 g s + h s^2 >= D - g^2 / h` with `g = q.T`,
    /// `h = |T|^2 + 2 q.c - 2 |T.c| > 0`. Epipolar parabolas are nearly
    /// straight, so the bound is within a percent of the distance at the
    /// first iterate and most targets of a band's cells are decided
    /// without a step.
    #[inline]
    fn within(&self, p: &Point2<f64>, limit_sq: f64) -> bool {
        const MAX_STEPS: usize = 8;
        const SETTLED_SQ: f64 = 1e-12;
        let d = p.coords - self.a;
        let mut u = d.dot(&self.chord_scaled).clamp(0.0, 1.0);
        if !u.is_finite() {
            return d.norm_squared() <= limit_sq;
        }
        for _ in 0..MAX_STEPS {
            let q = (self.b + self.c * u) * u - d;
            let distance_sq = q.norm_squared();
            if distance_sq <= limit_sq {
                return true;
            }
            let tangent = self.b + self.c * (2.0 * u);
            let tangent_sq = tangent.norm_squared();
            let g = q.dot(&tangent);
            let slope = tangent_sq + 2.0 * q.dot(&self.c);
            let bound = slope - 2.0 * tangent.dot(&self.c).abs();
            // distance_sq - g^2 / bound > limit_sq, without the division.
            if bound > 0.0 && (distance_sq - limit_sq) * bound > g * g {
                return false;
            }
            if slope <= 0.0 {
                break;
            }
            let next = (u - g / slope).clamp(0.0, 1.0);
            let moved = next - u;
            u = next;
            if moved * moved * tangent_sq < SETTLED_SQ {
                break;
            }
        }
        ((self.b + self.c * u) * u - d).norm_squared() <= limit_sq
    }
}

/// The image in one camera of a ray's segment inside the volume.
///
/// A chain of parabolas, each through the images of the ends and middle of
/// its part of the segment (2m + 1 projections for m parts): within a tenth
/// of the tolerance of the true (bent) curve, as bands need, where the
/// pair's [`EpipolarGeometry`] says how many parts that takes (one, for
/// every pair of the simulator's rigs). Bands measure distances to the
/// parabolas themselves, so no further approximation enters.
#[derive(Default)]
pub(super) struct EpipolarCurve {
    near: f64,
    far: f64,
    /// The parts, in order along the ray; empty if the ray was not traced.
    parts: Vec<Parabola>,
}

impl EpipolarCurve {
    /// Traces `ray` between `near` and `far` into `camera` in `parts`
    /// parabolas; false (and no parts) if the segment does not image there.
    pub(super) fn trace(
        &mut self,
        camera: &Camera,
        ray: &Ray,
        (near, far): (f64, f64),
        parts: usize,
    ) -> bool {
        self.near = near;
        self.far = far;
        self.parts.clear();
        let project = |s: usize| {
            let u = s as f64 / (2 * parts) as f64;
            camera.project(&ray.at(near + (far - near) * u)).ok()
        };
        let Some(mut start) = project(0) else {
            return false;
        };
        for part in 0..parts {
            let (Some(middle), Some(end)) = (project(2 * part + 1), project(2 * part + 2)) else {
                self.parts.clear();
                return false;
            };
            self.parts.push(Parabola::through(start, middle, end));
            start = end;
        }
        true
    }

    /// The image of the ray's point at parameter `t`; `None` outside the
    /// traced segment.
    #[inline]
    pub(super) fn at(&self, t: f64) -> Option<Point2<f64>> {
        let u = (t - self.near) / (self.far - self.near);
        if !(0.0..=1.0).contains(&u) || self.parts.is_empty() {
            return None;
        }
        let scaled = u * self.parts.len() as f64;
        let part = (scaled as usize).min(self.parts.len() - 1);
        Some(self.parts[part].at(scaled - part as f64))
    }

    /// The parabolas, in order along the ray; none if the ray was not
    /// traced.
    pub(super) fn parts(&self) -> &[Parabola] {
        &self.parts
    }

    /// Whether `p` lies within `sqrt(limit_sq)` of the curve.
    #[inline]
    pub(super) fn within(&self, p: &Point2<f64>, limit_sq: f64) -> bool {
        self.parts.iter().any(|part| part.within(p, limit_sq))
    }
}

/// The most parabolas an epipolar curve is traced in.
const MAX_PARTS: usize = 32;

/// What the matcher knows in advance of the epipolar curves from camera `i`
/// in camera `k`, from the rays through a 13 x 13 grid of camera i's pixels
/// cut by the volume: how many parabolas trace them within the limit, and
/// the pencil their chords form.
#[derive(Clone, Debug)]
pub(super) struct EpipolarGeometry {
    pub(super) parts: usize,
    pub(super) pencil: Pencil,
}

impl EpipolarGeometry {
    /// Samples the pair. Parabolas are checked at a quarter and three
    /// quarters of each part, where their error peaks; rays that miss the
    /// volume or do not image are skipped.
    pub(super) fn sample(
        cameras: &[Camera],
        volume: &Volume,
        (i, k): (usize, usize),
        limit: f64,
    ) -> Self {
        const SAMPLES: u32 = 12;
        let mut segments = Vec::new();
        let sensor = cameras[i].sensor();
        for row in 0..=SAMPLES {
            for column in 0..=SAMPLES {
                let pixel = Point2::new(
                    f64::from(sensor.width) * f64::from(column) / f64::from(SAMPLES),
                    f64::from(sensor.height) * f64::from(row) / f64::from(SAMPLES),
                );
                let Ok(ray) = cameras[i].ray(pixel) else {
                    continue;
                };
                if let Some(span) = clip(&ray, volume) {
                    segments.push((ray, span));
                }
            }
        }
        let project = |ray: &Ray, (near, far): (f64, f64), u: f64| {
            cameras[k].project(&ray.at(near + (far - near) * u)).ok()
        };
        let chords: Vec<(Point2<f64>, Point2<f64>)> = segments
            .iter()
            .filter_map(|(ray, span)| Some((project(ray, *span, 0.0)?, project(ray, *span, 1.0)?)))
            .collect();
        let pencil = Pencil::fit(&chords).unwrap_or_else(Pencil::strips);
        let fits = |parts: usize| {
            segments.iter().all(|(ray, span)| {
                let points: Option<Vec<Point2<f64>>> = (0..=4 * parts)
                    .map(|s| project(ray, *span, s as f64 / (4 * parts) as f64))
                    .collect();
                let Some(points) = points else {
                    return true;
                };
                points.chunks_exact(4).enumerate().all(|(part, quarter)| {
                    let parabola = Parabola::through(quarter[0], quarter[2], points[4 * part + 4]);
                    (parabola.at(0.25) - quarter[1]).norm() <= limit
                        && (parabola.at(0.75) - quarter[3]).norm() <= limit
                })
            })
        };
        let parts = if i == k {
            1
        } else {
            (1..=MAX_PARTS)
                .find(|&parts| fits(parts))
                .unwrap_or(MAX_PARTS)
        };
        EpipolarGeometry { parts, pencil }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::RigSpec;

    #[test]
    fn closest_approach_is_the_foot_on_the_first_ray() {
        let ray = |origin: [f64; 3], direction: [f64; 3]| Ray {
            origin: nalgebra::Point3::from(origin),
            direction: nalgebra::Vector3::from(direction).normalize(),
        };
        let a = ray([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
        let b = ray([5.0, 2.0, -3.0], [0.0, 0.0, 1.0]);
        let t = closest_approach(&a, &b).unwrap();
        assert!((t - 5.0).abs() < 1e-12, "{t}");
        assert_eq!(
            closest_approach(&a, &ray([0.0, 1.0, 0.0], [2.0, 0.0, 0.0])),
            None
        );
    }

    /// The distance to a parabola by brute force: the best of 2001 samples,
    /// refined by ternary search between its neighbours.
    fn brute_force_distance(parabola: &Parabola, p: &Point2<f64>) -> f64 {
        let distance = |u: f64| (parabola.at(u) - p).norm();
        let best = (0..=2000)
            .map(|i| f64::from(i) / 2000.0)
            .min_by(|x, y| distance(*x).total_cmp(&distance(*y)))
            .unwrap();
        let (mut lo, mut hi) = ((best - 5e-4).max(0.0), (best + 5e-4).min(1.0));
        for _ in 0..100 {
            let (m1, m2) = (lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0);
            if distance(m1) <= distance(m2) {
                hi = m2;
            } else {
                lo = m1;
            }
        }
        distance((lo + hi) / 2.0)
    }

    proptest::proptest! {
        /// `within` decides exactly as the distance does, for parabolas
        /// bent as epipolar curves are (a bend up to a fortieth of the
        /// length; the simulator's curves bend about a hundredth) and
        /// points across and beyond their ends.
        #[test]
        fn parabola_within_agrees_with_the_distance(
            length in 1.0..800.0f64,
            heading in 0.0..std::f64::consts::TAU,
            bend in -0.1..0.1f64,
            skew in -0.05..0.05f64,
            along in -0.2..1.2f64,
            across in -4.0..4.0f64,
            limit in 0.01..2.0f64,
        ) {
            let direction = Vector2::new(heading.cos(), heading.sin());
            let normal = Vector2::new(-direction.y, direction.x);
            let a = Point2::new(300.0, 200.0);
            let end = a + direction * length;
            let middle = nalgebra::center(&a, &end)
                + (normal * bend + direction * skew) * length / 4.0;
            let parabola = Parabola::through(a, middle, end);
            let p = parabola.at(along.clamp(0.0, 1.0))
                + direction * (along - along.clamp(0.0, 1.0)) * length
                + normal * across;
            let distance = brute_force_distance(&parabola, &p);
            let within = parabola.within(&p, limit * limit);
            if distance < limit - 1e-6 {
                proptest::prop_assert!(within, "distance {distance} < limit {limit}");
            }
            if distance > limit + 1e-6 {
                proptest::prop_assert!(!within, "distance {distance} > limit {limit}");
            }
        }
    }

    /// The traced curves stay within a tenth of the tolerance of the exact
    /// projections, for rays between the sampled ones and for tolerances
    /// tight enough that one parabola per curve no longer does.
    #[test]
    fn epipolar_curves_stay_within_a_tenth_of_the_tolerance() {
        let spec = RigSpec::convergent(4);
        let cameras: Vec<Camera> = spec.build().unwrap();
        let volume = spec.volume;
        let mut most_parts = 0;
        for tolerance in [0.5, 0.01] {
            for (i, k) in (0..4).flat_map(|i| (0..4).map(move |k| (i, k))) {
                if i == k {
                    continue;
                }
                let geometry =
                    EpipolarGeometry::sample(&cameras, &volume, (i, k), PARABOLA_SHARE * tolerance);
                most_parts = most_parts.max(geometry.parts);
                let sensor = cameras[i].sensor();
                let mut curve = EpipolarCurve::default();
                // Pixels halfway between the sampled ones (12 x 12 grid).
                for (row, column) in (0..12).flat_map(|r| (0..12).map(move |c| (r, c))) {
                    let pixel = Point2::new(
                        f64::from(sensor.width) * (column as f64 + 0.5) / 12.0,
                        f64::from(sensor.height) * (row as f64 + 0.5) / 12.0,
                    );
                    let ray = cameras[i].ray(pixel).unwrap();
                    let Some((near, far)) = clip(&ray, &volume) else {
                        continue;
                    };
                    assert!(curve.trace(&cameras[k], &ray, (near, far), geometry.parts));
                    for step in 0..=100 {
                        let t = (near + (far - near) * f64::from(step) / 100.0).min(far);
                        let exact = cameras[k].project(&ray.at(t)).unwrap();
                        let error = (curve.at(t).unwrap() - exact).norm();
                        assert!(
                            error <= tolerance / 10.0,
                            "pair ({i}, {k}), tolerance {tolerance}: {error} px off"
                        );
                        assert!(curve.within(&exact, error * error + 1e-18));
                    }
                }
            }
        }
        assert!(most_parts > 1, "no pair needed more than one parabola");
    }
}
