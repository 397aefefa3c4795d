//! One camera's working images for IPR: the background-free recording as
//! floats, the residual (the recording minus the particles found so far),
//! the 2D peaks of the residual, and the painting of particle images into
//! it.

use nalgebra::Point2;

use super::otf::Otf;
use crate::photogrammetry::detect::Preprocessing;
use crate::photogrammetry::image::{GreyImage, GreyPixels, Mask};
use crate::photogrammetry::target::Target;

/// Side (px) of the tiles over which the background is estimated.
const TILE: usize = 64;

/// Percentile of a tile's samples taken as its background: low enough to
/// stay below the particles at 0.15 ppp, where about 90% of the pixels
/// hold some particle light above one grey level (2.5 px images), so a
/// twentieth of the tile still sees the bare background. It lies about
/// 1.6 noise sigmas below the background's mean, a pedestal that the
/// shaking's symmetric model cannot turn into a position bias.
const BACKGROUND_PERCENTILE: f64 = 0.05;

/// One camera's residual image and model.
#[derive(Clone, Debug)]
pub struct View {
    pub width: usize,
    pub height: usize,
    /// The recording minus the background minus every particle's image.
    pub residual: Vec<f32>,
    pub mask: Option<Mask>,
    pub otf: Otf,
    /// `(pxx, pxy, pyy)` of [`Otf::precision`].
    pub precision: (f64, f64, f64),
    pub radius: i64,
}

/// The samples as floats minus the background image, if any.
fn samples(image: &GreyImage, preprocessing: &Preprocessing) -> Vec<f32> {
    let mut out: Vec<f32> = match image.pixels() {
        GreyPixels::Eight(p) => p.iter().map(|&v| f32::from(v)).collect(),
        GreyPixels::Sixteen(p) => p.iter().map(|&v| f32::from(v)).collect(),
    };
    if let Some(background) = &preprocessing.background {
        match background.pixels() {
            GreyPixels::Eight(p) => out.iter_mut().zip(p).for_each(|(v, &b)| *v -= f32::from(b)),
            GreyPixels::Sixteen(p) => out.iter_mut().zip(p).for_each(|(v, &b)| *v -= f32::from(b)),
        }
    }
    out
}

/// Subtracts a smooth background: per [`TILE`] square the
/// [`BACKGROUND_PERCENTILE`] of its usable samples, interpolated bilinearly
/// between the tiles' centres.
fn subtract_background(values: &mut [f32], width: usize, height: usize, mask: Option<&Mask>) {
    let (tx, ty) = (width.div_ceil(TILE), height.div_ceil(TILE));
    let mut levels = vec![0f32; tx * ty];
    let mut buffer = Vec::with_capacity(TILE * TILE);
    for j in 0..ty {
        for i in 0..tx {
            buffer.clear();
            for y in j * TILE..((j + 1) * TILE).min(height) {
                for x in i * TILE..((i + 1) * TILE).min(width) {
                    let index = y * width + x;
                    if mask.map_or(true, |m| m.uses(index)) {
                        buffer.push(values[index]);
                    }
                }
            }
            levels[j * tx + i] = if buffer.is_empty() {
                f32::NAN
            } else {
                let k = ((buffer.len() - 1) as f64 * BACKGROUND_PERCENTILE) as usize;
                *buffer.select_nth_unstable_by(k, f32::total_cmp).1
            };
        }
    }
    // Fully masked tiles take the mean of the others (0 if none).
    let known: Vec<f32> = levels.iter().copied().filter(|v| v.is_finite()).collect();
    let fill = if known.is_empty() {
        0.0
    } else {
        known.iter().sum::<f32>() / known.len() as f32
    };
    levels
        .iter_mut()
        .filter(|v| !v.is_finite())
        .for_each(|v| *v = fill);
    let level = |i: isize, j: isize| {
        let i = i.clamp(0, tx as isize - 1) as usize;
        let j = j.clamp(0, ty as isize - 1) as usize;
        levels[j * tx + i]
    };
    for y in 0..height {
        let fy = (y as f32 + 0.5) / TILE as f32 - 0.5;
        let (j, wy) = (fy.floor() as isize, fy - fy.floor());
        for x in 0..width {
            let fx = (x as f32 + 0.5) / TILE as f32 - 0.5;
            let (i, wx) = (fx.floor() as isize, fx - fx.floor());
            let b = (1.0 - wy) * ((1.0 - wx) * level(i, j) + wx * level(i + 1, j))
                + wy * ((1.0 - wx) * level(i, j + 1) + wx * level(i + 1, j + 1));
            values[y * width + x] -= b;
        }
    }
}

