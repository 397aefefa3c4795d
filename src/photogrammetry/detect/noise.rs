//! The image's noise level after the high-pass filter, estimated on a
//! sparse sample before the filter runs (see the parent module, step 3).

use super::highpass::subtracted_row;
use super::{Detector, Grey, MAX_HIGHPASS_RADIUS};
/// Rows on which the noise level is sampled (fewer on shorter images).
pub(super) const NOISE_ROWS: usize = 32;

/// Samples of the noise level, at most: a quantile-based sigma of `N`
/// samples has a relative standard error of about `1.2 / sqrt(N)`, 1.2% at
/// 10,000, far below what the rules need.
pub(super) const NOISE_SAMPLES: usize = 1 << 14;

/// Where the noise level is sampled: the first sampled row, the step from
/// one to the next, and the step between sampled pixels of a row.
/// [`NOISE_ROWS`] rows spread evenly over the image, each sampled every
/// `column_step`-th pixel so that at most about [`NOISE_SAMPLES`] pixels
/// are (every 4th pixel of 32 rows of a 1280x1024 frame: 10,240 samples).
/// A sampled row's filtered values need its window's `2r + 1` rows summed,
/// so rows far apart cost less than many close together: at the default
/// radius, 32 windows of 21 rows are two thirds of a 1024-row image, where
/// every 16th row (windows that overlap) took every row in and out once.
/// Rows are what the sample is short of on real images, whose structure is
/// correlated along a row: on the test_cavity recording (defaults,
/// `tests/photogrammetry/real_recording.rs`) 16 rows gave 2.71x OpenPTV's
/// count, 32 rows 2.62x, the 64 rows of before 2.65x.
pub(super) fn noise_steps(width: usize, height: usize) -> (usize, usize, usize) {
    let rows = NOISE_ROWS.min(height);
    let row_step = height / rows;
    let column_step = (rows * width).div_ceil(NOISE_SAMPLES).max(1);
    (row_step / 2, row_step, column_step)
}

/// Appends to `out` the high-pass filtered value, signed and in levels
/// (`LEVEL_SCALE` times grey levels, rounded down), of every
/// `column_step`-th pixel of `row`, with the window sums of
/// [`filter_row`](super::highpass::filter_row) (`column_sums` over `rows` rows, radius `r`; `row` less
/// the background if any). `prefix`
/// is scratch (the running sums of `column_sums`). One pass of additions
/// over the row, on a sampled row only.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn sample_filtered_row<G: Grey>(
    row: &[G],
    column_sums: &[u32],
    r: usize,
    rows: u64,
    column_step: usize,
    prefix: &mut Vec<u64>,
    out: &mut Vec<i32>,
) {
    let width = row.len();
    prefix.clear();
    prefix.push(0);
    let mut total = 0u64;
    for &v in column_sums {
        total += u64::from(v);
        prefix.push(total);
    }
    for x in (0..width).step_by(column_step) {
        let (lo, hi) = (x.saturating_sub(r), (x + r + 1).min(width));
        let s = (prefix[hi] - prefix[lo]) as i64;
        let c = (rows * (hi - lo) as u64) as i64;
        let g = i64::from(row[x].value());
        let level = (g * c - s) * G::LEVEL_SCALE as i64;
        out.push(level.div_euclid(c) as i32);
    }
}

/// The noise level (levels, standard deviation) of a sample of high-pass
/// filtered values: `1.4826 (median - q25)`, the robust standard deviation
/// of the sample's lower half. Particles only add to the filtered values,
/// so the lower half is the background's: pixel noise, and whatever
/// faint structure the filter leaves at the particles' scale. 0 for an
/// empty sample.
pub(super) fn noise_sigma(samples: &mut [i32]) -> u32 {
    if samples.is_empty() {
        return 0;
    }
    let middle = samples.len() / 2;
    let (lower, &mut median, _) = samples.select_nth_unstable(middle);
    if lower.is_empty() {
        return 0;
    }
    let quarter = lower.len() / 2;
    let q25 = *lower.select_nth_unstable(quarter).1;
    let spread = i64::from(median) - i64::from(q25);
    (spread.max(0) * 14826 / 10000).min(i64::from(u32::MAX)) as u32
}

impl<G: Grey> Detector<'_, G> {
    /// The image's noise level after the high-pass filter: [`noise_sigma`]
    /// of the filtered values on the sample grid of [`noise_steps`]. It is
    /// computed ahead of the filter, so that blobs can be measured while the
    /// filter runs: the window sums of the sampled rows come from column
    /// sums carried from one sampled row's window to the next (rows between
    /// windows are skipped), at most one pass of additions in and one out
    /// over the image, and only the sampled pixels are divided.
    #[inline(always)]
    pub(super) fn sample_noise(&self) -> u32 {
        let (width, height) = (self.width, self.height);
        let r = self.parameters.highpass_radius.min(MAX_HIGHPASS_RADIUS) as usize;
        let (first_row, row_step, column_step) = noise_steps(width, height);
        let mut samples = Vec::new();
        let mut scratch = vec![G::ZERO; if self.background.is_some() { width } else { 0 }];
        let (pixels, background) = (self.pixels, self.background);
        if r == 0 {
            // No filter: the filtered value is the value.
            for y in (first_row..height).step_by(row_step) {
                let row = subtracted_row(pixels, background, width, y, &mut scratch);
                for &g in row.iter().step_by(column_step) {
                    samples.push((u64::from(g.value()) * G::LEVEL_SCALE) as i32);
                }
            }
            return noise_sigma(&mut samples);
        }
        let mut sums = vec![0u32; width];
        let mut prefix = Vec::new();
        // The rows `low..high` are in `sums`.
        let (mut low, mut high) = (0, 0);
        for y in (first_row..height).step_by(row_step) {
            let (want_low, want_high) = (y.saturating_sub(r), (y + r + 1).min(height));
            if want_low >= high {
                sums.fill(0);
                (low, high) = (want_low, want_low);
            }
            for row in high..want_high {
                let row = subtracted_row(pixels, background, width, row, &mut scratch);
                for (sum, &g) in sums.iter_mut().zip(row) {
                    *sum += g.value();
                }
            }
            for row in low..want_low {
                let row = subtracted_row(pixels, background, width, row, &mut scratch);
                for (sum, &g) in sums.iter_mut().zip(row) {
                    *sum -= g.value();
                }
            }
            (low, high) = (want_low, want_high);
            let rows = (want_high - want_low) as u64;
            let row = subtracted_row(pixels, background, width, y, &mut scratch);
            sample_filtered_row(row, &sums, r, rows, column_step, &mut prefix, &mut samples);
        }
        noise_sigma(&mut samples)
    }

    /// Whether a rule needs the image's noise level: the significance test
    /// ([`DetectionParameters::min_snr`](super::DetectionParameters::min_snr)) or the automatic split rule.
    pub(super) fn wants_noise(&self) -> bool {
        let p = self.parameters;
        p.min_snr > 0 || (p.split && p.split_depth.is_none())
    }
}
