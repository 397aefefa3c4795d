//! The resection of one camera (the design paper's section 5), step by
//! step: its observation equations, a closed-form start ([`super::dlt`]),
//! the exterior and interior orientation through the strict model, then
//! all free parameters, holding what the data cannot determine and
//! excluding gross errors, and the report.
//!
//! * Parameters the data cannot determine (a singular normal matrix, or a
//!   correlation above the limit) are held and reported; exterior
//!   parameters are never held. Distortion and affine terms are held at
//!   the setup's value; the principal point and distance at the better
//!   known of their estimate and the setup's value (see
//!   `Resection::hold_correlated`).
//! * Data snooping (Baarda 1968, with Pope's a posteriori variance): the
//!   point with the largest test statistic `vᵢᵀ Qvvᵢ⁻¹ vᵢ / sigma0²`
//!   (chi-square with 2 degrees of freedom under the null hypothesis) above
//!   the Bonferroni-corrected critical value is excluded and the adjustment
//!   repeated, one point at a time.

use std::collections::HashSet;

use nalgebra::{Point3, Vector2, Vector3};

use super::adjustment::{self, from_vector, to_vector, Equation, Statistics};
use super::prepare::Prepared;
use super::report::{camera_report, CameraReport, PointResidual};
use super::{
    dlt, snooping_critical, CalibrationError, CalibrationOptions, MarkObservation, Parameter,
    ParameterSet, MIN_POINTS,
};
use crate::photogrammetry::camera::{rotation_matrix, Camera, CameraParameters};

/// The resection of one camera, from the closed-form start to the report.
pub(super) fn resect_camera(
    k: usize,
    setup: &CameraParameters,
    observed: &[MarkObservation],
    prepared: &Prepared,
    options: &CalibrationOptions,
) -> Result<(CameraParameters, CameraReport), CalibrationError> {
    let equations = observation_equations(k, &setup.name, observed, prepared)?;
    check_point_count(k, setup, &equations, prepared.fixed)?;
    let coplanar = in_one_plane(k, setup, &equations, prepared.fixed)?;
    let unknown = options.unknown.get(k).copied().unwrap_or_default();
    let priors = priors(setup, unknown) - prepared.fixed;
    let start = closed_form_start(k, setup, &equations, coplanar, prepared.fixed | priors)?;
    let mut resection = Resection {
        camera: k,
        setup,
        options,
        fixed: prepared.fixed,
        priors,
        active: equations,
        parameters: start,
        free: prepared.fixed.complement(),
        held: Vec::new(),
        held_at_estimate: ParameterSet::empty(),
        held_at_prior: Vec::new(),
        excluded: Vec::new(),
        excluded_equations: Vec::new(),
        iterations: 0,
    };
    // Before the adjustment: the exterior orientation (and the interior
    // parameters the setup has no value for) with the setup's values for
    // the rest, then, at that estimate, which parameters the observations
    // can determine at all.
    let first = (ParameterSet::exterior() | (ParameterSet::interior() - priors)) - prepared.fixed;
    // The start of the exterior orientation: the closed form's and, for a
    // setup with the orientation (e.g. OpenPTV's .ori), the setup's, often
    // the better one on a shallow target; the one that fits the
    // observations better is kept.
    let oriented = has_orientation(setup, unknown);
    let equations = resection.equations();
    let from_setup = if oriented {
        valid_start(setup.clone())
            .and_then(|s| adjustment::adjust(&s, first, &equations, options.max_iterations))
    } else {
        None
    };
    let from_closed_form = adjustment::adjust(
        &resection.parameters,
        first,
        &equations,
        options.max_iterations,
    );
    let cost = |a: &adjustment::Adjusted| {
        adjustment::cost(&a.parameters, &equations).unwrap_or(f64::INFINITY)
    };
    let best = [from_closed_form, from_setup]
        .into_iter()
        .flatten()
        .min_by(|a, b| cost(a).total_cmp(&cost(b)))
        .ok_or_else(|| resection.no_convergence())?;
    resection.iterations += best.iterations;
    resection.parameters = best.parameters;
    resection.hold_undeterminable()?;
    let mut before = resection.statistics(resection.free)?;
    while resection.hold_implausible(&before, robust_sigma0(&before)) {
        // What is left free, at the same estimate.
        before = resection.statistics(resection.free)?;
    }
    // Step 2: the exterior and interior orientation through the strict
    // model, from which all free parameters start.
    resection.adjust(
        (ParameterSet::exterior() | ParameterSet::interior()) - resection.free.complement(),
    )?;
    let mut stats = resection.adjust_all()?;
    if resection.release_determined(&stats)? {
        stats = resection.adjust_all()?;
    }
    resection.check_geometry(&stats)?;
    Ok(resection.finish(&stats))
}

