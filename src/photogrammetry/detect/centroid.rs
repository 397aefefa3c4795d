//! Step 4 (see the parent module): each particle's moments, its weighted
//! centroid (or the Gaussian fit of [`crate::photogrammetry::centroid`]),
//! the filters on size and sum of grey, and the significance test.

use crate::photogrammetry::centroid::{self as gaussian, Centroid, PeakSamples};

use super::{key_index, Detector, Found, Grey, Target};
#[derive(Clone, Copy, Debug)]
pub(super) struct Moments {
    n: u64,
    /// Sum of levels.
    sumg: u64,
    /// Sum of weights `level - threshold`.
    weight: u64,
    /// Sums of weight times column and row, relative to the blob's corner.
    weight_x: u128,
    weight_y: u128,
    xmin: usize,
    xmax: usize,
    ymin: usize,
    ymax: usize,
}

impl Moments {
    pub(super) fn new() -> Moments {
        Moments {
            n: 0,
            sumg: 0,
            weight: 0,
            weight_x: 0,
            weight_y: 0,
            xmin: usize::MAX,
            xmax: 0,
            ymin: usize::MAX,
            ymax: 0,
        }
    }

    #[inline]
    pub(super) fn add(
        &mut self,
        (x, y): (usize, usize),
        level: u32,
        corner: (usize, usize),
        threshold: u32,
    ) {
        // Every blob pixel is above the threshold, so its weight is >= 1.
        let w = u64::from(level.saturating_sub(threshold));
        self.n += 1;
        self.sumg += u64::from(level);
        self.weight += w;
        self.weight_x += u128::from(w) * (x - corner.0) as u128;
        self.weight_y += u128::from(w) * (y - corner.1) as u128;
        self.xmin = self.xmin.min(x);
        self.xmax = self.xmax.max(x);
        self.ymin = self.ymin.min(y);
        self.ymax = self.ymax.max(y);
    }
}

impl<G: Grey> Detector<'_, G> {
    /// Step 4 for one particle, the pixels `range` of `blob`: its moments,
    /// and its target (with its pixels, when asked for) if it passes the
    /// filters.
    pub(super) fn measure_particle<const PIXELS: bool>(
        &self,
        range: std::ops::Range<usize>,
        corner: (usize, usize),
        threshold: u32,
        found: &mut Found,
    ) {
        let pixels = &self.blob[range.clone()];
        let mut m = Moments::new();
        for &k in pixels {
            let p = key_index(k);
            m.add(
                self.position(p),
                u32::from(self.levels[p]),
                corner,
                threshold,
            );
        }
        if let Some(mut target) = self.target(&m, corner) {
            if self.parameters.centroid == Centroid::Gaussian {
                let samples = self.peak_samples(pixels, range.len() == self.blob.len());
                (target.x, target.y) = gaussian::gaussian_centre(&samples, (target.x, target.y));
            }
            found.0.push(target);
            if PIXELS {
                found.1.push(
                    pixels
                        .iter()
                        .map(|&k| {
                            let (x, y) = self.position(key_index(k));
                            (x as u32, y as u32)
                        })
                        .collect(),
                );
            }
        }
    }

    /// Whether a particle's sum of grey is at least
    /// [`DetectionParameters::min_snr`](super::DetectionParameters::min_snr) times the noise of a sum over its
    /// pixels: `sumg >= min_snr · sigma · sqrt(n)`, squared in integers.
    pub(super) fn significant(&self, m: &Moments) -> bool {
        let k = u128::from(self.parameters.min_snr);
        let noise = u128::from(self.noise);
        let sumg = u128::from(m.sumg);
        sumg * sumg >= k * k * noise * noise * u128::from(m.n)
    }

    /// Step 4: the target of a particle's moments, if it passes the filters
    /// and does not touch the image border.
    pub(super) fn target(&self, m: &Moments, corner: (usize, usize)) -> Option<Target> {
        let p = self.parameters;
        if m.weight == 0
            || m.xmin == 0
            || m.ymin == 0
            || m.xmax + 1 >= self.width
            || m.ymax + 1 >= self.height
        {
            return None;
        }
        let n = u32::try_from(m.n).unwrap_or(u32::MAX);
        let nx = u32::try_from(m.xmax - m.xmin + 1).unwrap_or(u32::MAX);
        let ny = u32::try_from(m.ymax - m.ymin + 1).unwrap_or(u32::MAX);
        // Levels are in 16-bit grey levels; sumg is in the image's.
        let sumg = (m.sumg + G::LEVEL_SCALE / 2) / G::LEVEL_SCALE;
        let passes = (p.min_pixels..=p.max_pixels).contains(&n)
            && (p.min_nx..=p.max_nx).contains(&nx)
            && (p.min_ny..=p.max_ny).contains(&ny)
            && sumg >= p.min_sumg
            && self.significant(m);
        if !passes {
            return None;
        }
        let weight = m.weight as f64;
        Some(Target {
            x: corner.0 as f64 + 0.5 + m.weight_x as f64 / weight,
            y: corner.1 as f64 + 0.5 + m.weight_y as f64 / weight,
            n,
            nx,
            ny,
            sumg,
        })
    }

    /// The Gaussian centroid's samples ([`crate::photogrammetry::centroid`]) of the
    /// particle whose keys are `pixels`: its brightest pixel (the first in
    /// raster order of equal ones) and the four beside it, each relative to
    /// the peak's window mean (its level less the difference of the raw
    /// samples). A neighbour is usable if it is inside the image and the
    /// mask, and is not another particle's: with `whole` the particle is
    /// the whole blob, else its keys are sorted (`particle << 32 | index`).
    pub(super) fn peak_samples(&self, pixels: &[u64], whole: bool) -> PeakSamples {
        let p = pixels
            .iter()
            .map(|&k| key_index(k))
            .max_by_key(|&q| (self.levels[q], std::cmp::Reverse(q)))
            .unwrap_or(0);
        let (x, y) = self.position(p);
        let sample = |q: usize| {
            let g = self.pixels[q];
            let s = self.background.map_or(g.value(), |b| g.less::<true>(b[q]));
            i64::from(s) * G::LEVEL_SCALE as i64
        };
        let centre = i64::from(self.levels[p]);
        let value = |q: usize| {
            let own = if self.levels[q] != 0 {
                whole
                    || pixels
                        .binary_search(&((pixels[0] & !0xffff_ffff) | q as u64))
                        .is_ok()
            } else {
                self.mask.map_or(true, |mask| mask.uses(q))
            };
            own.then(|| (centre - sample(p) + sample(q)) as f64)
        };
        let (w, h) = (self.width, self.height);
        PeakSamples {
            peak: (x, y),
            centre: centre as f64,
            x: [(x > 0).then(|| p - 1), (x + 1 < w).then_some(p + 1)].map(|q| q.and_then(value)),
            y: [(y > 0).then(|| p - w), (y + 1 < h).then_some(p + w)].map(|q| q.and_then(value)),
        }
    }
}
