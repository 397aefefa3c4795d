//! The particle image model (the "optical transfer function" of the IPR
//! papers, Wieneke 2013, section 2.2; Schanz et al. 2013): one camera's
//! image of a particle of intensity `a` whose centre projects to `(u0, v0)`
//! is the elliptic Gaussian
//!
//! `I(u, v) = a exp(-(pxx du² + 2 pxy du dv + pyy dv²) / 2)`,
//! `du = u - u0`, `dv = v - v0`,
//!
//! evaluated at the pixel centres (pixel `k` spans `[k, k + 1)`, its centre
//! is `k + 0.5`, the camera model's convention); `[[pxx, pxy], [pxy, pyy]]`
//! is the inverse of the spot's covariance. A sensor integrates the light
//! over each pixel's area, which widens a Gaussian of standard deviation
//! `s` to about `sqrt(s² + 1/12)` px: that is what the estimate measures.
//!
//! The estimate comes from the recording itself: the isolated local maxima
//! of the background-free image (no brighter pixel and no other maximum
//! above a fifth of its height within [`ISOLATION_PX`]), each fitted by
//! Gauss-Newton with the seven parameters `a, u0, v0, pxx, pxy, pyy` and a
//! local background; the model is the median of the fits, its uncertainty
//! the fits' robust spread (1.4826 MAD) and the median's standard error
//! (1.2533 sd / sqrt(n)). One model per camera; a variation over
//! sub-volumes is not estimated (see docs/ipr.md).

use nalgebra::{SMatrix, SVector};

/// Radius (px) within which a maximum used for the estimate has no other
/// maximum above a fifth of its height.
pub const ISOLATION_PX: i64 = 4;

/// Fewest isolated maxima the estimate needs.
pub const MIN_SAMPLES: usize = 10;

/// Most isolated maxima fitted (a larger sample changes the median by less
/// than its standard error; spread evenly over the image).
const MAX_SAMPLES: usize = 2000;

/// One camera's particle image model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Otf {
    /// Standard deviation of the spot along x (px).
    pub sigma_x: f64,
    /// Standard deviation along y (px).
    pub sigma_y: f64,
    /// Correlation of x and y (-1..1): the ellipse's tilt.
    pub rho: f64,
    /// Median peak height of the isolated particle images (grey levels
    /// above the background).
    pub peak: f64,
    /// Robust spread (1.4826 MAD) of the fitted `sigma_x` over the sample.
    pub sigma_x_spread: f64,
    /// Robust spread of the fitted `sigma_y`.
    pub sigma_y_spread: f64,
    /// Standard error of the median `sigma_x` and `sigma_y` (px).
    pub sigma_error: f64,
    /// Isolated particle images fitted.
    pub samples: usize,
}

impl Otf {
    /// A round spot of standard deviation `sigma` (px) and typical peak
    /// `peak`: a stated model, e.g. a simulator's.
    pub fn round(sigma: f64, peak: f64) -> Otf {
        Otf {
            sigma_x: sigma,
            sigma_y: sigma,
            rho: 0.0,
            peak,
            sigma_x_spread: 0.0,
            sigma_y_spread: 0.0,
            sigma_error: 0.0,
            samples: 0,
        }
    }

    /// The inverse covariance `(pxx, pxy, pyy)`.
    pub fn precision(&self) -> (f64, f64, f64) {
        let (sx, sy, rho) = (self.sigma_x, self.sigma_y, self.rho.clamp(-0.95, 0.95));
        let det = sx * sx * sy * sy * (1.0 - rho * rho);
        (sy * sy / det, -rho * sx * sy / det, sx * sx / det)
    }

    /// Half-size (px) of the patch that holds a particle image: 3 standard
    /// deviations of the wider axis from the centre pixel, at least 2 px
    /// (the spot's tail beyond 3 sigma is 1% of its peak).
    pub fn radius(&self) -> i64 {
        (3.0 * self.sigma_x.max(self.sigma_y))
            .ceil()
            .clamp(2.0, 12.0) as i64
    }
}