/// The parameters whose setup values are a prior the observations can be
/// judged against (see [`Parameter::plausible_range`]): all but the
/// exterior orientation and the values the setup leaves out; and not the
/// principal distance where the setup's is a placeholder, shorter than half
/// the sensor's half-diagonal (a diagonal field of view over 127°: no PTV
/// lens, e.g. the `c = 1` of a setup written without an orientation).
fn priors(setup: &CameraParameters, unknown: ParameterSet) -> ParameterSet {
    let mut priors = ParameterSet::all() - ParameterSet::exterior() - unknown;
    let s = &setup.sensor;
    let r = 0.5 * (f64::from(s.width) * s.pixel_size_x).hypot(f64::from(s.height) * s.pixel_size_y);
    // NaN counts as a placeholder too.
    let placeholder =
        setup.interior.c.abs().partial_cmp(&(0.5 * r)) != Some(std::cmp::Ordering::Greater);
    if placeholder {
        priors.remove(Parameter::C);
    }
    priors
}

/// `stats` (over `estimated`, the held-at-prior parameters among them)
/// with each `(parameter, sigma)` prior added to the normal matrix as a
/// pseudo-observation of weight `sigma0² / sigma²`, and the redundancy
/// restored (each prior is one observation more); `None` when the result
/// is still singular.
fn with_prior(
    mut stats: Statistics,
    priors: &[(Parameter, f64)],
    estimated: ParameterSet,
) -> Option<Statistics> {
    let order: Vec<Parameter> = estimated.iter().collect();
    let redundancy = stats.redundancy + priors.len();
    let vtv = stats.sigma0 * stats.sigma0 * stats.redundancy as f64;
    let sigma0 = if redundancy > 0 {
        (vtv / redundancy as f64).sqrt()
    } else {
        0.0
    };
    let mut normal = stats.normal.clone();
    for (p, sigma) in priors {
        let k = order.iter().position(|o| o == p)?;
        if *sigma > 0.0 && sigma0 > 0.0 {
            normal[(k, k)] += (sigma0 / sigma).powi(2);
        }
    }
    stats.cofactor = Some(normal.cholesky()?.inverse());
    stats.sigma0 = sigma0;
    stats.redundancy = redundancy;
    Some(stats)
}

/// Whether the setup gives the camera's orientation (e.g. OpenPTV's .ori
/// files), a start for the exterior orientation: none of its exterior or
/// interior values left out, and a principal distance that is not a
/// placeholder (see [`priors`]; a setup written without an orientation
/// has zeros and `c = 1`).
pub(super) fn has_orientation(setup: &CameraParameters, unknown: ParameterSet) -> bool {
    (ParameterSet::exterior() | ParameterSet::interior())
        .iter()
        .all(|p| !unknown.contains(p))
        && priors(setup, unknown).contains(Parameter::C)
}

