//! Step 4: best-first selection of the candidate groups, with acceptance
//! thresholds from the frame's own image noise; and, for a band wider than
//! that noise needs, the probe that measures it first and narrows the band.

use super::completion::{CandidateGroups, Completion};
use super::{size, Search, NONE};
use crate::photogrammetry::statistics::chi_square_quantile;

/// The fewest candidate groups from which the frame's image noise is
/// estimated.
const NOISE_SAMPLE: usize = 50;

/// How many seed targets with a group of every camera the probe of a wide
/// band looks for ([`Search::first_stage`]): the median of 100 squared
/// spreads is within about 8% (one standard deviation) of the true one, the
/// noise within 4%.
const PROBE_GROUPS: usize = 100;

/// The probe visits at most this share of the first seed camera's targets.
const PROBE_SHARE: usize = 4;

/// The band a wide one is narrowed to covers a true pair's epipolar
/// distance to this many of its standard deviations: 3.5 loses 5 in 10,000
/// true pairs (normal tails), fewer where the cameras' scales differ less
/// than the bound `pair_scale` takes, and with four or more cameras those
/// are still found from the other seed pair. (A 0.5 px band at 0.1 px
/// noise, the benchmark's, is 3.3 of them; 4 cost the benchmark 8% more
/// work at 2 px for no more particles.)
const BAND_SIGMAS: f64 = 3.5;

/// The golden ratio's fractional part: the probe's k-th target is at
/// `frac(k * GOLDEN) * n`, a sequence that covers the targets (filed in
/// cell order, i.e. over the image) evenly at every length.
const GOLDEN: f64 = 0.618_033_988_749_894_9;

impl Search<'_, '_> {
    /// The frame's image noise (sigma^2, px^2) from candidate groups: each
    /// seed target's best group of the largest size, or `None` with fewer
    /// than [`NOISE_SAMPLE`] of them.
    ///
    /// The largest groups are nearly all true; their spreads give the image
    /// noise sigma. A member's miss is a 2D residual, so for m rays the
    /// summed squared misses are sigma^2 times a chi-square of k = 2m - 3
    /// degrees of freedom (2m coordinates, 3 for the point), whose median
    /// is `k (1 - 2/(9k))^3` (Wilson-Hilferty; 4.36 for k = 5, exactly
    /// 4.35): sigma^2 is the median squared spread times m over that.
    ///
    /// Only one group per seed target counts, its best: in a wide band a
    /// target has many candidate groups of every size, nearly all of them
    /// random, and counted together those would be the majority and set
    /// the noise to the band's width. A target's best group is true
    /// wherever the particle is seen by every camera (73% of seed targets
    /// with 10% dropout); the others' best groups are random, and in a wide
    /// band most of them are of the largest size too, so the median is a
    /// true group's 70th percentile or so (on the benchmark at 2 px, sigma
    /// 0.113 px for 0.1). A lower quantile would be closer there, but on a
    /// rough calibration, whose errors vary over the volume, it is not the
    /// bulk's: the lower quartile narrowed test_cavity's 16.7 px band to
    /// 14.6 px and lost 3% of its particles; the median left it.
    fn noise(&self, groups: &CandidateGroups) -> Option<f64> {
        let largest = groups
            .sizes
            .iter()
            .zip(&groups.best)
            .filter(|(_, &best)| best)
            .map(|(&size, _)| size)
            .max()?;
        let mut spreads: Vec<f64> = (0..groups.sizes.len())
            .filter(|&g| groups.best[g] && groups.sizes[g] == largest)
            .map(|g| groups.spreads[g] * groups.spreads[g])
            .collect();
        if spreads.len() < NOISE_SAMPLE {
            return None;
        }
        let middle = spreads.len() / 2;
        let (_, median, _) = spreads.select_nth_unstable_by(middle, f64::total_cmp);
        let m = largest as f64;
        let k = 2.0 * m - 3.0;
        Some(*median * m / chi_square_quantile(k, 0.0))
    }

    /// Sets the acceptance threshold from the frame itself (see
    /// [`Search::noise`]).
    ///
    /// A member is accepted where it is likelier to be the particle's image
    /// than a stranger's: its miss r has to satisfy
    /// `exp(-r^2 / 2 sigma^2) / (2 pi sigma^2) > density`, i.e.
    /// `r^2 < 2 sigma^2 ln(1 / (2 pi sigma^2 density))`, and at least
    /// 2 sigma and at most 3 sigma (1.1% of true members lost: a group of
    /// four then stays a triplet, a triplet is lost, about 3% of them), and
    /// between a tenth of the narrowest band (noise-free data; the band, or
    /// 0.5 px for a wider one) and the tolerance. The band the user gives
    /// is only the upper bound: in a wide band a member that misses by many
    /// sigma is dropped, and its group falls back to the smaller one
    /// (`select`). On the benchmark scenes a more lenient limit for a
    /// group's last three members (3.5 or 4 sigma) found fewer particles,
    /// not more: the random groups it lets in take targets from true ones.
    /// With fewer than [`NOISE_SAMPLE`] groups the tolerance stands.
    pub(super) fn estimate_noise(&mut self, groups: &CandidateGroups) {
        let Some(sigma_sq) = self.noise(groups) else {
            return;
        };
        let density = self
            .frames
            .iter()
            .map(|f| f.grid.density())
            .fold(0.0, f64::max);
        let odds = 1.0 / (2.0 * std::f64::consts::PI * sigma_sq * density);
        let limit_sq = sigma_sq * (2.0 * odds.max(1.0).ln()).clamp(2.0 * 2.0, 3.0 * 3.0);
        let tolerance = self.matcher.tolerance;
        self.acceptance = limit_sq
            .sqrt()
            .clamp(self.matcher.narrowest_band / 10.0, tolerance);
    }