/// The seven parameters of one spot's fit: `a, u0, v0, pxx, pxy, pyy, b`.
type Params = SVector<f64, 7>;

/// Fits one spot on the patch of half-size `r` around pixel `(i, j)`;
/// `None` when the fit does not converge to a plausible spot.
fn fit_spot(
    image: &[f32],
    width: usize,
    height: usize,
    (i, j): (i64, i64),
    r: i64,
) -> Option<Params> {
    if i < r || j < r || i + r >= width as i64 || j + r >= height as i64 {
        return None;
    }
    let sample = |x: i64, y: i64| f64::from(image[y as usize * width + x as usize]);
    let mut border = Vec::new();
    for k in -r..=r {
        border.extend([sample(i + k, j - r), sample(i + k, j + r)]);
        border.extend([sample(i - r, j + k), sample(i + r, j + k)]);
    }
    border.sort_by(f64::total_cmp);
    let b0 = border[border.len() / 2];
    let mut p = Params::from_column_slice(&[
        sample(i, j) - b0,
        i as f64 + 0.5,
        j as f64 + 0.5,
        2.0,
        0.0,
        2.0,
        b0,
    ]);
    for _ in 0..15 {
        let mut h = SMatrix::<f64, 7, 7>::zeros();
        let mut g = Params::zeros();
        for y in j - r..=j + r {
            for x in i - r..=i + r {
                let (du, dv) = (x as f64 + 0.5 - p[1], y as f64 + 0.5 - p[2]);
                let q = p[3] * du * du + 2.0 * p[4] * du * dv + p[5] * dv * dv;
                let e = (-0.5 * q).exp();
                let model = p[0] * e + p[6];
                let d = Params::from_column_slice(&[
                    e,
                    p[0] * e * (p[3] * du + p[4] * dv),
                    p[0] * e * (p[4] * du + p[5] * dv),
                    -0.5 * p[0] * e * du * du,
                    -p[0] * e * du * dv,
                    -0.5 * p[0] * e * dv * dv,
                    1.0,
                ]);
                h += d * d.transpose();
                g += d * (sample(x, y) - model);
            }
        }
        // A little Levenberg damping keeps the first steps in range.
        for k in 0..7 {
            h[(k, k)] *= 1.0 + 1e-3;
        }
        let step = h.cholesky()?.solve(&g);
        p += step;
        if !(p[0] > 0.0 && p[3] > 0.0 && p[5] > 0.0 && p[3] * p[5] > p[4] * p[4]) {
            return None;
        }
        if step[1].abs() + step[2].abs() < 1e-4 {
            break;
        }
    }
    let plausible = (p[1] - (i as f64 + 0.5)).abs() < 1.0
        && (p[2] - (j as f64 + 0.5)).abs() < 1.0
        && p.iter().all(|v| v.is_finite());
    plausible.then_some(p)
}

/// The median and the robust spread (1.4826 MAD) of `values`.
fn median_spread(values: &mut [f64]) -> (f64, f64) {
    values.sort_by(f64::total_cmp);
    let median = values[values.len() / 2];
    let mut deviations: Vec<f64> = values.iter().map(|v| (v - median).abs()).collect();
    deviations.sort_by(f64::total_cmp);
    (median, 1.4826 * deviations[deviations.len() / 2])
}