/// sigma0 from the median absolute residual (`1.4826 median |v|`, the
/// normal distribution's sigma), scaled by `sqrt(2n / r)` as `vᵀv / r` is:
/// the image noise as the bulk of the points show it, unspoilt by gross
/// errors not yet excluded, for judging what the observations determine
/// before they are snooped.
fn robust_sigma0(stats: &Statistics) -> f64 {
    let mut v: Vec<f64> = stats
        .residuals
        .iter()
        .flat_map(|r| [r.x.abs(), r.y.abs()])
        .collect();
    if v.is_empty() || stats.redundancy == 0 {
        return stats.sigma0;
    }
    v.sort_by(f64::total_cmp);
    let median = v[v.len() / 2];
    let scale = (v.len() as f64 / stats.redundancy as f64).sqrt();
    (1.4826 * median * scale).min(stats.sigma0)
}

/// Checks one camera's observations and turns the usable ones (control
/// points that are not check points) into observation equations with ids.
fn observation_equations(
    camera: usize,
    name: &str,
    observed: &[MarkObservation],
    prepared: &Prepared,
) -> Result<Vec<(u64, Equation)>, CalibrationError> {
    if observed.is_empty() {
        return Err(CalibrationError::NoObservations {
            camera,
            name: name.to_owned(),
        });
    }
    let mut seen = HashSet::with_capacity(observed.len());
    let mut usable = Vec::with_capacity(observed.len());
    for o in observed {
        if !(o.pixel.x.is_finite() && o.pixel.y.is_finite()) {
            return Err(CalibrationError::NonFiniteObservation { camera, id: o.id });
        }
        let Some(point) = prepared.control.get(&o.id) else {
            return Err(CalibrationError::UnknownId { camera, id: o.id });
        };
        if !seen.insert(o.id) {
            return Err(CalibrationError::DuplicateObservation { camera, id: o.id });
        }
        if !prepared.check.contains(&o.id) {
            usable.push((
                o.id,
                Equation {
                    point: *point,
                    pixel: o.pixel,
                },
            ));
        }
    }
    Ok(usable)
}

/// Points needed for `free` parameters: the DLT's 6, and a redundancy of at
/// least 2 so that sigma0 exists.
fn points_needed(free: usize) -> usize {
    MIN_POINTS.max((free + 2).div_ceil(2))
}

/// Enough usable points for the free parameters.
fn check_point_count(
    k: usize,
    setup: &CameraParameters,
    equations: &[(u64, Equation)],
    fixed: ParameterSet,
) -> Result<(), CalibrationError> {
    let free = fixed.complement().len();
    let needed = points_needed(free);
    if equations.len() < needed {
        return Err(CalibrationError::TooFewPoints {
            camera: k,
            name: setup.name.clone(),
            usable: equations.len(),
            needed,
            free,
        });
    }
    Ok(())
}

/// Whether the control points lie in one plane; an error if they do and
/// the interior orientation is free, which a plane cannot determine
/// together with the position.
fn in_one_plane(
    k: usize,
    setup: &CameraParameters,
    equations: &[(u64, Equation)],
    fixed: ParameterSet,
) -> Result<bool, CalibrationError> {
    let points: Vec<Point3<f64>> = equations.iter().map(|(_, e)| e.point).collect();
    let coplanar = dlt::flatness(&points) < 1e-3;
    let free_interior: Vec<Parameter> = (ParameterSet::interior() - fixed).iter().collect();
    if coplanar && !free_interior.is_empty() {
        return Err(CalibrationError::Coplanar {
            camera: k,
            name: setup.name.clone(),
            count: equations.len(),
            free: free_interior,
        });
    }
    Ok(coplanar)
}

/// Step 1: the closed-form start (the DLT, or the plane homography for
/// `coplanar` points), ignoring refraction and (unknown) distortion, which
/// start at the setup's values as the fixed parameters do.
fn closed_form_start(
    k: usize,
    setup: &CameraParameters,
    equations: &[(u64, Equation)],
    coplanar: bool,
    fixed: ParameterSet,
) -> Result<CameraParameters, CalibrationError> {
    let metric: Vec<(Point3<f64>, Vector2<f64>)> = equations
        .iter()
        .filter_map(|(_, e)| Some((e.point, dlt::ideal_metric(setup, e.pixel)?)))
        .collect();
    let start = if coplanar {
        dlt::start_from_plane(setup, &metric)
    } else {
        dlt::start_from_dlt(setup, &metric)
    }
    .ok_or_else(|| CalibrationError::NoStart {
        camera: k,
        name: setup.name.clone(),
    })?;
    let setup_vector = to_vector(setup);
    let mut v = to_vector(&start);
    for p in (fixed | ParameterSet::distortion()).iter() {
        v[p.index()] = setup_vector[p.index()];
    }
    valid_start(from_vector(setup, &v)).ok_or_else(|| CalibrationError::NoConvergence {
        camera: k,
        name: setup.name.clone(),
    })
}

