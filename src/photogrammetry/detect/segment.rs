//! Blobs: the 4-connected sets of pixels above the threshold, found a few
//! rows behind the filter in the blocks it marked, flooded into one
//! buffer, and handed to splitting and measuring (see the parent
//! module, step 2).

use super::{key, key_index, key_level, Detector, Found, Grey};
/// Rows between the last row [`HighPass`](super::highpass::HighPass) has filtered and the last row in
/// which [`Detector::run`] looks for blobs' first pixels: room for a
/// particle image to end before the filter's frontier.
pub(super) const TRAIL: usize = 8;

impl<G: Grey> Detector<'_, G> {
    /// Finds the blobs whose first pixel (in raster order) is at `*scan`
    /// or after and before `end`, and measures each; `*scan` follows. With
    /// `frontier`, the last row filtered so far, a blob that reaches it is
    /// left for later: the search stops at its first pixel and returns its
    /// row.
    pub(super) fn find_blobs<const PIXELS: bool>(
        &mut self,
        scan: &mut usize,
        end: usize,
        frontier: Option<usize>,
        found: &mut Found,
    ) -> Option<usize> {
        // Most of the image is below the threshold: only the blocks the
        // filter marked are searched (see `RowOut`), a word of marks (4,096
        // pixels) at a time; a marked block whose levels are all 0 (its
        // blobs were measured from an earlier block) is passed by one OR,
        // which the compiler vectorises.
        while *scan < end {
            let block = *scan >> 6;
            let later = self.marks[block >> 6] >> (block & 63);
            if later == 0 {
                *scan = (((block >> 6) + 1) << 12).min(end);
                continue;
            }
            let block = block + later.trailing_zeros() as usize;
            let (start, stop) = ((block << 6).max(*scan), ((block + 1) << 6).min(end));
            if start >= stop {
                *scan = end;
                break;
            }
            if self.levels[start..stop].iter().fold(0, |any, &l| any | l) != 0 {
                for seed in start..stop {
                    if self.levels[seed] == 0 || self.is_deferred(seed) {
                        continue; // below the threshold, or part of an earlier blob
                    }
                    self.reserve_blob(frontier);
                    let last = self.flood(seed);
                    if let Some(frontier) = frontier {
                        if last >= frontier * self.width {
                            *scan = seed;
                            return Some(self.position(seed).1);
                        }
                    }
                    if self.measure_blob::<PIXELS>(found) {
                        for &k in &self.blob {
                            self.levels[key_index(k)] = 0;
                        }
                    }
                    if found.0.len() > self.limit {
                        // Past the limit: the caller stops.
                        *scan = end;
                        return None;
                    }
                }
            }
            *scan = stop;
        }
        None
    }

    /// Makes room in `blob` for every pixel above the threshold so far (a
    /// blob never holds more), so that the flood never reallocates. While
    /// rows are still being filtered (`frontier`, the last one) the room
    /// doubles, but never beyond the pixels filtered; then it is exact. The
    /// old room is freed before the new is taken: the blob is at most 8
    /// bytes a pixel of the image, never twice that.
    pub(super) fn reserve_blob(&mut self, frontier: Option<usize>) {
        if self.blob.capacity() >= self.above {
            return;
        }
        let room = match frontier {
            Some(row) => (2 * self.blob.capacity())
                .max(self.above)
                .min((row + 1) * self.width),
            None => self.above,
        };
        self.blob = Vec::new();
        self.blob.reserve_exact(room);
    }

    /// Collects the blob of `seed` (4-connected: pixels join by an edge)
    /// into `blob` and its bounding box into `bounds`, breadth first with `blob` itself as
    /// the queue, and returns its last pixel (the largest index). Pixels are
    /// taken out of `levels` while it runs (so none is taken twice) and put
    /// back at the end, for the measuring step to read.
    pub(super) fn flood(&mut self, seed: usize) -> usize {
        let (width, height) = (self.width, self.height);
        self.blob.clear();
        self.take(seed);
        let mut head = 0;
        let mut last = seed;
        // The bounding box, as the pixels are expanded.
        let (mut xmin, mut ymin, mut xmax, mut ymax) = (usize::MAX, usize::MAX, 0, 0);
        while head < self.blob.len() {
            let p = key_index(self.blob[head]);
            head += 1;
            last = last.max(p);
            let (x, y) = self.position(p);
            xmin = xmin.min(x);
            ymin = ymin.min(y);
            xmax = xmax.max(x);
            ymax = ymax.max(y);
            // Only the four edge neighbours join a blob.
            if y > 0 {
                self.take(p - width);
            }
            if x > 0 {
                self.take(p - 1);
            }
            if x + 1 < width {
                self.take(p + 1);
            }
            if y + 1 < height {
                self.take(p + width);
            }
        }
        for &k in &self.blob {
            self.levels[key_index(k)] = key_level(k);
        }
        self.bounds = ((xmin, ymin), (xmax - xmin + 1, ymax - ymin + 1));
        last
    }

    /// Moves pixel `q` into the blob if it is above the threshold and not
    /// taken yet.
    #[inline(always)]
    pub(super) fn take(&mut self, q: usize) {
        let level = self.levels[q];
        if level != 0 {
            self.levels[q] = 0;
            // Within the capacity reserved in `run`: no reallocation.
            self.blob.push(key(level, q));
        }
    }

    /// Column and row of pixel index `p` (see [`Rows`](super::Rows)).
    #[inline(always)]
    pub(super) fn position(&self, p: usize) -> (usize, usize) {
        self.rows.position(p)
    }

    /// Steps 3 and 4 for the blob in `blob`: splits it, measures each
    /// particle and keeps those that pass the filters. Returns false for a
    /// blob deferred to the end of the frame (its levels must stay).
    pub(super) fn measure_blob<const PIXELS: bool>(&mut self, found: &mut Found) -> bool {
        let threshold = self.threshold_level();
        let (corner, size) = self.blob_box();
        let maxima = if !self.parameters.split || self.blob.len() < 3 {
            1
        } else {
            self.count_maxima(2)
        };
        if maxima == 1 {
            let before = found.0.len();
            self.measure_particle::<PIXELS>(0..self.blob.len(), corner, threshold, found);
            if self.defers() && found.0.len() > before {
                self.target_sizes.push(found.0[before].n);
            }
            return true;
        }
        if self.defers() {
            // The automatic rule: split when the frame is known.
            if self.deferred_marks.is_empty() {
                self.deferred_marks = vec![0; (self.width * self.height).div_ceil(64)];
            }
            for &k in &self.blob {
                let p = key_index(k);
                self.deferred_marks[p >> 6] |= 1 << (p & 63);
            }
            // The flood's first pixel is its seed.
            self.deferred.push(key_index(self.blob[0]));
            self.store_deferred();
            return false;
        }
        self.split_and_measure::<PIXELS>(corner, size, threshold, found);
        true
    }

    /// Whether pixel `p` belongs to a deferred blob.
    #[inline(always)]
    pub(super) fn is_deferred(&self, p: usize) -> bool {
        !self.deferred_marks.is_empty() && (self.deferred_marks[p >> 6] >> (p & 63)) & 1 == 1
    }

    /// Whether blobs with several maxima wait for the whole frame: with the
    /// automatic split rule.
    pub(super) fn defers(&self) -> bool {
        self.parameters.split && self.parameters.split_depth.is_none()
    }

    /// The threshold in levels (16-bit grey levels).
    pub(super) fn threshold_level(&self) -> u32 {
        (u64::from(self.parameters.threshold) * G::LEVEL_SCALE).min(u64::from(u32::MAX)) as u32
    }

    /// The bounding box of the blob in `blob`: its corner (column, row) and
    /// size (found by [`Detector::flood`] as it expands the pixels).
    pub(super) fn blob_box(&self) -> ((usize, usize), (usize, usize)) {
        self.bounds
    }
}