/// Estimates a camera's model from its background-free image (`width` x
/// `height` samples, row by row): maxima above `threshold` (grey levels)
/// that are isolated, fitted one by one; `usable(index)` says whether a
/// pixel may be used (the mask). `None` with fewer than [`MIN_SAMPLES`]
/// plausible fits.
pub fn estimate(
    image: &[f32],
    width: usize,
    height: usize,
    threshold: f32,
    usable: &dyn Fn(usize) -> bool,
) -> Option<Otf> {
    let r = ISOLATION_PX;
    let (w, h) = (width as i64, height as i64);
    let at = |x: i64, y: i64| image[y as usize * width + x as usize];
    let mut isolated = Vec::new();
    for y in r..h - r {
        for x in r..w - r {
            let v = at(x, y);
            if v <= threshold || !usable(y as usize * width + x as usize) {
                continue;
            }
            let mut alone = true;
            'window: for yy in y - r..=y + r {
                for xx in x - r..=x + r {
                    if (xx, yy) == (x, y) {
                        continue;
                    }
                    let u = at(xx, yy);
                    let near = (xx - x).abs() <= 1 && (yy - y).abs() <= 1;
                    // Another maximum (a pixel not below its 4 neighbours)
                    // above a fifth of this one's height, or a brighter
                    // pixel, disqualifies it.
                    let brighter = u > v || (u == v && (yy, xx) < (y, x));
                    let other_maximum = !near
                        && u > 0.2 * v
                        && xx > 0
                        && yy > 0
                        && xx + 1 < w
                        && yy + 1 < h
                        && u >= at(xx - 1, yy)
                        && u >= at(xx + 1, yy)
                        && u >= at(xx, yy - 1)
                        && u >= at(xx, yy + 1);
                    if brighter || other_maximum {
                        alone = false;
                        break 'window;
                    }
                }
            }
            if alone {
                isolated.push((x, y));
            }
        }
    }
    let stride = isolated.len().div_ceil(MAX_SAMPLES).max(1);
    let fits: Vec<Params> = isolated
        .iter()
        .step_by(stride)
        .filter_map(|&(x, y)| fit_spot(image, width, height, (x, y), 3))
        .collect();
    if fits.len() < MIN_SAMPLES {
        return None;
    }
    let mut sx = Vec::with_capacity(fits.len());
    let mut sy = Vec::with_capacity(fits.len());
    let mut rho = Vec::with_capacity(fits.len());
    let mut peak = Vec::with_capacity(fits.len());
    for p in &fits {
        let det = p[3] * p[5] - p[4] * p[4];
        let (cxx, cxy, cyy) = (p[5] / det, -p[4] / det, p[3] / det);
        sx.push(cxx.sqrt());
        sy.push(cyy.sqrt());
        rho.push(cxy / (cxx * cyy).sqrt());
        peak.push(p[0]);
    }
    let n = fits.len();
    let (sigma_x, sigma_x_spread) = median_spread(&mut sx);
    let (sigma_y, sigma_y_spread) = median_spread(&mut sy);
    let (rho, _) = median_spread(&mut rho);
    let (peak, _) = median_spread(&mut peak);
    let sigma_error = 1.2533 * sigma_x_spread.max(sigma_y_spread) / (n as f64).sqrt();
    Some(Otf {
        sigma_x,
        sigma_y,
        rho,
        peak,
        sigma_x_spread,
        sigma_y_spread,
        sigma_error,
        samples: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Draws round spots of `sigma` at pixel-centre sampling on a grid far
    /// apart; the estimate must return `sigma` within a hundredth of a
    /// pixel (noise-free samples: only the fit's convergence limits it).
    #[test]
    fn recovers_a_sampled_spot() {
        let (w, h) = (200usize, 200usize);
        let sigma = 0.8;
        let mut image = vec![0f32; w * h];
        for cy in 0..9 {
            for cx in 0..9 {
                let (u0, v0) = (12.0 + 20.0 * cx as f64 + 0.3, 12.0 + 20.0 * cy as f64 - 0.2);
                for y in 0..h {
                    for x in 0..w {
                        let (du, dv) = (x as f64 + 0.5 - u0, y as f64 + 0.5 - v0);
                        let g = 100.0 * (-(du * du + dv * dv) / (2.0 * sigma * sigma)).exp();
                        image[y * w + x] += g as f32;
                    }
                }
            }
        }
        let otf = estimate(&image, w, h, 10.0, &|_| true).expect("81 isolated spots");
        assert_eq!(otf.samples, 81);
        assert!((otf.sigma_x - sigma).abs() < 0.01, "{otf:?}");
        assert!((otf.sigma_y - sigma).abs() < 0.01, "{otf:?}");
        assert!(otf.rho.abs() < 0.01, "{otf:?}");
        assert!((otf.peak - 100.0).abs() < 1.0, "{otf:?}");
    }
}