/// The start, if it is a valid camera; else the same orientation moved back
/// along its axis until the media accept it (a pinhole fit through a
/// refracting wall may put the centre too close to the wall).
pub(super) fn valid_start(start: CameraParameters) -> Option<CameraParameters> {
    if Camera::new(start.clone()).is_ok() {
        return Some(start);
    }
    let rotation = rotation_matrix(
        start.exterior.omega,
        start.exterior.phi,
        start.exterior.kappa,
    );
    // The camera looks along its -z axis: backwards is +z.
    let back = rotation.column(2).into_owned();
    let mut moved = start;
    for _ in 0..20 {
        moved.exterior.position += back * 50.0;
        if Camera::new(moved.clone()).is_ok() {
            return Some(moved);
        }
    }
    None
}

/// One camera's resection as it goes: the current estimate, what is free,
/// held and excluded.
pub(super) struct Resection<'a> {
    /// The camera's number (0-based), for errors.
    camera: usize,
    setup: &'a CameraParameters,
    pub(super) options: &'a CalibrationOptions,
    /// The parameters the user fixed.
    pub(super) fixed: ParameterSet,
    /// The free parameters whose setup values are a prior: held there when
    /// the observations cannot determine them within their plausible range.
    priors: ParameterSet,
    /// The observation equations in use, with their points' ids (gross
    /// errors taken out).
    pub(super) active: Vec<(u64, Equation)>,
    /// The current estimate.
    pub(super) parameters: CameraParameters,
    /// The parameters being estimated.
    pub(super) free: ParameterSet,
    /// The parameters held, and why, in the order they were held.
    pub(super) held: Vec<(Parameter, String)>,
    /// Parameters held at their least-squares estimate for a correlation:
    /// their uncertainty stays in the others' standard deviations.
    held_at_estimate: ParameterSet,
    /// Parameters held at the setup's value because the observations do
    /// not determine them, each with its prior standard deviation (a third
    /// of its plausible range): the others' standard deviations keep it.
    held_at_prior: Vec<(Parameter, f64)>,
    /// Points excluded as gross errors, in the order they were found.
    pub(super) excluded: Vec<PointResidual>,
    /// The observation equations of the excluded points, to take back
    /// when the model changes (see `release_determined`).
    excluded_equations: Vec<(u64, Equation)>,
    /// Levenberg-Marquardt iterations, all adjustments together.
    pub(super) iterations: usize,
}

