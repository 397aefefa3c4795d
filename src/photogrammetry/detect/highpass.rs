//! Steps 1 and 2 of detection (see the parent module): the high-pass
//! filter, a row at a time from running column sums, and the threshold
//! test on its result, in vector-friendly runs of pixels. The AVX2 copy of
//! these loops is [`Detector::run`]'s (chosen at run time).

use super::{Detector, Grey, Mask, MAX_HIGHPASS_RADIUS};
/// The level of a pixel whose filtered value `g - s/c` exceeds the
/// threshold `t`, given `d = g c - s` and the window size `c`:
/// `round(k d / c)` with `k = LEVEL_SCALE`, kept above `k t` (so its weight
/// is at least 1). It is at most `k g`, which fits in 16 bits.
#[inline]
pub(super) fn level_above<G: Grey>(d: u64, c: u64, threshold: u64) -> u16 {
    let scale = G::LEVEL_SCALE;
    let level = (2 * d * scale + c) / (2 * c);
    level.max(threshold * scale + 1).min(u64::from(u16::MAX)) as u16
}

/// One row of [`HighPass`]'s filter: the window sum of column
/// `x` is the sum of `column_sums` over columns `x-r ..= x+r` (clipped), of
/// `rows * columns` pixels. Keeps the level of every pixel above the
/// threshold in `out`.
pub(super) fn filter_row<G: Grey>(
    row: &[G],
    column_sums: &[u32],
    r: usize,
    rows: u64,
    threshold: u64,
    out: &mut RowOut,
) {
    let width = row.len();
    let mut keep = |x: usize, d: u64, c: u64| out.keep(x, level_above::<G>(d, c, threshold));
    let columns = |x: usize| ((x + r).min(width - 1) - x.saturating_sub(r) + 1) as u64;
    // Columns 0 .. r-1; the loop adds column x + r before it looks at x.
    let mut s: u64 = column_sums[..r.min(width)]
        .iter()
        .map(|&v| u64::from(v))
        .sum();
    // Left edge: columns enter the window, none leave.
    let left_end = (r + 1).min(width);
    for x in 0..left_end {
        if x + r < width {
            s += u64::from(column_sums[x + r]);
        }
        let c = rows * columns(x);
        let gc = u64::from(row[x].value()) * c;
        if gc > s + threshold * c {
            keep(x, gc - s, c);
        }
    }
    // Interior: column x + r enters and x - r - 1 leaves; the window is
    // always rows x (2r + 1). The hot loop of the detector: no bounds
    // checks, the running sum stays in a register.
    let interior_end = width.saturating_sub(r).max(left_end);
    if interior_end > left_end {
        let c = rows * (2 * r + 1) as u64;
        let tc = threshold * c;
        let n = interior_end - left_end;
        // Equal lengths, so that indexing needs no bounds checks; the
        // background is not read unless `BG`.
        let entering = &column_sums[left_end + r..][..n];
        let leaving = &column_sums[left_end - r - 1..][..n];
        let pixels = &row[left_end..][..n];
        let mut k = 0;
        while k < n {
            k = next_above(entering, leaving, pixels, c, tc, &mut s, k);
            if k < n {
                let gc = u64::from(pixels[k].value()) * c;
                keep(left_end + k, gc - s, c);
                k += 1;
            }
        }
    }
    // Right edge: columns leave, none enter.
    for x in interior_end..width {
        if x + r < width {
            s += u64::from(column_sums[x + r]);
        }
        if x > r {
            s -= u64::from(column_sums[x - r - 1]);
        }
        let c = rows * columns(x);
        let gc = u64::from(row[x].value()) * c;
        if gc > s + threshold * c {
            keep(x, gc - s, c);
        }
    }
}