/// The background-free samples of `image` (its background image, then the
/// tiles' level subtracted), masked-out pixels set to 0.
pub fn background_free(image: &GreyImage, preprocessing: &Preprocessing) -> Vec<f32> {
    let (width, height) = (image.width() as usize, image.height() as usize);
    let mut values = samples(image, preprocessing);
    subtract_background(&mut values, width, height, preprocessing.mask.as_ref());
    if let Some(mask) = &preprocessing.mask {
        for (index, value) in values.iter_mut().enumerate() {
            if !mask.uses(index) {
                *value = 0.0;
            }
        }
    }
    values
}

impl View {
    /// Whether pixel `index` may be used.
    #[inline]
    pub fn usable(&self, index: usize) -> bool {
        self.mask.as_ref().map_or(true, |m| m.uses(index))
    }

    /// The pixel rectangle `[x0, x1) x [y0, y1)` of a particle image
    /// centred at `centre`, clipped to the image; `None` if empty.
    #[inline]
    pub fn patch(&self, centre: Point2<f64>) -> Option<(usize, usize, usize, usize)> {
        if !(centre.x.is_finite() && centre.y.is_finite()) {
            return None;
        }
        let (cx, cy) = (
            (centre.x - 0.5).round() as i64,
            (centre.y - 0.5).round() as i64,
        );
        let r = self.radius;
        let x0 = (cx - r).max(0);
        let y0 = (cy - r).max(0);
        let x1 = (cx + r + 1).min(self.width as i64);
        let y1 = (cy + r + 1).min(self.height as i64);
        (x1 > x0 && y1 > y0).then_some((x0 as usize, x1 as usize, y0 as usize, y1 as usize))
    }

    /// The model spot (peak 1) at pixel `(x, y)` for a centre `centre`.
    #[inline]
    pub fn spot(&self, x: usize, y: usize, centre: Point2<f64>) -> (f64, f64, f64) {
        let (pxx, pxy, pyy) = self.precision;
        let (du, dv) = (x as f64 + 0.5 - centre.x, y as f64 + 0.5 - centre.y);
        let g = (-0.5 * (pxx * du * du + 2.0 * pxy * du * dv + pyy * dv * dv)).exp();
        // dG/du0 and dG/dv0.
        (g, g * (pxx * du + pxy * dv), g * (pxy * du + pyy * dv))
    }

    /// Adds `amplitude` times the spot at `centre` to the residual
    /// (negative: subtracts a particle's image).
    pub fn paint(&mut self, centre: Point2<f64>, amplitude: f64) {
        let Some((x0, x1, y0, y1)) = self.patch(centre) else {
            return;
        };
        for y in y0..y1 {
            for x in x0..x1 {
                let (g, _, _) = self.spot(x, y, centre);
                self.residual[y * self.width + x] += (amplitude * g) as f32;
            }
        }
    }

    /// The least-squares amplitude of the spot at `centre` in the residual
    /// (0 if negative or off the image).
    pub fn amplitude(&self, centre: Point2<f64>) -> f64 {
        let Some((x0, x1, y0, y1)) = self.patch(centre) else {
            return 0.0;
        };
        let (mut gg, mut gr) = (0.0, 0.0);
        for y in y0..y1 {
            for x in x0..x1 {
                let index = y * self.width + x;
                if self.usable(index) {
                    let (g, _, _) = self.spot(x, y, centre);
                    gg += g * g;
                    gr += g * f64::from(self.residual[index]);
                }
            }
        }
        if gg > 0.0 {
            (gr / gg).max(0.0)
        } else {
            0.0
        }
    }

