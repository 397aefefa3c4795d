//! Levenberg-Marquardt on the normal equations: the one driver of the
//! calibration's adjustment (`calibrate/adjustment.rs`, section 5's
//! resection) and of self-calibration's bundle adjustment
//! (`selfcal/bundle.rs`, which wand calibration uses too).
//!
//! The problem owns its estimate and knows its algebra; the driver owns the
//! damping and the decisions. At each iteration the problem linearises at
//! its current estimate, the normal equations `N Δ = g` (`N = AᵀWA`,
//! `g = AᵀWv`, `v` observed minus computed), and on request gives a trial:
//! the solution of the damped system `(N + λ diag(N)) Δ = g` (Marquardt's
//! scaling by the diagonal, with whatever the problem adds: the bundle's
//! Schur reduction and gauge constraints), the estimate moved by `Δ` and
//! the linear model's reduction of the cost `vᵀWv`,
//! `L(0) - L(Δ) = ‖v‖²_W - ‖v - AΔ‖²_W = Δᵀ(2g - NΔ)`.
//!
//! **Damping: Nielsen's rule** (Nielsen 1999; Madsen, Nielsen, Tingleff
//! 2004, *Methods for non-linear least squares problems*, Eq. 2.21 and
//! Algorithm 3.16). A trial whose cost does not exceed the current one is
//! taken; with the gain ratio `ρ = (F(x) - F(x + Δ)) / (L(0) - L(Δ))`,
//!
//! ```text
//! accepted:  λ ← λ · max(1/3, 1 - (2ρ - 1)³),   ν ← 2
//! rejected:  λ ← λ · ν,                         ν ← 2ν
//! ```
//!
//! It is the better of the two rules the adjustments had (the bundle's was
//! `λ/3` on success whatever the step's quality and `×10` after a state it
//! could not linearise): a step the linear model predicted well (`ρ ≈ 1`)
//! moves λ towards Gauss-Newton by the largest factor, a poor one (`ρ`
//! small) keeps it, so the damping follows the model's quality instead of
//! oscillating, and consecutive failures grow λ geometrically faster, so a
//! hopeless λ is left in a few trials. Madsen et al. report it needs fewer
//! iterations than Marquardt's `×10 / ÷10` rule on their test problems.
//! A trial whose predicted reduction is not positive (the bundle's gauge
//! constraints can take back a drift at a cost) counts as `ρ ≥ 1` when its
//! cost fell: λ shrinks by 3, as both adjustments did.
//!
//! **Stopping**, with the problem's relative tolerance `ε`:
//! 1. the undamped (Gauss-Newton) step promises a reduction of at most
//!    `ε F(x)`: converged. That promise is the gap to the quadratic
//!    model's minimum, `gᵀN⁻¹g`; a parameter `p` of standard deviation
//!    `σ_p` is then within about `σ_p √(ε r)` of the minimum (`r` the
//!    redundancy, `F ≈ r σ0²`). A small reduction by an accepted step is
//!    no such test: a damped step can be small far from the minimum.
//! 2. no trial reduced the cost in [`TRIALS`] (λ grown by `2^(k(k+1)/2)`,
//!    far beyond any useful damping): stuck, not converged;
//! 3. the iteration limit: not converged.
//!
//! An estimate the problem cannot linearise (a step moved a wall past a
//! particle) is taken back to the last accepted one and λ grows as after a
//! failed trial; with nothing to take back, the adjustment fails.

/// Damped trials per iteration before the adjustment counts as stuck.
pub(crate) const TRIALS: usize = 30;

/// The absolute floor of the stopping test (cost units, px²): a cost of
/// zero stops at a predicted reduction of rounding size.
const FLOOR: f64 = 1e-30;

/// A least-squares problem as the driver sees it: an estimate the problem
/// holds, its normal equations and trial steps.
pub(crate) trait LeastSquares {
    /// The normal equations linearised at the current estimate.
    type Normal;
    /// An estimate of the unknowns (the current one moved by a step).
    type Estimate;

    /// The weighted sum of squared residuals at the current estimate, or
    /// `None` where it cannot be evaluated.
    fn cost(&self) -> Option<f64>;

    /// The weighted sum of squared residuals at `estimate`, or `None` where
    /// it cannot be evaluated (a point does not image).
    fn cost_of(&self, estimate: &Self::Estimate) -> Option<f64>;

    /// The normal equations at the current estimate, or `None` where it
    /// cannot be linearised.
    fn normal(&self) -> Option<Self::Normal>;

    /// The step of the system damped by `lambda` (relative to the normal
    /// matrix's diagonal; 0: Gauss-Newton): the moved estimate and the
    /// linear model's reduction of the cost, or `None` where the system is
    /// singular.
    fn trial(&self, normal: &Self::Normal, lambda: f64) -> Option<Trial<Self::Estimate>>;