/// [`filter_row`] in 32-bit arithmetic, for when `c (max grey + t)` is
/// below 2^31 for the largest window `c` (8-bit images up to a radius of
/// about 90 at the default threshold, 16-bit ones up to 6). The row's
/// window sums come from a prefix sum of `column_sums` (into `prefix`, one
/// more than the row's columns): the sum over columns `lo..hi` is
/// `prefix[hi] - prefix[lo]`. Wrapping adds are exact, as every true window
/// sum fits. Away from the edges every window has the same size, and the
/// test runs over runs of [`NARROW_RUN`] pixels at once with no dependency
/// from one pixel to the next, which the compiler vectorises, into a bit
/// per pixel ([`run_above`]); only the pixels above are then visited.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn filter_row_narrow<G: Grey>(
    row: &[G],
    column_sums: &[u32],
    prefix: &mut [u32],
    r: usize,
    rows: u32,
    threshold: u32,
    out: &mut RowOut,
) {
    let width = row.len();
    let mut total = 0u32;
    prefix[0] = 0;
    for (p, &sum) in prefix[1..=width].iter_mut().zip(column_sums) {
        total = total.wrapping_add(sum);
        *p = total;
    }
    let prefix = &prefix[..=width];
    let mut keep = |x: usize, d: u32, c: u32| {
        out.keep(
            x,
            level_above::<G>(u64::from(d), u64::from(c), u64::from(threshold)),
        );
    };
    // Edges: the window is clipped, so its size varies.
    let interior = r.min(width)..width.saturating_sub(r).max(r.min(width));
    for x in (0..interior.start).chain(interior.end..width) {
        let (lo, hi) = (x.saturating_sub(r), (x + r).min(width - 1) + 1);
        let s = prefix[hi].wrapping_sub(prefix[lo]);
        let c = rows * (hi - lo) as u32;
        let gc = row[x].value() * c;
        if gc > s + threshold * c {
            keep(x, gc - s, c);
        }
    }
    // Interior: windows of `rows x (2r + 1)`.
    let n = interior.len();
    if n == 0 {
        return;
    }
    let c = rows * (2 * r + 1) as u32;
    let tc = threshold * c;
    let upper = &prefix[interior.start + r + 1..][..n];
    let lower = &prefix[interior.start - r..][..n];
    let pixels = &row[interior.start..][..n];
    let mut start = 0;
    while start < n {
        let end = (start + NARROW_RUN).min(n);
        let mut above = run_above(
            &pixels[start..end],
            &upper[start..end],
            &lower[start..end],
            c,
            tc,
        );
        // The pixels above, one bit each: only they are visited.
        while above != 0 {
            let k = start + above.trailing_zeros() as usize;
            above &= above - 1;
            let d = (pixels[k].value() * c).wrapping_sub(upper[k].wrapping_sub(lower[k]));
            keep(interior.start + k, d, c);
        }
        start = end;
    }
}

/// Which pixels of a run (at most 32) are above the threshold, as bits
/// (pixel `k` is bit `k`): `g c > s + t c` with `s = upper - lower`, all in
/// 32 bits (see [`filter_row_narrow`]). No pixel depends on another, so
/// the compiler vectorises it; the caller visits only the set bits, with
/// no branch per pixel to mispredict.
#[inline(always)]
pub(super) fn run_above<G: Grey>(
    pixels: &[G],
    upper: &[u32],
    lower: &[u32],
    c: u32,
    tc: u32,
) -> u32 {
    let n = pixels.len();
    let (upper, lower) = (&upper[..n], &lower[..n]);
    let mut above = 0u32;
    for k in 0..n {
        let gc = pixels[k].value() * c;
        let s = upper[k].wrapping_sub(lower[k]);
        above |= u32::from(gc > s + tc) << k;
    }
    above
}

/// Pixels [`filter_row_narrow`] tests at once.
pub(super) const NARROW_RUN: usize = 32;

/// The hot loop of [`filter_row`]'s interior: from pixel `k` on, slides the
/// window sum `s` one column at a time (column `k`'s window gains
/// `entering[k]` and loses `leaving[k]`) until a pixel's `g c` exceeds
/// `s + t c`, and returns that pixel (or the row's end). Apart from the
/// caller, so that everything it needs stays in registers: one add on the
/// running sum's dependency chain, a multiply and a compare per pixel.
#[allow(clippy::too_many_arguments)]
#[inline(never)]
pub(super) fn next_above<G: Grey>(
    entering: &[u32],
    leaving: &[u32],
    pixels: &[G],
    c: u64,
    tc: u64,
    s: &mut u64,
    mut k: usize,
) -> usize {
    let n = pixels.len();
    // Equal lengths, so that indexing needs no bounds checks.
    let (entering, leaving) = (&entering[..n], &leaving[..n]);
    let mut sum = *s;
    while k < n {
        sum = sum.wrapping_add_signed(i64::from(entering[k]) - i64::from(leaving[k]));
        if u64::from(pixels[k].value()) * c > sum + tc {
            break;
        }
        k += 1;
    }
    *s = sum;
    k
}