    /// The local maxima of the residual above `threshold` (a pixel above
    /// its 8 neighbours, the first of equal ones), located to a sub-pixel
    /// position by a three-point Gaussian fit along x and y.
    pub fn peaks(&self, threshold: f32) -> Vec<Target> {
        let (w, h) = (self.width, self.height);
        let r = &self.residual;
        let mut peaks = Vec::new();
        for y in 1..h.saturating_sub(1) {
            for x in 1..w.saturating_sub(1) {
                let index = y * w + x;
                let v = r[index];
                if v <= threshold || !self.usable(index) {
                    continue;
                }
                let mut maximum = true;
                for (dx, dy) in [(-1, -1), (0, -1), (1, -1), (-1, 0)] {
                    let other = ((y as isize + dy) as usize) * w + (x as isize + dx) as usize;
                    maximum &= v > r[other];
                }
                for (dx, dy) in [(1, 0), (-1, 1), (0, 1), (1, 1)] {
                    let other = ((y as isize + dy) as usize) * w + (x as isize + dx) as usize;
                    maximum &= v >= r[other];
                }
                if !maximum {
                    continue;
                }
                let offset = |low: f32, high: f32| {
                    let (l, c, h) = (f64::from(low), f64::from(v), f64::from(high));
                    if l > 0.0 && h > 0.0 {
                        let (l, c, h) = (l.ln(), c.ln(), h.ln());
                        let denominator = 2.0 * (l - 2.0 * c + h);
                        if denominator < 0.0 {
                            return ((l - h) / denominator).clamp(-0.5, 0.5);
                        }
                    }
                    let denominator = 2.0 * (l - 2.0 * c + h);
                    if denominator < 0.0 {
                        ((l - h) / denominator).clamp(-0.5, 0.5)
                    } else {
                        0.0
                    }
                };
                let dx = offset(r[index - 1], r[index + 1]);
                let dy = offset(r[index - w], r[index + w]);
                peaks.push(Target {
                    x: x as f64 + 0.5 + dx,
                    y: y as f64 + 0.5 + dy,
                    n: 0,
                    nx: 0,
                    ny: 0,
                    sumg: v.max(0.0) as u64,
                });
            }
        }
        peaks
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spot painted at a sub-pixel position is found there by the peak
    /// search within 0.05 px (the three-point Gaussian fit is exact for a
    /// sampled Gaussian without noise along an axis; the other axis'
    /// offset is the only error), and its least-squares amplitude is the
    /// painted one.
    #[test]
    fn painted_spot_is_found_and_measured() {
        let otf = Otf::round(0.7, 100.0);
        let mut view = View {
            width: 40,
            height: 30,
            residual: vec![0.0; 1200],
            mask: None,
            otf,
            precision: otf.precision(),
            radius: otf.radius(),
        };
        let centre = Point2::new(17.3, 12.8);
        view.paint(centre, 120.0);
        let peaks = view.peaks(10.0);
        assert_eq!(peaks.len(), 1);
        assert!((peaks[0].x - centre.x).abs() < 0.05, "{peaks:?}");
        assert!((peaks[0].y - centre.y).abs() < 0.05, "{peaks:?}");
        assert!((view.amplitude(centre) - 120.0).abs() < 1e-3);
        view.paint(centre, -120.0);
        assert!(view.residual.iter().all(|v| v.abs() < 1e-4));
    }

    /// A flat background with a few bright spots is removed to within the
    /// spots' share of the low percentile (0 here).
    #[test]
    fn background_is_removed() {
        let (w, h) = (130usize, 70usize);
        let mut values: Vec<f32> = (0..w * h).map(|i| 20.0 + (i % w) as f32 * 0.02).collect();
        for k in 0..30 {
            values[(k * 37) % (w * h)] += 100.0;
        }
        subtract_background(&mut values, w, h, None);
        let worst = values
            .iter()
            .filter(|v| **v < 50.0)
            .fold(0f32, |m, v| m.max(v.abs()));
        assert!(worst < 0.7, "{worst}");
    }
}
