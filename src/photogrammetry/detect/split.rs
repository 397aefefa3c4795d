//! Step 3 (see the parent module): splitting a blob of several local
//! maxima by flooding it from the top, with the absolute (OpenPTV's
//! `discont`) or the automatic rule, and the automatic rule's deferral of
//! such blobs to the end of the frame.

use super::centroid::Moments;
use super::{
    key, key_index, key_level, Detector, Found, Grey, Mask, TooManyTargets, AUTO_SPLIT_CAP,
    AUTO_SPLIT_FRACTION, AUTO_SPLIT_NOISE_STRUCTURED, STRUCTURED_SPLITS,
};
use crate::photogrammetry::centroid::Centroid;
/// "No region / not yet visited" in the splitting step.
pub(super) const NONE: u32 = u32::MAX;

/// The most particles of a split blob whose moments are summed in one pass
/// over its pixels ([`Detector::split_and_measure`]): 1,024 moments, 96 KiB
/// of scratch kept from blob to blob; a blob parted into more is sorted by
/// particle and measured one particle at a time, so the scratch stays
/// bounded whatever the image.
const MOMENTS_IN_PASS: usize = 1024;

/// The largest blob whose split reserves room for half its pixels as
/// local maxima rather than counting them (4,096 pixels: 24 KiB of
/// regions and particle numbers at most, 40 KiB with the automatic rule).
const COUNTED_BLOB: usize = 1 << 12;

/// Blobs of fewer pixels are sorted by comparison ([`sort_keys`]); the
/// radix sort's passes cost more than they save below this.
const RADIX_FROM: usize = 256;

/// The most keys [`sort_keys`] sorts by radix: its scratch (8 bytes a key,
/// kept from blob to blob) stays within 8 MiB; a larger blob is sorted in
/// place by comparison, so a hostile frame's one huge blob costs no more
/// memory than before.
pub(super) const RADIX_UP_TO: usize = 1 << 20;

/// Sorts a blob's [`key`]s ascending: bright to dark, equal levels in
/// raster order. Keys are distinct (each holds its pixel's index), so
/// every correct sort gives the same order. Blobs of [`RADIX_FROM`] to
/// [`RADIX_UP_TO`] pixels, and no more than `most` (the detector's
/// [`Detector::radix_most`]), are sorted by least-significant-digit radix, a
/// byte a pass, over only the bytes in which the keys differ (for a real
/// frame's blob of a few thousand pixels, about two of the level and
/// three of the index): a counting pass over all of them at once, then a
/// stable scatter a byte, between `keys` and `scratch`. Comparison sorts
/// of thousands of keys, whose order is hard to predict, cost about twice
/// as many instructions and many mispredicted branches.
pub(super) fn sort_keys(keys: &mut [u64], scratch: &mut Vec<u64>, most: usize) {
    if keys.len() < RADIX_FROM || keys.len() > most.min(RADIX_UP_TO) {
        keys.sort_unstable();
        return;
    }
    let differ = keys.iter().fold(0, |d, &k| d | (k ^ keys[0]));
    let mut digits = [0u32; 8];
    let mut passes = 0;
    for d in 0..8 {
        if (differ >> (8 * d)) & 0xff != 0 {
            digits[passes] = d;
            passes += 1;
        }
    }
    let digits = &digits[..passes];
    let mut counts = [[0u32; 256]; 8];
    for &k in keys.iter() {
        for (i, &d) in digits.iter().enumerate() {
            counts[i][((k >> (8 * d)) & 0xff) as usize] += 1;
        }
    }
    // Every scratch key is written before it is read: only its growth is
    // filled.
    if scratch.len() < keys.len() {
        scratch.resize(keys.len(), 0);
    }
    let scratch = &mut scratch[..keys.len()];
    let mut from_keys = true;
    for (i, &d) in digits.iter().enumerate() {
        let mut starts = [0u32; 256];
        let mut sum = 0;
        for (start, &count) in starts.iter_mut().zip(&counts[i]) {
            *start = sum;
            sum += count;
        }
        let (source, target): (&[u64], &mut [u64]) = if from_keys {
            (&*keys, &mut *scratch)
        } else {
            (&*scratch, &mut *keys)
        };
        for &k in source {
            let digit = ((k >> (8 * d)) & 0xff) as usize;
            target[starts[digit] as usize] = k;
            starts[digit] += 1;
        }
        from_keys = !from_keys;
    }
    if !from_keys {
        keys.copy_from_slice(scratch);
    }
}