impl Resection<'_> {
    fn no_convergence(&self) -> CalibrationError {
        CalibrationError::NoConvergence {
            camera: self.camera,
            name: self.setup.name.clone(),
        }
    }

    fn equations(&self) -> Vec<Equation> {
        self.active.iter().map(|(_, e)| *e).collect()
    }

    /// Adjusts `free` from the current estimate; whether it converged.
    fn adjust(&mut self, free: ParameterSet) -> Result<bool, CalibrationError> {
        let adjusted = adjustment::adjust(
            &self.parameters,
            free,
            &self.equations(),
            self.options.max_iterations,
        )
        .ok_or_else(|| self.no_convergence())?;
        self.iterations += adjusted.iterations;
        self.parameters = adjusted.parameters;
        Ok(adjusted.converged)
    }

    /// The statistics of the current estimate with `free` estimated.
    fn statistics(&self, free: ParameterSet) -> Result<Statistics, CalibrationError> {
        adjustment::statistics(&self.parameters, free, &self.equations())
            .ok_or_else(|| self.no_convergence())
    }

    /// Step 3: all free parameters, holding what the data cannot determine,
    /// and data snooping, until no parameter is to be held and no point
    /// excluded; the final adjustment's statistics.
    fn adjust_all(&mut self) -> Result<Statistics, CalibrationError> {
        loop {
            self.hold_undeterminable()?;
            // Gross errors can slow the convergence down; only the final
            // adjustment, after snooping, must have converged.
            let converged = self.adjust(self.free)?;
            let stats = self.statistics(self.free)?;
            // Correlations first and snooping next, as before the priors;
            // a parameter is held at its prior only once no gross error is
            // left to exclude: with one still in, the model error it
            // leaves would make a determinable parameter (k1) look
            // undetermined, and a hold is never undone.
            if self.hold_correlated(&stats)
                || self.snoop(&stats)
                || self.hold_implausible(&stats, stats.sigma0)
            {
                continue;
            }
            return if converged {
                Ok(stats)
            } else {
                Err(self.no_convergence())
            };
        }
    }

    /// Holds what the data cannot determine at all (a singular normal
    /// matrix), judged at the current estimate, one parameter at a time.
    fn hold_undeterminable(&mut self) -> Result<(), CalibrationError> {
        loop {
            let stats = self.statistics(self.free)?;
            let Some((p, reason)) =
                undeterminable(&stats, self.free, self.options.max_correlation, false)
            else {
                return Ok(());
            };
            self.hold(p, reason, false);
        }
    }

    /// Holds one of the pair correlated most above the limit (or one the
    /// normal matrix no longer determines), judged at the least-squares
    /// solution `stats`; whether one was held.
    ///
    /// The observations then determine only a combination of the pair
    /// (c and z0: the rig's scale), and the held one needs a value. Of the
    /// two at hand, the better known is taken: its least-squares estimate,
    /// known to its standard deviation `sigma` (with its partner free), or
    /// the setup's value, known to a third of its plausible range (see
    /// [`Parameter::plausible_range`]). So a parameter with a prior whose
    /// `3 sigma` exceeds that range is held at the setup's value, as the
    /// range test ([`Self::hold_implausible`]) would hold it; otherwise at
    /// its estimate, which leaves the others' estimates as they are.
    /// Distortion and affine terms go back to the setup's value either way
    /// (see [`Parameter::held_at_setup`]).
    fn hold_correlated(&mut self, stats: &Statistics) -> bool {
        let Some((p, reason)) =
            undeterminable(stats, self.free, self.options.max_correlation, true)
        else {
            return false;
        };
        let index = self.free.iter().position(|o| o == p);
        let from_prior = match (&stats.cofactor, index, p.plausible_range(self.setup)) {
            (Some(q), Some(k), Some(range)) if self.priors.contains(p) && !p.held_at_setup() => {
                let sigma = stats.sigma0 * q[(k, k)].max(0.0).sqrt();
                (3.0 * sigma > range).then_some((sigma, range))
            }
            _ => None,
        };
        match from_prior {
            Some((sigma, range)) => self.hold_at_prior(
                p,
                range,
                format!(
                    "{reason}, and its standard deviation {sigma:.3e} is more than a third of its \
                     plausible range ±{range:.3e} around the setup's value: held there, the \
                     better known of the two"
                ),
            ),
            None => self.hold(p, reason, true),
        }
        true
    }

    /// Stops estimating `p` and sets it to the setup's value, a prior of
    /// standard deviation `range / 3` whose uncertainty the others'
    /// standard deviations keep (see [`Self::finish`]).
    fn hold_at_prior(&mut self, p: Parameter, range: f64, reason: String) {
        self.free.remove(p);
        let mut v = to_vector(&self.parameters);
        v[p.index()] = to_vector(self.setup)[p.index()];
        self.parameters = from_vector(&self.parameters, &v);
        self.held_at_prior.push((p, range / 3.0));
        self.held.push((p, reason));
    }

    /// Holds, at the setup's value, the parameter first in
    /// [`Parameter::range_order`] among those with a prior whose standard
    /// deviation (`sigma0` times the cofactor's root) is more than a third
    /// of their plausible range: the 3-sigma interval the observations
    /// leave is wider than the values a real camera plausibly takes, so
    /// the setup's value is better than the estimate; whether one was held.
    fn hold_implausible(&mut self, stats: &Statistics, sigma0: f64) -> bool {
        let Some(q) = &stats.cofactor else {
            return false;
        };
        let worst = self
            .free
            .iter()
            .enumerate()
            .filter(|(_, p)| self.priors.contains(*p) && p.holdable())
            .filter_map(|(k, p)| {
                let sigma = sigma0 * q[(k, k)].max(0.0).sqrt();
                let range = p.plausible_range(self.setup)?;
                (3.0 * sigma > range).then_some((p, sigma, range))
            })
            .min_by_key(|(p, _, _)| p.range_order());
        let Some((p, sigma, range)) = worst else {
            return false;
        };
        self.hold_at_prior(
            p,
            range,
            format!(
                "the observations do not determine it: its standard deviation {sigma:.3e} is more \
                 than a third of its plausible range ±{range:.3e} around the setup's value \
                 (held there, in the order distortion, affine terms and principal point, then c)"
            ),
        );
        true
    }

    /// Frees again the parameters held at their priors that the adjusted
    /// observations do determine (three standard deviations within the
    /// plausible range, with this adjustment's sigma0); whether any was.
    /// The holds made before the adjustment were judged at an estimate
    /// without the parameters held, whose residuals carry their model
    /// error (an unmodelled k1 of a few pixels at the corners) and any
    /// gross error not yet excluded: a determinable parameter can look
    /// undetermined there, and held at the setup's zero it would leave
    /// that model error in the result, and points excluded for it.
    fn release_determined(&mut self, stats: &Statistics) -> Result<bool, CalibrationError> {
        let mut released = false;
        let candidates: Vec<(Parameter, f64)> = self.held_at_prior.clone();
        for (p, prior) in candidates {
            let mut free = self.free;
            free.insert(p);
            let Some(trial) = adjustment::statistics(&self.parameters, free, &self.equations())
            else {
                continue;
            };
            let Some(q) = &trial.cofactor else { continue };
            let Some(k) = free.iter().position(|o| o == p) else {
                continue;
            };
            let sigma = stats.sigma0 * q[(k, k)].max(0.0).sqrt();
            if 3.0 * sigma <= 3.0 * prior {
                self.free.insert(p);
                self.held_at_prior.retain(|(h, _)| *h != p);
                self.held.retain(|(h, _)| *h != p);
                released = true;
            }
        }
        if released {
            // Points excluded while a determinable parameter was held may
            // have shown its model error, not a gross error of their own:
            // all are taken back and tested again.
            self.active.append(&mut self.excluded_equations);
            self.excluded.clear();
        }
        Ok(released)
    }

    /// A result whose geometry the observations do not fix is an error:
    /// a projective centre whose standard deviation (as reported: with
    /// what is held as uncertain as it is) is over a third of 10%
    /// of its distance to the control points (the rig's scale, which c
    /// trades with, as undetermined as c's test would hold c), or a principal distance estimated more than its plausible
    /// range away from the setup's.
    fn check_geometry(&self, stats: &Statistics) -> Result<(), CalibrationError> {
        let free_names = || {
            (self.free - ParameterSet::exterior())
                .iter()
                .map(|p| p.name())
                .collect::<Vec<_>>()
                .join(", ")
        };
        let centroid = self
            .active
            .iter()
            .fold(Vector3::zeros(), |sum, (_, e)| sum + e.point.coords)
            / self.active.len().max(1) as f64;
        let distance = (self.parameters.exterior.position - centroid).norm();
        // The standard deviations the report gives: with the uncertainty of
        // what is held (at an estimate, or at the setup's value as a
        // prior), not conditioned on it.
        let marginal = self.marginal();
        let (stats, estimated) = match &marginal {
            Some((m, set)) => (m, *set),
            None => (stats, self.free),
        };
        if let Some(q) = &stats.cofactor {
            let sigma = estimated
                .iter()
                .enumerate()
                .filter(|(_, p)| ParameterSet::position().contains(*p))
                .map(|(k, _)| stats.sigma0 * q[(k, k)].max(0.0).sqrt())
                .fold(0.0, f64::max);
            // The position's relative uncertainty is the rig's scale's,
            // the one c trades with (sigma_c / c = sigma_z / distance): over
            // a third of c's plausible 10% is what holds c.
            if 3.0 * sigma > 0.1 * distance {
                return Err(CalibrationError::ImplausibleGeometry {
                    camera: self.camera,
                    name: self.setup.name.clone(),
                    reason: format!(
                        "its position has a standard deviation of {sigma:.1} mm at {distance:.0} \
                         mm from the control points (3 sigma over 10%: the rig's scale is not \
                         determined), with {} free",
                        free_names()
                    ),
                });
            }
        }
        let c = Parameter::C;
        if self.free.contains(c) && self.priors.contains(c) {
            let range = c.plausible_range(self.setup).unwrap_or(f64::INFINITY);
            let (estimate, nominal) = (self.parameters.interior.c, self.setup.interior.c);
            if (estimate - nominal).abs() > range {
                return Err(CalibrationError::ImplausibleGeometry {
                    camera: self.camera,
                    name: self.setup.name.clone(),
                    reason: format!(
                        "its principal distance came out {estimate:.2} mm against the setup's \
                         {nominal:.2} mm (more than 10% apart), with {} free",
                        free_names()
                    ),
                });
            }
        }
        Ok(())
    }

    /// Stops estimating `p`: distortion and affine terms go back to the
    /// setup's value; the others stay at the current estimate, `at_estimate`
    /// marking one whose uncertainty the others' sigmas keep.
    fn hold(&mut self, p: Parameter, reason: String, at_estimate: bool) {
        self.free.remove(p);
        if p.held_at_setup() {
            let mut v = to_vector(&self.parameters);
            v[p.index()] = to_vector(self.setup)[p.index()];
            self.parameters = from_vector(&self.parameters, &v);
        } else if at_estimate {
            self.held_at_estimate.insert(p);
        }
        self.held.push((p, reason));
    }

    /// Data snooping: excludes the point with the largest test statistic
    /// if it is significant and one can be spared; whether one was.
    fn snoop(&mut self, stats: &Statistics) -> bool {
        let critical = snooping_critical(self.options.snooping_alpha, self.active.len());
        let worst = stats
            .test
            .iter()
            .enumerate()
            .filter_map(|(i, t)| t.map(|t| (i, t)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        match worst {
            Some((i, t)) if t > critical && self.active.len() > points_needed(self.free.len()) => {
                let (id, equation) = self.active.remove(i);
                self.excluded_equations.push((id, equation));
                self.excluded.push(PointResidual {
                    id,
                    x_px: stats.residuals[i].x,
                    y_px: stats.residuals[i].y,
                    image_px: [equation.pixel.x, equation.pixel.y],
                    test: Some(t),
                });
                true
            }
            _ => false,
        }
    }

    /// The calibrated camera and its report. Standard deviations and
    /// covariance come with the parameters held at their estimates still
    /// free: conditioning on a value that is itself uncertain would make the
    /// others' look better than they are.
    ///
    /// A parameter held at the setup's value because the observations do
    /// not determine it is not known exactly either: the setup's value is a
    /// prior, within its plausible range (3 sigma). Its uncertainty enters
    /// the others' as that prior would in the adjustment: the normal
    /// matrix with it free, plus `sigma0² / sigma_prior²` on its diagonal
    /// (a pseudo-observation of its value; the redundancy is unchanged, one
    /// observation and one unknown more), inverted. Without that, holding
    /// a non-zero truth at zero would bias the others beyond their
    /// reported standard deviations.
    fn finish(self, stats: &Statistics) -> (CameraParameters, CameraReport) {
        let marginal = self.marginal();
        let uncertainty = match &marginal {
            Some((m, set)) => (m, *set),
            None => (stats, self.free),
        };
        let report = camera_report(&self, stats, uncertainty);
        (self.parameters, report)
    }

    /// The statistics the reported standard deviations come from (see
    /// [`Self::finish`]): with the parameters held at their estimates free
    /// and those held at the setup's value as priors, over the returned
    /// set; `None` when nothing is held so (the final adjustment's serve)
    /// or the result is singular.
    fn marginal(&self) -> Option<(Statistics, ParameterSet)> {
        let mut with_priors = self.free | self.held_at_estimate;
        let priors = self.held_at_prior.clone();
        for (p, _) in &priors {
            with_priors.insert(*p);
        }
        if with_priors == self.free {
            return None;
        }
        adjustment::statistics(&self.parameters, with_priors, &self.equations())
            .and_then(|m| with_prior(m, &priors, with_priors))
            .filter(|m| m.cofactor.is_some())
            .map(|m| (m, with_priors))
    }
}

/// Which free parameter to hold next, and why, or `None` if all are
/// determinable: one in the direction of a singular normal matrix, or (with
/// `correlations`) the one to hold of the pair correlated most above
/// `max_correlation`. `free` are the statistics' parameters; exterior
/// parameters are never held.
pub(crate) fn undeterminable(
    stats: &Statistics,
    free: ParameterSet,
    max_correlation: f64,
    correlations: bool,
) -> Option<(Parameter, String)> {
    let order: Vec<Parameter> = free.iter().collect();
    let holdable = |p: Parameter| p.holdable();
    let priority = |p: Parameter| p.hold_priority();
    // A singular normal matrix: hold the parameter that dominates the
    // direction the data do not see.
    let eigen = dlt::symmetric_eigen(stats.scaled_normal.clone())?;
    let (smallest, value) = eigen
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .map(|(i, v)| (i, *v))?;
    if value < 1e-10 || stats.cofactor.is_none() {
        let vector = eigen.eigenvectors.column(smallest);
        // Among the holdable parameters that take a real part in the
        // direction, the one first in the holding order: e.g. scx rather
        // than c when the two are interchangeable.
        let largest = (0..order.len())
            .filter(|&k| holdable(order[k]))
            .map(|k| vector[k].abs())
            .fold(0.0, f64::max);
        let worst = (0..order.len())
            .filter(|&k| holdable(order[k]) && vector[k].abs() >= 0.3 * largest)
            .min_by_key(|&k| priority(order[k]))?;
        return Some((
            order[worst],
            format!(
                "the observations do not determine it (the normal matrix is singular along a \
                 direction made mostly of {})",
                order[worst].name()
            ),
        ));
    }
    if !correlations {
        return None;
    }
    let q = stats.cofactor.as_ref()?;
    let mut worst: Option<(f64, usize, usize)> = None;
    for a in 0..order.len() {
        for b in a + 1..order.len() {
            if !holdable(order[a]) && !holdable(order[b]) {
                continue;
            }
            let r = q[(a, b)] / (q[(a, a)] * q[(b, b)]).sqrt();
            if r.abs() > max_correlation && worst.map_or(true, |(w, _, _)| r.abs() > w) {
                worst = Some((r.abs(), a, b));
            }
        }
    }
    let (r, a, b) = worst?;
    let (hold, other) = match (holdable(order[a]), holdable(order[b])) {
        (true, false) => (a, b),
        (false, true) => (b, a),
        _ if priority(order[a]) <= priority(order[b]) => (a, b),
        _ => (b, a),
    };
    Some((
        order[hold],
        format!(
            "correlated with {} at {:.4} (limit {})",
            order[other].name(),
            r,
            max_correlation
        ),
    ))
}