    /// Makes `estimate` the current one; gives back the one it replaces.
    fn accept(&mut self, estimate: Self::Estimate) -> Self::Estimate;
}

/// One trial step.
pub(crate) struct Trial<E> {
    /// The current estimate moved by the step.
    pub estimate: E,
    /// The linear model's reduction of the cost, `Δᵀ(2g - NΔ)`.
    pub predicted: f64,
}

/// The settings of one adjustment.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Settings {
    /// The starting damping, relative to the normal matrix's diagonal.
    pub lambda: f64,
    /// Linearisations at the most.
    pub max_iterations: usize,
    /// The relative reduction of the cost below which it has converged.
    pub tolerance: f64,
}

/// How an adjustment ended. The problem holds the final estimate.
pub(crate) struct Outcome<E, N> {
    /// The cost at the final estimate.
    pub cost: f64,
    /// Linearisations used.
    pub iterations: usize,
    /// Whether a stopping test was met (else stuck or out of iterations).
    pub converged: bool,
    /// The estimate before the last accepted step and its cost, for a
    /// caller that cannot linearise the final one.
    pub previous: Option<(E, f64)>,
    /// The normal equations at the final estimate where the driver has
    /// them (it stopped on the Gauss-Newton test), for the statistics.
    pub normal: Option<N>,
}

/// Nielsen's damping (see the module doc).
#[derive(Clone, Copy, Debug)]
struct Damping {
    lambda: f64,
    nu: f64,
}

impl Damping {
    fn new(lambda: f64) -> Damping {
        Damping { lambda, nu: 2.0 }
    }

    /// After an accepted step of gain ratio `rho`.
    fn accepted(&mut self, rho: f64) {
        let factor = if rho >= 1.0 {
            1.0 / 3.0
        } else {
            f64::max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0).powi(3))
        };
        self.lambda = (self.lambda * factor).max(1e-12);
        self.nu = 2.0;
    }

    /// After a rejected or singular trial.
    fn rejected(&mut self) {
        self.lambda *= self.nu;
        self.nu *= 2.0;
    }
}