/// any, saturating at 0: the image's own row, or the difference written
/// into `scratch` (one row long).
#[inline(always)]
pub(super) fn subtracted_row<'s, G: Grey>(
    pixels: &'s [G],
    background: Option<&[G]>,
    width: usize,
    row: usize,
    scratch: &'s mut [G],
) -> &'s [G] {
    let samples = &pixels[row * width..(row + 1) * width];
    match background {
        Some(background) => {
            let behind = &background[row * width..(row + 1) * width];
            for ((out, &g), &b) in scratch.iter_mut().zip(samples).zip(behind) {
                *out = g.saturating_less(b);
            }
            &scratch[..width]
        }
        None => samples,
    }
}

/// Where [`HighPass`] keeps one row's pixels above the threshold: their
/// levels in the row's part of the image's `levels`, their count in
/// `above`, and their blocks in `marks`, one bit per block of 64 pixels in
/// raster order (block `i` holds pixels `64 i .. 64 i + 63`, bit `i % 64`
/// of word `i / 64`). [`Detector::find_blobs`] looks for blobs only in
/// marked blocks; a block stays marked once its blobs are measured (and
/// its levels cleared), so the marks are a superset of the blocks that
/// hold levels, which is all the search needs.
pub(super) struct RowOut<'a> {
    /// The row's levels.
    pub(super) levels: &'a mut [u16],
    /// The row's first pixel (`y * width`).
    pub(super) start: usize,
    pub(super) marks: &'a mut [u64],
    pub(super) above: &'a mut usize,
}

impl RowOut<'_> {
    /// Keeps pixel `x` of the row, above the threshold, at `level`.
    #[inline(always)]
    fn keep(&mut self, x: usize, level: u16) {
        self.levels[x] = level;
        *self.above += 1;
        let block = (self.start + x) >> 6;
        self.marks[block >> 6] |= 1 << (block & 63);
    }
}

/// Steps 1 and 2, one row at a time: the high-pass filtered value of every
/// pixel above the threshold, as its level, for [`Detector::run`] to find
/// blobs in the rows done while the rows are still in cache.
///
/// For pixel value `g`, window sum `s` and window size `c` the filtered
/// value is `g - s / c`; the test `g - s/c > t` is done exactly as
/// `g c > s + t c` in integers, and only pixels that pass are divided. The
/// level is the filtered value in 16-bit grey levels, rounded and kept above
/// the threshold, so every blob pixel has a weight of at least 1. The
/// background, if any, is subtracted a row at a time (saturating at 0) into
/// three rows of scratch (the rows entering and leaving the window and the
/// row being filtered), one vector instruction for many samples; no copy of
/// the image is made. Masked-out pixels are never above the threshold (they
/// still count in their neighbours' background means).
pub(super) struct HighPass<'a, G: Grey> {
    pixels: &'a [G],
    background: Option<&'a [G]>,
    mask: Option<&'a Mask>,
    width: usize,
    height: usize,
    r: usize,
    threshold: u64,
    /// 32-bit arithmetic: every sum and product fits (see
    /// [`filter_row_narrow`]).
    narrow: bool,
    /// Window sums of each column over the rows of the current window.
    column_sums: Vec<u32>,
    /// [`filter_row_narrow`]'s prefix sums (`width + 1`), if narrow.
    prefix: Vec<u32>,
    /// Rows less the background (empty without one).
    entering: Vec<G>,
    leaving: Vec<G>,
    current: Vec<G>,
    /// The next row to filter.
    next: usize,
}

impl<'a, G: Grey> HighPass<'a, G> {
    pub(super) fn new(detector: &Detector<'a, G>) -> Self {
        let (width, height) = (detector.width, detector.height);
        let threshold = u64::from(detector.parameters.threshold);
        let r = detector.parameters.highpass_radius.min(MAX_HIGHPASS_RADIUS) as usize;
        let window = ((2 * r + 1).min(height) * (2 * r + 1).min(width)) as u64;
        let narrow = r > 0
            && window
                .checked_mul(G::MAX_VALUE + threshold)
                .is_some_and(|m| m < 1 << 31);
        let scratch = if detector.background.is_some() {
            width
        } else {
            0
        };
        let mut filter = HighPass {
            pixels: detector.pixels,
            background: detector.background,
            mask: detector.mask,
            width,
            height,
            r,
            threshold,
            narrow,
            column_sums: vec![0; if r > 0 { width } else { 0 }],
            prefix: vec![0; if narrow { width + 1 } else { 0 }],
            entering: vec![G::ZERO; scratch],
            leaving: vec![G::ZERO; scratch],
            current: vec![G::ZERO; scratch],
            next: 0,
        };
        if r > 0 {
            for row in 0..r.min(height) {
                let row = subtracted_row(
                    filter.pixels,
                    filter.background,
                    width,
                    row,
                    &mut filter.entering,
                );
                for (sum, &g) in filter.column_sums.iter_mut().zip(row) {
                    *sum += g.value();
                }
            }
        }
        filter
    }