    /// Steps 2 and 3 for the first seed pair. A band wider than the
    /// narrowest the matcher prepared (0.5 px) is first probed: seed
    /// targets spread over the image are completed in the full band until
    /// [`PROBE_GROUPS`] of them have a group of every camera (or a quarter
    /// of the targets were tried), their best groups give the frame's noise
    /// ([`Search::noise`]), and the rest of the search runs in the band
    /// that noise needs: [`BAND_SIGMAS`] standard deviations of a true
    /// pair's epipolar distance (sigma in each image, scaled between the
    /// cameras' pixels), never below the narrowest band, never above the
    /// tolerance.
    ///
    /// A band wider than the noise finds nothing true that the narrow one
    /// misses, since no member may miss by more than the acceptance (3
    /// sigma at most), while its candidates grow with its width (partners
    /// in the band) and its square (completion around each), and random
    /// groups crowd out true ones in the per-target caps. Where the frame's
    /// noise is as wide as the band (a rough calibration, the case wide
    /// bands are for), the band stays.
    pub(super) fn first_stage(&mut self, seed: (usize, usize)) -> CandidateGroups {
        let (i, count) = (seed.0, self.frames.len());
        let n = self.frames[i].targets.len();
        let mut groups = CandidateGroups::default();
        let mut scratch = Completion::new(count);
        let mut probed = Vec::new();
        if self.band_px > self.matcher.narrowest_band && n > 0 {
            probed.resize(n, false);
            let mut full = 0;
            for k in 0..n.div_ceil(PROBE_SHARE) {
                if self.should_stop(k) {
                    return groups;
                }
                let a = ((k as f64 * GOLDEN).fract() * n as f64) as usize;
                if std::mem::replace(&mut probed[a], true) {
                    continue;
                }
                let start = groups.sizes.len();
                if self.complete(seed, a, &mut scratch, &mut groups) > 0
                    && groups.sizes[start] == count
                {
                    full += 1;
                    if full == PROBE_GROUPS {
                        break;
                    }
                }
            }
            if let Some(sigma_sq) = self.noise(&groups) {
                let band = (BAND_SIGMAS * sigma_sq.sqrt() * self.matcher.pair_scale)
                    .clamp(self.matcher.narrowest_band, self.band_px);
                if band < self.band_px {
                    self.band_px = band;
                    // The pencil grids' sectors follow the band's width.
                    self.pencil_grids.fill_with(|| None);
                }
            }
        }
        for a in 0..n {
            if self.should_stop(a) {
                break;
            }
            if probed.get(a).copied().unwrap_or(false) {
                continue;
            }
            self.complete(seed, a, &mut scratch, &mut groups);
        }
        groups
    }

    /// Every group of `groups` within the acceptance threshold (trimmed to
    /// it where a member misses by more), each member set once (`kept`),
    /// none marking its targets used.
    pub(super) fn keep_all(
        &mut self,
        groups: CandidateGroups,
        kept: &mut std::collections::HashSet<Vec<u32>>,
    ) {
        let count = self.frames.len();
        let mut members = groups.members;
        let limit = self.acceptance;
        for g in 0..groups.sizes.len() {
            let group = &mut members[g * count..(g + 1) * count];
            if groups.largest[g] > limit && self.trim(group, limit, |_| false).is_none() {
                continue;
            }
            if size(group) >= 3 && kept.insert(group.to_vec()) {
                self.accepted.extend_from_slice(group);
            }
        }
    }

    /// Step 4: best-first selection of groups of three or more.
    pub(super) fn select(&mut self, groups: CandidateGroups) {
        let count = self.frames.len();
        // Re-trim every candidate to the acceptance threshold (those within
        // it already stand as they are), then order.
        let mut ranked: Vec<(usize, f64, usize)> = Vec::with_capacity(groups.sizes.len());
        let mut members = groups.members;
        let limit = self.acceptance;
        for g in 0..groups.sizes.len() {
            if groups.largest[g] <= limit {
                ranked.push((groups.sizes[g], groups.spreads[g], g));
                continue;
            }
            let group = &mut members[g * count..(g + 1) * count];
            if let Some(fit) = self.trim(group, limit, |_| false) {
                ranked.push((size(group), fit.spread, g));
            }
        }
        ranked.sort_unstable_by(|x, y| y.0.cmp(&x.0).then(x.1.total_cmp(&y.1)));
        for (_, _, g) in ranked {
            let group = &members[g * count..(g + 1) * count];
            let free = group
                .iter()
                .enumerate()
                .all(|(k, &m)| m == NONE || !self.used[k][m as usize]);
            if free {
                self.keep(group);
            }
        }
    }
}
