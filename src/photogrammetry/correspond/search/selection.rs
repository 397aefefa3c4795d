//! Step 4: best-first selection of the candidate groups, with acceptance
//! thresholds from the frame's own image noise.

use super::completion::CandidateGroups;
use super::{size, Search, NONE};

/// The fewest candidate groups from which the frame's image noise is
/// estimated.
const NOISE_SAMPLE: usize = 50;

impl Search<'_, '_> {
    /// Sets the acceptance threshold from the frame itself.
    ///
    /// The largest groups are nearly all true; their spreads give the image
    /// noise sigma (a member's miss is a 2D residual, so for m rays the mean
    /// squared miss is about 2 sigma^2 (1 - 3/(2m))). A member is then
    /// accepted where it is likelier to be the particle's image than a
    /// stranger's: its miss r has to satisfy
    /// `exp(-r^2 / 2 sigma^2) / (2 pi sigma^2) > density`, i.e.
    /// `r^2 < 2 sigma^2 ln(1 / (2 pi sigma^2 density))`, and at least
    /// 2 sigma and at most 3 sigma (1.1% of true members lost: a group of
    /// four then stays a triplet, a triplet is lost, about 3% of them), and
    /// between a tenth of the tolerance (noise-free data) and the tolerance.
    /// On the benchmark scenes a more lenient limit for a group's last three
    /// members (3.5 or 4 sigma) found fewer particles, not more: the random
    /// groups it lets in take targets from true ones. With fewer than
    /// [`NOISE_SAMPLE`] groups the tolerance stands.
    pub(super) fn estimate_noise(&mut self, groups: &CandidateGroups) {
        let Some(&largest) = groups.sizes.iter().max() else {
            return;
        };
        let mut spreads: Vec<f64> = groups
            .sizes
            .iter()
            .zip(&groups.spreads)
            .filter(|(&size, _)| size == largest)
            .map(|(_, &spread)| spread * spread)
            .collect();
        if spreads.len() < NOISE_SAMPLE {
            return;
        }
        let middle = spreads.len() / 2;
        let (_, median, _) = spreads.select_nth_unstable_by(middle, f64::total_cmp);
        let m = largest as f64;
        let sigma_sq = *median / (2.0 * (1.0 - 1.5 / m));
        let density = self
            .frames
            .iter()
            .map(|f| f.grid.density())
            .fold(0.0, f64::max);
        let odds = 1.0 / (2.0 * std::f64::consts::PI * sigma_sq * density);
        let limit_sq = sigma_sq * (2.0 * odds.max(1.0).ln()).clamp(2.0 * 2.0, 3.0 * 3.0);
        let tolerance = self.matcher.tolerance;
        self.acceptance = limit_sq.sqrt().clamp(tolerance / 10.0, tolerance);
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