/// The most keys of deferred blobs kept for their split at the end of the
/// frame ([`Detector::store_deferred`]): 2^20, 8 MiB.
const STORED_KEYS: usize = 1 << 20;

/// A deferred blob whose keys are kept ([`Detector::store_deferred`]):
/// where they are in `stored_keys`, and its bounding box.
#[derive(Clone, Copy, Debug)]
pub(super) struct StoredBlob {
    start: u32,
    len: u32,
    corner: (u32, u32),
    size: (u32, u32),
}

#[derive(Clone, Copy, Debug)]
pub(super) struct Region {
    parent: u32,
    /// The grey value of its maximum.
    peak: u32,
}

#[derive(Clone, Copy)]
pub(super) enum SplitRule {
    /// It rises above the saddle by more than this.
    Absolute(u32),
    /// It rises by more than `noise` and than a fraction
    /// ([`AUTO_SPLIT_FRACTION`]) of its height above `threshold`.
    /// And its cap (its pixels brighter than the saddle) holds a volume
    /// above the saddle of more than `cap` times the square root of its
    /// pixel count ([`AUTO_SPLIT_CAP`] times the noise level).
    Auto {
        noise: u32,
        threshold: u32,
        cap: u32,
    },
}

impl<G: Grey> Detector<'_, G> {
    /// The automatic split rule's blobs with several maxima, deferred by
    /// [`Detector::measure_blob`]: split with [`AUTO_SPLIT_NOISE`](super::AUTO_SPLIT_NOISE); if
    /// that parts more targets than chance overlaps explain
    /// ([`Detector::structured`]), split again with
    /// [`AUTO_SPLIT_NOISE_STRUCTURED`] instead. Each is flooded again from
    /// its seed; at the end their levels are cleared by their marks.
    ///
    /// With a limit: once the first split's targets and `found` are more
    /// than the limit, the first split's targets are counted (and their
    /// sizes kept), no longer kept; if the frame is then not structured it
    /// has those targets and detection stops ([`TooManyTargets`]), else
    /// every deferred blob is measured again with the higher floor, and
    /// detection stops as soon as `found` passes the limit.
    pub(super) fn split_deferred<const PIXELS: bool>(
        &mut self,
        found: &mut Found,
    ) -> Result<(), TooManyTargets> {
        if self.deferred.is_empty() {
            return Ok(());
        }
        self.reserve_blob(None);
        let mut fine: Found = (Vec::new(), Vec::new());
        // Per deferred blob: whether a saddle kept particles apart, and
        // where its targets in `fine` end.
        let mut first = Vec::with_capacity(self.deferred.len());
        let mut parted = 0;
        // The first split's targets, kept in `fine` or only counted.
        let mut counted = 0;
        let mut kept = true;
        for blob in 0..self.deferred.len() {
            let before = fine.0.len();
            self.measure_deferred::<PIXELS>(blob, &mut fine);
            let new = fine.0.len() - before;
            parted += new.saturating_sub(1);
            counted += new;
            first.push((self.kept_apart, counted));
            if kept && found.0.len() + counted > self.limit {
                kept = false;
                self.target_sizes.extend(fine.0.iter().map(|t| t.n));
                fine = (Vec::new(), Vec::new());
            } else if !kept {
                self.target_sizes.extend(fine.0.iter().map(|t| t.n));
                fine.0.clear();
                fine.1.clear();
            }
        }
        if kept {
            self.target_sizes.extend(fine.0.iter().map(|t| t.n));
        }
        if self.structured(found.0.len() + counted, parted) {
            self.split_noise = AUTO_SPLIT_NOISE_STRUCTURED;
            let mut pixels = fine.1.into_iter();
            let mut start = 0;
            for (blob, &(kept_apart, end)) in first.iter().enumerate() {
                if kept_apart || !kept {
                    if PIXELS && kept {
                        pixels.by_ref().take(end - start).for_each(drop);
                    }
                    self.measure_deferred::<PIXELS>(blob, found);
                    self.check_limit(found)?;
                } else {
                    // Every saddle merged all the particles it met into
                    // one: each region merged was insignificant with the
                    // lower floor, so with the higher one too, and whichever
                    // region anchors them the union is the same, so the
                    // flood goes through the same states with either floor
                    // and its target stands.
                    found.0.extend_from_slice(&fine.0[start..end]);
                    if PIXELS {
                        found.1.extend(pixels.by_ref().take(end - start));
                    }
                    self.check_limit(found)?;
                }
                start = end;
            }
        } else if !kept {
            return Err(TooManyTargets { limit: self.limit });
        } else {
            found.0.append(&mut fine.0);
            found.1.append(&mut fine.1);
            self.check_limit(found)?;
        }
        // Clear the deferred blobs' levels, word by word of their marks.
        for (word, &marks) in self.deferred_marks.iter().enumerate() {
            let mut marks = marks;
            while marks != 0 {
                self.levels[(word << 6) + marks.trailing_zeros() as usize] = 0;
                marks &= marks - 1;
            }
        }
        self.deferred = Vec::new();
        self.deferred_marks = Vec::new();
        self.stored = Vec::new();
        self.stored_keys = Vec::new();
        Ok(())
    }

    /// Floods deferred blob number `blob` from its seed, splits it and
    /// measures its particles (its levels stay).
    pub(super) fn measure_deferred<const PIXELS: bool>(&mut self, blob: usize, found: &mut Found) {
        if let Some(stored) = self.stored.get(blob) {
            // Its keys, already sorted, as its flood found them.
            let (start, len) = (stored.start as usize, stored.len as usize);
            self.blob.clear();
            self.blob
                .extend_from_slice(&self.stored_keys[start..start + len]);
            self.bounds = (
                (stored.corner.0 as usize, stored.corner.1 as usize),
                (stored.size.0 as usize, stored.size.1 as usize),
            );
            self.presorted = true;
        } else {
            self.flood(self.deferred[blob]);
        }
        let (corner, size) = self.blob_box();
        self.split_and_measure::<PIXELS>(corner, size, self.threshold_level(), found);
        self.presorted = false;
    }

    /// Keeps the keys of the blob just deferred (in `blob`), sorted, and its
    /// bounding box, so that [`Detector::measure_deferred`] need not flood
    /// and sort it again (up to twice): while the blobs deferred so far all
    /// fit in [`Detector::store_budget`] keys. Past that, this blob and
    /// every later one are flooded again from their seeds.
    pub(super) fn store_deferred(&mut self) {
        let budget = self.store_budget();
        if self.stored.len() + 1 != self.deferred.len()
            || self.stored_keys.len() + self.blob.len() > budget
        {
            return;
        }
        if self.stored_keys.capacity() == 0 {
            self.stored_keys.reserve_exact(budget);
        }
        self.sort_blob();
        let ((x, y), (w, h)) = self.bounds;
        self.stored.push(StoredBlob {
            start: self.stored_keys.len() as u32,
            len: self.blob.len() as u32,
            corner: (x as u32, y as u32),
            size: (w as u32, h as u32),
        });
        self.stored_keys.extend_from_slice(&self.blob);
    }

    /// The largest blob whose keys [`sort_keys`] sorts by radix: an eighth
    /// of the image's pixels, so that its scratch (8 bytes a key) is at
    /// most a byte a pixel of the image.
    pub(super) fn radix_most(&self) -> usize {
        self.width * self.height / 8
    }

    /// Sorts the keys in `blob` ([`sort_keys`]).
    pub(super) fn sort_blob(&mut self) {
        let most = self.radix_most();
        sort_keys(&mut self.blob, &mut self.sorted, most);
    }

    /// How many deferred blobs' keys [`Detector::store_deferred`] keeps: an
    /// eighth of the image's pixels, at most [`STORED_KEYS`]. A key costs 8
    /// bytes and its blob's [`StoredBlob`] (24 bytes, a blob of 3 pixels or
    /// more) at most 8 more: at most 2 bytes a pixel of the image, and
    /// 16 MiB.
    pub(super) fn store_budget(&self) -> usize {
        (self.width * self.height / 8).min(STORED_KEYS)
    }

    /// Whether the frame's particle images have structure of their own:
    /// its splits parted `parted` targets more than its blobs, of `targets`
    /// in all, and chance overlaps explain far fewer (see the module
    /// documentation, "Structured particle images").
    pub(super) fn structured(&mut self, targets: usize, parted: usize) -> bool {
        if self.target_sizes.is_empty() || parted == 0 {
            return false;
        }
        let middle = self.target_sizes.len() / 2;
        let area = f64::from(*self.target_sizes.select_nth_unstable(middle).1);
        // Two particle images touch when their centres are closer than one
        // image diameter and the pixel between.
        let reach = 2.0 * (area / std::f64::consts::PI).sqrt() + 1.0;
        let pixels = self
            .mask
            .map_or((self.width * self.height) as u64, Mask::used)
            .max(1) as f64;
        let density = targets as f64 / pixels;
        let overlaps =
            targets as f64 * (1.0 - (-density * std::f64::consts::PI * reach * reach).exp()) / 2.0;
        // Beyond the noise of a count: 3 sigma of a Poisson count of that
        // mean, and 3 for a mean near 0 (a lone pair is not a statistic).
        let bound = STRUCTURED_SPLITS * overlaps;
        parted as f64 > bound + 3.0 * bound.sqrt() + 3.0
    }

    /// Splits the blob in `blob` (of bounding box `corner`, `size`) and
    /// measures each particle.
    pub(super) fn split_and_measure<const PIXELS: bool>(
        &mut self,
        corner: (usize, usize),
        size: (usize, usize),
        threshold: u32,
        found: &mut Found,
    ) {
        // The reservations' count (see `split`): counted where the blob is
        // large enough for its scratch to matter; a small blob's (at most
        // one maximum per 2 pixels) is reserved without the pass.
        let maxima = if self.blob.len() <= COUNTED_BLOB {
            self.blob.len().div_ceil(2)
        } else {
            self.count_maxima(usize::MAX)
        };
        self.split(corner, size, maxima);
        // Number the particles in flooding order, and re-key each pixel by
        // its particle: sorted, each particle's pixels are contiguous and
        // particles are measured one at a time, in that order. Where the
        // targets need only their moments (no pixel lists, no Gaussian fit
        // around a peak) and the particles are few, their moments are
        // summed in this same pass instead, and the sort is not needed:
        // the moments are integer sums and extremes, so the targets are the
        // same whatever the order of the pixels.
        self.slot.clear();
        self.slot.resize(self.regions.len(), NONE);
        self.moments.clear();
        let mut summed = !PIXELS && self.parameters.centroid != Centroid::Gaussian;
        let mut particles = 0u32;
        for rank in 0..self.blob.len() {
            let k = self.blob[rank];
            let p = key_index(k);
            let (x, y) = self.position(p);
            let cell = self.cell((x, y), corner, size.0 + 2);
            let root = self.find(self.grid[cell]) as usize;
            // Left `NONE` for the next blob (see `split`).
            self.grid[cell] = NONE;
            if self.slot[root] == NONE {
                self.slot[root] = particles;
                particles += 1;
                if summed {
                    if self.moments.len() < MOMENTS_IN_PASS {
                        self.moments.push(Moments::new());
                    } else {
                        summed = false;
                    }
                }
            }
            let particle = self.slot[root];
            if summed {
                self.moments[particle as usize].add(
                    (x, y),
                    u32::from(key_level(k)),
                    corner,
                    threshold,
                );
            }
            self.blob[rank] = (u64::from(particle) << 32) | p as u64;
        }
        if summed {
            for m in &self.moments {
                if let Some(target) = self.target(m, corner) {
                    found.0.push(target);
                }
            }
            return;
        }
        self.sort_blob();
        let mut start = 0;
        while start < self.blob.len() {
            let particle = self.blob[start] >> 32;
            let end = start
                + self.blob[start..]
                    .iter()
                    .position(|&k| k >> 32 != particle)
                    .unwrap_or(self.blob.len() - start);
            self.measure_particle::<PIXELS>(start..end, corner, threshold, found);
            start = end;
        }
    }

    /// How many pixels of the blob would start a particle when it is
    /// flooded, counting up to `limit`: those with no neighbour that comes
    /// before them in flooding order (brighter, or as bright and earlier in
    /// raster order). Only the edge neighbours are compared (they are in
    /// the blob if above the threshold; a diagonal neighbour may be in
    /// another blob): left out, the count is at least the particles the
    /// split starts (which compares all 8 neighbours within the blob), so a
    /// count of 1 is still exact. Most blobs are single particles, and
    /// counting to 2 spares them the sort.
    pub(super) fn count_maxima(&self, limit: usize) -> usize {
        let (width, height) = (self.width, self.height);
        let mut maxima = 0;
        for &k in &self.blob {
            let p = key_index(k);
            let level = self.levels[p];
            let (x, y) = self.position(p);
            let first = if x > 0 && y > 0 && x + 1 < width && y + 1 < height {
                // Away from the border, by offset: the neighbours before
                // `p` in raster order must be darker, those after it no
                // brighter.
                let levels = &self.levels;
                let (w, before, after) = (
                    width,
                    |q: usize| levels[q] < level,
                    |q: usize| levels[q] <= level,
                );
                before(p - w) && before(p - 1) && after(p + 1) && after(p + w)
            } else {
                self.first_at_border(p, level, (x, y))
            };
            if first {
                maxima += 1;
                if maxima >= limit {
                    return maxima;
                }
            }
        }
        maxima
    }

    /// [`Detector::count_maxima`]'s test at the image's border: whether no
    /// neighbour of pixel `p` (at `level`, position `(x, y)`) comes before
    /// it in flooding order.
    pub(super) fn first_at_border(&self, p: usize, level: u16, (x, y): (usize, usize)) -> bool {
        let (width, height) = (self.width, self.height);
        for ny in y.saturating_sub(1)..=(y + 1).min(height - 1) {
            for nx in x.saturating_sub(1)..=(x + 1).min(width - 1) {
                if nx != x && ny != y {
                    continue; // see `count_maxima`
                }
                let q = ny * width + nx;
                let other = self.levels[q];
                // Raster order: rows above, or this row to the left.
                if other > level || (other == level && q < p) {
                    return false;
                }
            }
        }
        true
    }

    /// Step 3: floods the blob (`maxima` local maxima, bounding box of
    /// `size` at `corner`) from its brightest pixel down, leaving each
    /// pixel's region in `grid`.
    pub(super) fn split(&mut self, corner: (usize, usize), size: (usize, usize), maxima: usize) {
        self.kept_apart = false;
        let rule = match self.parameters.split_depth {
            Some(depth) => SplitRule::Absolute(
                (u64::from(depth) * G::LEVEL_SCALE).min(u64::from(u32::MAX)) as u32,
            ),
            None => SplitRule::Auto {
                noise: self.noise_depth(),
                threshold: self.threshold_level(),
                cap: (u64::from(self.noise) * AUTO_SPLIT_CAP / 10).min(u64::from(u32::MAX)) as u32,
            },
        };
        let auto = matches!(rule, SplitRule::Auto { .. });
        // Bright to dark; equal values in raster order, so that the result
        // does not depend on where the blob lies in the image.
        if !self.presorted {
            self.sort_blob();
        }
        let (box_width, box_height) = size;
        // The grid has a border of one unvisited cell on every side, so a
        // pixel's eight neighbours are at fixed offsets, none out of range.
        let stride = box_width + 2;
        let cells = stride * (box_height + 2);
        // Exact reservations: these grow to the largest blob's needs and no
        // further. The grid is all `NONE` between blobs (the measuring pass
        // of `split_and_measure`, the one reader of what this leaves, sets
        // each of the blob's cells back), so only its growth is filled, not
        // the whole box: a blob of a few pixels in a long diagonal box
        // costs its pixels, not its box.
        debug_assert!(self.grid[..cells.min(self.grid.len())]
            .iter()
            .all(|&r| r == NONE));
        if self.grid.len() < cells {
            self.grid.reserve_exact(cells - self.grid.len());
            self.grid.resize(cells, NONE);
        }
        self.regions.clear();
        self.regions.reserve_exact(maxima);
        self.caps.clear();
        if auto {
            self.caps.reserve_exact(maxima);
        }
        self.slot.clear();
        self.slot.reserve_exact(maxima);
        // The eight neighbours in raster order: offsets in the grid and in
        // the image.
        let (s, w) = (stride as isize, self.width as isize);
        let around: [(isize, isize); 8] = [
            (-s - 1, -w - 1),
            (-s, -w),
            (-s + 1, -w + 1),
            (-1, -1),
            (1, 1),
            (s - 1, w - 1),
            (s, w),
            (s + 1, w + 1),
        ];
        for rank in 0..self.blob.len() {
            let k = self.blob[rank];
            let level = u32::from(key_level(k));
            let p = key_index(k);
            let cell = self.cell(self.position(p), corner, stride);
            // Visited neighbours (all at least as bright) hold the region
            // their pixel joined, unvisited ones `NONE` (`u32::MAX`). Most
            // pixels see one region only: the smallest and largest of the
            // neighbours' regions tell, without a lookup each.
            let grid = |i: usize| self.grid[cell.wrapping_add_signed(around[i].0)];
            // (Written out: `around.map` was a call a pixel.)
            let regions = [
                grid(0),
                grid(1),
                grid(2),
                grid(3),
                grid(4),
                grid(5),
                grid(6),
                grid(7),
            ];
            let lowest = regions.iter().fold(NONE, |a, &r| a.min(r));
            let highest = regions.iter().fold(0, |a, &r| a.max(r.wrapping_add(1)));
            if lowest == NONE {
                // A local maximum: a new particle.
                self.grid[cell] = self.regions.len() as u32;
                self.regions.push(Region {
                    parent: self.regions.len() as u32,
                    peak: level,
                });
                if auto {
                    self.caps.push((1, level));
                }
                continue;
            }
            let other = highest.wrapping_sub(1);
            let root = if other == lowest {
                // One region (as recorded): it joins that region's root.
                self.find(lowest)
            } else if let Some(root) = self.one_root(&regions, lowest, other) {
                // Two regions recorded, merged since: in a noisy blob, where
                // many small maxima have been merged into their particles,
                // most pixels meet two such names of one particle.
                root
            } else {
                // Several regions recorded: their roots, in raster order,
                // and a saddle where those differ.
                let mut cells = [(0usize, NONE); 8];
                let mut count = 0;
                let mut several = false;
                for (&region, &(_, offset)) in regions.iter().zip(&around) {
                    if region != NONE {
                        let root = self.find(region);
                        several |= count > 0 && root != cells[0].1;
                        cells[count] = (p.wrapping_add_signed(offset), root);
                        count += 1;
                    }
                }
                let mut brightest = cells[0].1;
                if several {
                    let mut neighbours = [(u64::MAX, NONE); 8];
                    for (slot, &(q, root)) in neighbours.iter_mut().zip(&cells[..count]) {
                        *slot = (key(self.levels[q], q), root);
                    }
                    let neighbours = &neighbours[..count];
                    brightest = neighbours
                        .iter()
                        .min_by_key(|(q, _)| *q)
                        .map_or(brightest, |&(_, root)| root);
                    self.merge_insignificant(neighbours, level, rule);
                    let first = self.find(neighbours[0].1);
                    for &(_, root) in &neighbours[1..] {
                        if self.find(root) != first {
                            self.kept_apart = true;
                            break;
                        }
                    }
                }
                // A saddle pixel goes to the particle of its brightest
                // neighbour.
                self.find(brightest)
            };
            self.grid[cell] = root;
            if auto {
                let cap = &mut self.caps[root as usize];
                *cap = (cap.0 + 1, cap.1.saturating_add(level));
            }
        }
    }

    /// The root of the neighbours' regions `regions` (`NONE` where not
    /// visited) if they name only `lowest` and `other` and those two have
    /// been merged; `None` if they name more, or two particles.
    #[inline(always)]
    fn one_root(&mut self, regions: &[u32; 8], lowest: u32, other: u32) -> Option<u32> {
        if !regions
            .iter()
            .all(|&r| r == NONE || r == lowest || r == other)
        {
            return None;
        }
        let root = self.find(lowest);
        (self.find(other) == root).then_some(root)
    }

    /// The cell in `grid` of the pixel at `(x, y)`, for a blob's bounding
    /// box at `corner` whose grid rows are `stride` cells (the box's width
    /// and its border of one cell on each side).
    #[inline(always)]
    pub(super) fn cell(
        &self,
        (x, y): (usize, usize),
        corner: (usize, usize),
        stride: usize,
    ) -> usize {
        (y - corner.1 + 1) * stride + (x - corner.0 + 1)
    }

    /// The automatic rule's noise floor in levels: [`AUTO_SPLIT_NOISE`](super::AUTO_SPLIT_NOISE)
    /// (or [`AUTO_SPLIT_NOISE_STRUCTURED`] in a structured frame) times the
    /// image's noise level.
    pub(super) fn noise_depth(&self) -> u32 {
        (u64::from(self.noise) * self.split_noise / 10).min(u64::from(u32::MAX)) as u32
    }

    /// At a pixel of grey value `level` where several particles meet: a
    /// particle whose peak does not rise enough above it (`rule`) is noise
    /// on a neighbour, and is merged into the particle of the brightest
    /// neighbour that is significant (or, if none is, into the highest one).
    pub(super) fn merge_insignificant(
        &mut self,
        neighbours: &[(u64, u32)],
        level: u32,
        rule: SplitRule,
    ) {
        let significant = |regions: &[Region], caps: &[(u32, u32)], root: u32| {
            let peak = regions[root as usize].peak;
            let rise = peak.saturating_sub(level);
            match rule {
                SplitRule::Absolute(depth) => rise > depth,
                SplitRule::Auto {
                    noise,
                    threshold,
                    cap,
                } => {
                    let (num, den) = AUTO_SPLIT_FRACTION;
                    // The cap: the particle's pixels so far, all at least
                    // as bright as the saddle, and their volume above it.
                    let (n, sum) = caps[root as usize];
                    // (A sum that saturated, of more than 65,536 pixels
                    // at full scale, is a bump far above any noise.)
                    let volume = if sum == u32::MAX {
                        u64::MAX
                    } else {
                        u64::from(sum).saturating_sub(u64::from(n) * u64::from(level))
                    };
                    rise > noise
                        && u64::from(rise) * u64::from(den)
                            > u64::from(peak.saturating_sub(threshold)) * u64::from(num)
                        && u128::from(volume) * u128::from(volume)
                            > u128::from(cap) * u128::from(cap) * u128::from(n)
                }
            }
        };
        let anchor = neighbours
            .iter()
            .filter(|&&(_, root)| significant(&self.regions, &self.caps, root))
            .min_by_key(|&&(q, _)| q)
            .map(|&(_, root)| root)
            .or_else(|| {
                neighbours
                    .iter()
                    .map(|&(_, root)| root)
                    .max_by_key(|&root| (self.regions[root as usize].peak, std::cmp::Reverse(root)))
            });
        let Some(anchor) = anchor else { return };
        for &(_, root) in neighbours {
            let root = self.find(root);
            if root != anchor && !significant(&self.regions, &self.caps, root) {
                self.regions[root as usize].parent = anchor;
                let peak = self.regions[root as usize].peak;
                let anchor_region = &mut self.regions[anchor as usize];
                anchor_region.peak = anchor_region.peak.max(peak);
                if !self.caps.is_empty() {
                    let (n, sum) = self.caps[root as usize];
                    let cap = &mut self.caps[anchor as usize];
                    *cap = (cap.0 + n, cap.1.saturating_add(sum));
                }
            }
        }
    }
    /// The root of a region, halving paths on the way.
    pub(super) fn find(&mut self, mut region: u32) -> u32 {
        while self.regions[region as usize].parent != region {
            let grandparent = self.regions[self.regions[region as usize].parent as usize].parent;
            self.regions[region as usize].parent = grandparent;
            region = grandparent;
        }
        region
    }
}