    /// Filters the next row into its part of `levels` (the whole image's,
    /// 0 where below the threshold), counts its pixels above the threshold
    /// in `above`, marks their blocks in `marks` (see [`RowOut`]), and
    /// returns the row; `None` once all rows are done.
    #[inline(always)]
    pub(super) fn next_row(
        &mut self,
        levels: &mut [u16],
        marks: &mut [u64],
        above: &mut usize,
    ) -> Option<usize> {
        let (y, width, height, r) = (self.next, self.width, self.height, self.r);
        let (pixels, background) = (self.pixels, self.background);
        if y >= height {
            return None;
        }
        self.next += 1;
        let before = *above;
        let mut out = RowOut {
            levels: &mut levels[y * width..(y + 1) * width],
            start: y * width,
            marks,
            above,
        };
        if r == 0 {
            let threshold = self.threshold;
            let row = subtracted_row(pixels, background, width, y, &mut self.current);
            for (x, &g) in row.iter().enumerate() {
                if u64::from(g.value()) > threshold {
                    out.keep(x, (u64::from(g.value()) * G::LEVEL_SCALE) as u16);
                }
            }
        } else {
            // Row y + r enters the window and row y - r - 1 leaves it; one
            // pass over the sums when both happen (the compiler vectorises
            // these loops; the sums never go below 0, so wrapping is exact).
            let mut sums = std::mem::take(&mut self.column_sums);
            match (y + r < height, y > r) {
                (true, true) => {
                    let new = subtracted_row(pixels, background, width, y + r, &mut self.entering);
                    let old =
                        subtracted_row(pixels, background, width, y - r - 1, &mut self.leaving);
                    for ((sum, &new), &old) in sums.iter_mut().zip(new).zip(old) {
                        *sum = sum.wrapping_add(new.value()).wrapping_sub(old.value());
                    }
                }
                (true, false) => {
                    let new = subtracted_row(pixels, background, width, y + r, &mut self.entering);
                    for (sum, &g) in sums.iter_mut().zip(new) {
                        *sum += g.value();
                    }
                }
                (false, true) => {
                    let old =
                        subtracted_row(pixels, background, width, y - r - 1, &mut self.leaving);
                    for (sum, &g) in sums.iter_mut().zip(old) {
                        *sum -= g.value();
                    }
                }
                (false, false) => {}
            }
            let rows = ((y + r).min(height - 1) - y.saturating_sub(r) + 1) as u64;
            let threshold = self.threshold;
            let (narrow, mut prefix) = (self.narrow, std::mem::take(&mut self.prefix));
            let row = subtracted_row(pixels, background, width, y, &mut self.current);
            if narrow {
                filter_row_narrow(
                    row,
                    &sums,
                    &mut prefix,
                    r,
                    rows as u32,
                    threshold as u32,
                    &mut out,
                );
            } else {
                filter_row(row, &sums, r, rows, threshold, &mut out);
            }
            self.prefix = prefix;
            self.column_sums = sums;
        }
        if let Some(mask) = self.mask {
            if *out.above > before {
                for (x, level) in out.levels.iter_mut().enumerate() {
                    if *level != 0 && !mask.uses(y * width + x) {
                        *level = 0;
                        *out.above -= 1;
                    }
                }
            }
        }
        Some(y)
    }
}

impl<G: Grey> Detector<'_, G> {
    /// Steps 1 and 2 for the whole image at once: fills `levels` and
    /// `above` (see [`HighPass`]).
    #[cfg(test)]
    pub(super) fn highpass_threshold(&mut self) {
        self.levels = vec![0; self.width * self.height];
        self.marks = vec![0; (self.width * self.height).div_ceil(64 * 64)];
        self.above = 0;
        let mut filter = HighPass::new(self);
        while filter
            .next_row(&mut self.levels, &mut self.marks, &mut self.above)
            .is_some()
        {}
        if self.wants_noise() {
            self.noise = self.sample_noise();
        }
    }
}