/// Adjusts `problem` from its current estimate (see the module doc); `None`
/// where its starting estimate cannot be evaluated, or cannot be linearised
/// with no earlier estimate to go back to.
pub(crate) fn minimise<P: LeastSquares>(
    problem: &mut P,
    settings: &Settings,
) -> Option<Outcome<P::Estimate, P::Normal>> {
    let mut cost = problem.cost()?;
    let mut damping = Damping::new(settings.lambda);
    let mut previous: Option<(P::Estimate, f64)> = None;
    let mut iterations = 0;
    let outcome = |cost, iterations, converged, previous, normal| {
        Some(Outcome {
            cost,
            iterations,
            converged,
            previous,
            normal,
        })
    };
    while iterations < settings.max_iterations {
        iterations += 1;
        let Some(normal) = problem.normal() else {
            let (estimate, before) = previous.take()?;
            problem.accept(estimate);
            cost = before;
            damping.rejected();
            continue;
        };
        let negligible = |reduction: f64, cost: f64| reduction <= settings.tolerance * cost + FLOOR;
        if problem
            .trial(&normal, 0.0)
            .is_some_and(|t| negligible(t.predicted, cost))
        {
            return outcome(cost, iterations, true, previous, Some(normal));
        }
        let mut reduction = None;
        for _ in 0..TRIALS {
            let Some(trial) = problem.trial(&normal, damping.lambda) else {
                damping.rejected();
                continue;
            };
            match problem.cost_of(&trial.estimate) {
                Some(c) if c <= cost => {
                    let actual = cost - c;
                    let rho = if trial.predicted > 0.0 {
                        actual / trial.predicted
                    } else {
                        f64::INFINITY
                    };
                    damping.accepted(rho);
                    previous = Some((problem.accept(trial.estimate), cost));
                    reduction = Some(actual);
                    break;
                }
                _ => damping.rejected(),
            }
        }
        let Some(reduction) = reduction else {
            return outcome(cost, iterations, false, previous, None);
        };
        cost -= reduction;
    }
    outcome(cost, iterations, false, previous, None)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rosenbrock's function as least squares, `r = (10 (y - x²), 1 - x)`,
    /// from Madsen et al.'s start (-1.2, 1): the classic curved valley
    /// where undamped Gauss-Newton steps overshoot.
    struct Rosenbrock {
        x: [f64; 2],
    }

    impl Rosenbrock {
        fn residuals(x: &[f64; 2]) -> [f64; 2] {
            [10.0 * (x[1] - x[0] * x[0]), 1.0 - x[0]]
        }
    }

    /// A 2 x 2 normal matrix and its right-hand side.
    type Normal2 = ([[f64; 2]; 2], [f64; 2]);

    impl LeastSquares for Rosenbrock {
        type Normal = Normal2;
        type Estimate = [f64; 2];

        fn cost(&self) -> Option<f64> {
            self.cost_of(&self.x)
        }

        fn cost_of(&self, x: &[f64; 2]) -> Option<f64> {
            let r = Rosenbrock::residuals(x);
            Some(r[0] * r[0] + r[1] * r[1])
        }

        fn normal(&self) -> Option<Self::Normal> {
            // v = -r (observed 0 minus computed r), A = dr/dx.
            let a = [[-20.0 * self.x[0], 10.0], [-1.0, 0.0]];
            let v = Rosenbrock::residuals(&self.x).map(|r| -r);
            let n = [
                [
                    a[0][0] * a[0][0] + a[1][0] * a[1][0],
                    a[0][0] * a[0][1] + a[1][0] * a[1][1],
                ],
                [
                    a[0][1] * a[0][0] + a[1][1] * a[1][0],
                    a[0][1] * a[0][1] + a[1][1] * a[1][1],
                ],
            ];
            let g = [
                a[0][0] * v[0] + a[1][0] * v[1],
                a[0][1] * v[0] + a[1][1] * v[1],
            ];
            Some((n, g))
        }

        fn trial(&self, (n, g): &Self::Normal, lambda: f64) -> Option<Trial<[f64; 2]>> {
            let m = [
                [n[0][0] * (1.0 + lambda), n[0][1]],
                [n[1][0], n[1][1] * (1.0 + lambda)],
            ];
            let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
            if det.abs() < 1e-300 {
                return None;
            }
            let d = [
                (m[1][1] * g[0] - m[0][1] * g[1]) / det,
                (m[0][0] * g[1] - m[1][0] * g[0]) / det,
            ];
            let nd = [
                n[0][0] * d[0] + n[0][1] * d[1],
                n[1][0] * d[0] + n[1][1] * d[1],
            ];
            Some(Trial {
                estimate: [self.x[0] + d[0], self.x[1] + d[1]],
                predicted: d[0] * (2.0 * g[0] - nd[0]) + d[1] * (2.0 * g[1] - nd[1]),
            })
        }

        fn accept(&mut self, x: [f64; 2]) -> [f64; 2] {
            std::mem::replace(&mut self.x, x)
        }
    }

    /// The adjustment from Madsen et al.'s start, at most `max_iterations`.
    fn from_madsens_start(max_iterations: usize) -> (Rosenbrock, Outcome<[f64; 2], Normal2>) {
        let mut problem = Rosenbrock { x: [-1.2, 1.0] };
        let settings = Settings {
            lambda: 1e-3,
            max_iterations,
            tolerance: 1e-12,
        };
        let outcome = minimise(&mut problem, &settings).unwrap();
        (problem, outcome)
    }

    #[test]
    fn finds_the_minimum_of_rosenbrocks_valley() {
        let (problem, outcome) = from_madsens_start(100);
        assert!(outcome.converged);
        // The minimum is (1, 1) with cost 0; a cost below 1e-16 puts x
        // within 1e-8 of 1 (|1 - x| ≤ √cost) and y within 3e-8 (|y - x²|
        // ≤ 1e-9).
        assert!((problem.x[0] - 1.0).abs() < 1e-8, "{:?}", problem.x);
        assert!((problem.x[1] - 1.0).abs() < 3e-8, "{:?}", problem.x);
        assert!(outcome.cost < 1e-16, "{}", outcome.cost);
        assert!(outcome.previous.is_some());
        assert!(outcome.iterations < 100);
    }

    #[test]
    fn the_iteration_limit_ends_without_convergence() {
        let (_, outcome) = from_madsens_start(2);
        assert!(!outcome.converged);
        assert_eq!(outcome.iterations, 2);
        // Two accepted steps lowered the cost from 24.2.
        assert!(outcome.cost < 24.2, "{}", outcome.cost);
    }

    #[test]
    fn nielsens_rule_follows_the_gain_ratio() {
        let mut d = Damping::new(1.0);
        d.rejected();
        d.rejected();
        // x2, then x4.
        assert_eq!((d.lambda, d.nu), (8.0, 8.0));
        d.accepted(0.5);
        // 1 - 0³ = 1: a half-right model keeps the damping.
        assert_eq!((d.lambda, d.nu), (8.0, 2.0));
        d.accepted(1.0);
        assert!((d.lambda - 8.0 / 3.0).abs() < 1e-15);
        d.accepted(0.25);
        // 1 - (-0.5)³ = 1.125.
        assert!((d.lambda - 3.0).abs() < 1e-12, "{}", d.lambda);
    }
}
