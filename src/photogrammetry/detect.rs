//! Particle detection: the targets of one camera frame (design paper,
//! section 6.1, "Image pre-processing").
//!
//! The paper's steps, one function each:
//!
//! 1. **High-pass filter** ([`DetectionParameters::highpass_radius`]): subtract
//!    from every pixel the mean of the `(2r+1)²` window around it (clipped at
//!    the image border), saturating at zero, to remove "non-uniformities of
//!    the background intensity level due to reflections and the nonuniform
//!    intensity profile of the light sheet". The mean comes from running
//!    column and row sums, so the cost is linear in the pixels and does not
//!    depend on `r`.
//! 2. **Threshold segmentation** ([`DetectionParameters::threshold`], one per
//!    camera): a pixel belongs to a particle image if its filtered grey value
//!    is larger than the threshold; blobs are 8-connected.
//! 3. **Splitting overlapping particles** ([`DetectionParameters::split`]):
//!    the paper's rules for a particle image are that "all pixels ... are
//!    larger than a preset threshold", "a particle image shows exactly one
//!    local maximum", "grey values drop continuously inside a particle
//!    image" and "a pixel representing a local grey value minimum belongs to
//!    the particle containing its neighbour pixel with the largest grey
//!    value". They are implemented by flooding each blob from the top: pixels
//!    are visited from bright to dark; a pixel with no brighter neighbour
//!    starts a particle at its local maximum, a pixel next to one particle
//!    joins it, and a pixel next to several (a saddle, i.e. a local minimum
//!    between maxima) joins the particle of its brightest neighbour. Noise
//!    makes small spurious maxima; the paper splits only where a
//!    discontinuity "exceeding a certain empirically determined limit" is
//!    found, so a maximum that rises no more than
//!    [`DetectionParameters::split_depth`] above the saddle where it meets a
//!    brighter particle is merged into that particle instead. The rules
//!    cannot part two particles whose sum has one maximum: with Gaussian
//!    images that happens below about one image diameter of separation
//!    (for 2.5 px particles, `tests/photogrammetry/detect_accuracy.rs` splits 98-100% of
//!    pairs 2.5 px or more apart, about 70% at 2..2.5 px, none below
//!    1.5 px).
//! 4. **Centroids**: the grey value weighted centre of gravity of each
//!    particle's pixels, with weights `g - threshold` as in OpenPTV's
//!    `targ_rec` (a pixel at the threshold weighs nothing, so a pixel that
//!    crosses it moves the centroid continuously). Filters on pixel count,
//!    extent and sum of grey values follow, and targets touching the image
//!    border are dropped (their centroid is cut off). `sumg` is the sum of
//!    the filtered grey values, in the image's grey levels.
//!
//! Coordinates follow the camera model ([`super::camera`]): pixel (column
//! `i`, row `j`) has its centre at (`i + 0.5`, `j + 0.5`). OpenPTV's
//! detectors have not agreed on this across versions (some put pixel centres
//! on integers); target files carry the convention of the tool that wrote
//! them and are never shifted on read or write, so compare across tools
//! knowing which convention each used.
//!
//! The image's own samples are read as they are (`u8` stays `u8`); the
//! filter makes one pass over them with running sums, and everything after
//! it costs in proportion to the pixels above the threshold, so a frame
//! takes time linear in its pixels (`benches/detect.rs`). Filtered values
//! are kept in 16-bit grey levels (8-bit values times 257), so the fraction
//! of the subtracted mean survives in the centroid weights, and an 8-bit
//! image and its 16-bit copy give the same targets. All of it is integer
//! arithmetic with ties broken in raster order, so results are exact and
//! repeatable: translating an image by whole pixels translates every
//! centroid by exactly that. [`detect_cameras`] detects the frames of
//! several cameras in parallel.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::image::{GreyImage, GreyPixels};
use super::target::Target;

/// The largest high-pass radius; larger ones are used as this. A window of
/// `2r+1 = 65535` rows keeps column sums of 16-bit data within 32 bits.
pub const MAX_HIGHPASS_RADIUS: u32 = 32767;

/// How to find the particles of one camera's frames.
///
/// Grey values (threshold, split depth, sum of grey) are in the image's own
/// units: 0..255 for 8-bit, 0..65535 for 16-bit images. Every field has a
/// default suited to 8-bit images of particles 1.5..4 px across, so a JSON
/// object gives only what it changes.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DetectionParameters {
    /// Grey threshold: a pixel is part of a particle image if its high-pass
    /// filtered value is larger than this.
    pub threshold: u16,
    /// Radius `r` (px) of the `(2r+1)²` window whose mean the high-pass
    /// filter subtracts; 0 turns the filter off. Make it several particle
    /// diameters, so that a particle hardly raises its own background.
    pub highpass_radius: u32,
    /// Fewest pixels of a target.
    pub min_pixels: u32,
    /// Most pixels of a target.
    pub max_pixels: u32,
    /// Smallest extent in x (columns spanned).
    pub min_nx: u32,
    /// Largest extent in x.
    pub max_nx: u32,
    /// Smallest extent in y (rows spanned).
    pub min_ny: u32,
    /// Largest extent in y.
    pub max_ny: u32,
    /// Smallest sum of (filtered) grey values of a target.
    pub min_sumg: u64,
    /// Whether to split blobs of overlapping particles at grey value minima;
    /// without it every connected blob is one target.
    pub split: bool,
    /// How far (grey levels) the fainter of two maxima must rise above the
    /// brightest path joining them for the blob to be split there; smaller
    /// rises are taken as noise on one particle.
    pub split_depth: u16,
}

impl Default for DetectionParameters {
    fn default() -> Self {
        DetectionParameters {
            threshold: 10,
            highpass_radius: 10,
            min_pixels: 2,
            max_pixels: 500,
            min_nx: 1,
            max_nx: 50,
            min_ny: 1,
            max_ny: 50,
            min_sumg: 0,
            split: true,
            split_depth: 4,
        }
    }
}

/// A parameter set that cannot find anything, or asks for the impossible.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct InvalidDetectionParameters {
    /// The field, named as in the JSON (the command line's flags mirror it).
    pub field: &'static str,
    /// What is wrong and what is expected.
    pub reason: String,
}

impl DetectionParameters {
    /// Checks that the minima do not exceed the maxima and that the radius
    /// is usable. [`detect`] accepts any parameters (impossible ones find
    /// nothing); this is for the edges that take parameters from people.
    pub fn validate(&self) -> Result<(), InvalidDetectionParameters> {
        for (field, min, max, max_name) in [
            ("min_pixels", self.min_pixels, self.max_pixels, "max_pixels"),
            ("min_nx", self.min_nx, self.max_nx, "max_nx"),
            ("min_ny", self.min_ny, self.max_ny, "max_ny"),
        ] {
            if min > max {
                return Err(InvalidDetectionParameters {
                    field,
                    reason: format!(
                        "{min} is larger than {max_name} ({max}); no target could pass both"
                    ),
                });
            }
        }
        if self.highpass_radius > MAX_HIGHPASS_RADIUS {
            return Err(InvalidDetectionParameters {
                field: "highpass_radius",
                reason: format!(
                    "{} is larger than the largest supported radius, {MAX_HIGHPASS_RADIUS}",
                    self.highpass_radius
                ),
            });
        }
        Ok(())
    }
}

/// The targets of one frame, sorted by y, then x (as OpenPTV sorts them
/// for the correspondence search).
pub fn detect(image: &GreyImage, parameters: &DetectionParameters) -> Vec<Target> {
    detect_with_pixels_if::<false>(image, parameters)
        .into_iter()
        .map(|(target, _)| target)
        .collect()
}

/// A target and the pixels (column, row) it was measured from.
#[derive(Clone, Debug, PartialEq)]
pub struct TargetPixels {
    /// The target.
    pub target: Target,
    /// Its pixels, (column, row), in no particular order.
    pub pixels: Vec<(u32, u32)>,
}

/// [`detect`], keeping each target's pixels: for overlays, and for
/// measuring how a segmentation divides the particles.
pub fn detect_with_pixels(
    image: &GreyImage,
    parameters: &DetectionParameters,
) -> Vec<TargetPixels> {
    detect_with_pixels_if::<true>(image, parameters)
        .into_iter()
        .map(|(target, pixels)| TargetPixels { target, pixels })
        .collect()
}

/// The targets of several cameras' frames, each with its own parameters
/// (its own threshold), detected in parallel; in camera order.
pub fn detect_cameras(frames: &[(&GreyImage, &DetectionParameters)]) -> Vec<Vec<Target>> {
    frames
        .par_iter()
        .map(|(image, parameters)| detect(image, parameters))
        .collect()
}

fn detect_with_pixels_if<const PIXELS: bool>(
    image: &GreyImage,
    parameters: &DetectionParameters,
) -> Vec<(Target, Vec<(u32, u32)>)> {
    // A GreyImage has at least one pixel and its samples fill its size.
    let (width, height) = (image.width() as usize, image.height() as usize);
    let mut found = match image.pixels() {
        GreyPixels::Eight(pixels) => {
            Detector::new(pixels, width, height, parameters).run::<PIXELS>()
        }
        GreyPixels::Sixteen(pixels) => {
            Detector::new(pixels, width, height, parameters).run::<PIXELS>()
        }
    };
    found.sort_by(|(a, _), (b, _)| a.y.total_cmp(&b.y).then(a.x.total_cmp(&b.x)));
    found
}

/// A sample type the detector works on directly.
trait Grey: Copy + Send + Sync {
    /// Levels (filtered grey values) are kept in 16-bit grey levels: 8-bit
    /// values times 257 (255 becomes 65535), 16-bit ones as they are. The
    /// mean subtracted is a fraction, so 8-bit levels keep 1/257 of a grey
    /// level and centroid weights are not rounded to whole grey levels; and
    /// an 8-bit image and its 16-bit copy (times 257) have the same levels,
    /// so they give the same targets.
    const LEVEL_SCALE: u64;
    /// The grey value.
    fn value(self) -> u32;
}

impl Grey for u8 {
    const LEVEL_SCALE: u64 = 257;
    #[inline(always)]
    fn value(self) -> u32 {
        u32::from(self)
    }
}

impl Grey for u16 {
    const LEVEL_SCALE: u64 = 1;
    #[inline(always)]
    fn value(self) -> u32 {
        u32::from(self)
    }
}

/// One row of [`Detector::highpass_threshold`]: the window sum of column
/// `x` is the sum of `column_sums` over columns `x-r ..= x+r` (clipped), of
/// `rows * columns` pixels. Writes the level of every pixel above the
/// threshold into `out` and its index (`first` + column) into `seeds`.
#[allow(clippy::too_many_arguments)]
fn filter_row<G: Grey>(
    row: &[G],
    column_sums: &[u32],
    r: usize,
    rows: u64,
    threshold: u64,
    out: &mut [u16],
    first: usize,
    seeds: &mut Vec<usize>,
) {
    let width = row.len();
    // round(k (g c - s) / c) with k = LEVEL_SCALE, above k t: only called
    // when g c > s + t c, i.e. when the filtered value exceeds the
    // threshold. It is at most k g, which fits in 16 bits.
    let scale = G::LEVEL_SCALE;
    let mut keep = |x: usize, d: u64, c: u64| {
        let level = (2 * d * scale + c) / (2 * c);
        out[x] = level.max(threshold * scale + 1).min(u64::from(u16::MAX)) as u16;
        seeds.push(first + x);
    };
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
        let entering = &column_sums[left_end + r..interior_end + r];
        let leaving = &column_sums[left_end - r - 1..interior_end - r - 1];
        let pixels = &row[left_end..interior_end];
        for (k, ((&enter, &leave), &g)) in entering.iter().zip(leaving).zip(pixels).enumerate() {
            // One add on the running sum's dependency chain, not two.
            s = s.wrapping_add_signed(i64::from(enter) - i64::from(leave));
            let gc = u64::from(g.value()) * c;
            if gc > s + tc {
                keep(left_end + k, gc - s, c);
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

/// "No region / not yet visited" in the splitting step.
const NONE: u32 = u32::MAX;

/// A pixel of a blob: position and level (filtered grey value in 16-bit
/// grey levels, see [`Grey::LEVEL_SCALE`]).
#[derive(Clone, Copy, Debug)]
struct BlobPixel {
    x: usize,
    y: usize,
    level: u32,
}

/// One maximum's particle while a blob is flooded (a union-find node).
#[derive(Clone, Copy, Debug)]
struct Region {
    parent: u32,
    /// The grey value of its maximum.
    peak: u32,
}

/// The sums a target's centroid and filters need.
#[derive(Clone, Copy, Debug)]
struct Moments {
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
    fn new() -> Moments {
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
    fn add(&mut self, p: &BlobPixel, corner: (usize, usize), threshold: u32) {
        // Every blob pixel is above the threshold, so its weight is >= 1.
        let w = u64::from(p.level.saturating_sub(threshold));
        self.n += 1;
        self.sumg += u64::from(p.level);
        self.weight += w;
        self.weight_x += u128::from(w) * (p.x - corner.0) as u128;
        self.weight_y += u128::from(w) * (p.y - corner.1) as u128;
        self.xmin = self.xmin.min(p.x);
        self.xmax = self.xmax.max(p.x);
        self.ymin = self.ymin.min(p.y);
        self.ymax = self.ymax.max(p.y);
    }
}

/// One frame's detection, with the scratch space it reuses from blob to blob.
struct Detector<'a, G: Grey> {
    pixels: &'a [G],
    width: usize,
    height: usize,
    parameters: &'a DetectionParameters,
    /// Levels (high-pass filtered grey values in 16-bit grey levels) of the
    /// pixels above the threshold; 0 elsewhere and once a pixel has been
    /// taken into a blob.
    levels: Vec<u16>,
    /// The pixels above the threshold, in raster order.
    seeds: Vec<usize>,
    /// The blob being measured.
    blob: Vec<BlobPixel>,
    /// The flood fill's pixels still to visit.
    stack: Vec<(usize, usize)>,
    /// Splitting: per cell of the blob's bounding box, the rank (in bright to
    /// dark order) of its pixel once visited, else `NONE`.
    grid: Vec<u32>,
    /// Splitting: per blob pixel (by rank), its region.
    region_of: Vec<u32>,
    regions: Vec<Region>,
    /// Splitting: per region root, its target's index in `moments`.
    slot: Vec<u32>,
    moments: Vec<Moments>,
}

impl<'a, G: Grey> Detector<'a, G> {
    fn new(
        pixels: &'a [G],
        width: usize,
        height: usize,
        parameters: &'a DetectionParameters,
    ) -> Self {
        Detector {
            pixels,
            width,
            height,
            parameters,
            levels: Vec::new(),
            seeds: Vec::new(),
            blob: Vec::new(),
            stack: Vec::new(),
            grid: Vec::new(),
            region_of: Vec::new(),
            regions: Vec::new(),
            slot: Vec::new(),
            moments: Vec::new(),
        }
    }

    fn run<const PIXELS: bool>(mut self) -> Vec<(Target, Vec<(u32, u32)>)> {
        self.highpass_threshold();
        let mut found = Vec::new();
        let seeds = std::mem::take(&mut self.seeds);
        for &seed in &seeds {
            if self.levels[seed] == 0 {
                continue; // already part of an earlier blob
            }
            self.flood(seed);
            self.measure_blob::<PIXELS>(&mut found);
        }
        found
    }

    /// Steps 1 and 2: fills `levels` with the high-pass filtered value of
    /// every pixel above the threshold and lists them in `seeds`.
    ///
    /// For pixel value `g`, window sum `s` and window size `c` the filtered
    /// value is `g - s / c`; the test `g - s/c > t` is done exactly as
    /// `g c > s + t c` in integers, and only pixels that pass are divided.
    /// The level is the filtered value in 16-bit grey levels, rounded and
    /// kept above the threshold, so every blob pixel has a weight of at
    /// least 1.
    fn highpass_threshold(&mut self) {
        let (width, height) = (self.width, self.height);
        let threshold = u64::from(self.parameters.threshold);
        self.levels = vec![0; width * height];
        let levels = &mut self.levels;
        let seeds = &mut self.seeds;
        let pixels = self.pixels;
        let r = self.parameters.highpass_radius.min(MAX_HIGHPASS_RADIUS) as usize;
        if r == 0 {
            for (i, &g) in pixels.iter().enumerate() {
                if u64::from(g.value()) > threshold {
                    levels[i] = (u64::from(g.value()) * G::LEVEL_SCALE) as u16;
                    seeds.push(i);
                }
            }
            return;
        }
        // Window sums of each column over the rows of the current window.
        let mut column_sums = vec![0u32; width];
        let add_row = |sums: &mut [u32], row: usize| {
            for (sum, &g) in sums.iter_mut().zip(&pixels[row * width..(row + 1) * width]) {
                *sum += g.value();
            }
        };
        for row in 0..r.min(height) {
            add_row(&mut column_sums, row);
        }
        for y in 0..height {
            if y + r < height {
                add_row(&mut column_sums, y + r);
            }
            if y > r {
                let row = y - r - 1;
                for (sum, &g) in column_sums
                    .iter_mut()
                    .zip(&pixels[row * width..(row + 1) * width])
                {
                    *sum -= g.value();
                }
            }
            let rows = ((y + r).min(height - 1) - y.saturating_sub(r) + 1) as u64;
            let row = &pixels[y * width..(y + 1) * width];
            let out = &mut levels[y * width..(y + 1) * width];
            filter_row(row, &column_sums, r, rows, threshold, out, y * width, seeds);
        }
    }

    /// Collects the 8-connected blob of `seed` into `blob`, taking its
    /// pixels out of `levels`.
    fn flood(&mut self, seed: usize) {
        let (width, height) = (self.width, self.height);
        self.blob.clear();
        self.stack.clear();
        let (x, y) = (seed % width, seed / width);
        self.blob.push(BlobPixel {
            x,
            y,
            level: u32::from(self.levels[seed]),
        });
        self.levels[seed] = 0;
        self.stack.push((x, y));
        while let Some((x, y)) = self.stack.pop() {
            if x > 0 && y > 0 && x + 1 < width && y + 1 < height {
                // Away from the border: the eight neighbours by offset.
                let p = y * width + x;
                for q in [
                    p - width - 1,
                    p - width,
                    p - width + 1,
                    p - 1,
                    p + 1,
                    p + width - 1,
                    p + width,
                    p + width + 1,
                ] {
                    self.take(q, q % width, q / width);
                }
                continue;
            }
            for ny in y.saturating_sub(1)..=(y + 1).min(height - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(width - 1) {
                    self.take(ny * width + nx, nx, ny);
                }
            }
        }
    }

    /// Moves pixel `q` = (`x`, `y`) into the blob if it is above the
    /// threshold and not taken yet.
    #[inline(always)]
    fn take(&mut self, q: usize, x: usize, y: usize) {
        let level = self.levels[q];
        if level != 0 {
            self.levels[q] = 0;
            self.blob.push(BlobPixel {
                x,
                y,
                level: u32::from(level),
            });
            self.stack.push((x, y));
        }
    }

    /// Steps 3 and 4 for the blob in `blob`: splits it, measures each
    /// particle and keeps those that pass the filters.
    fn measure_blob<const PIXELS: bool>(&mut self, found: &mut Vec<(Target, Vec<(u32, u32)>)>) {
        let threshold =
            (u64::from(self.parameters.threshold) * G::LEVEL_SCALE).min(u64::from(u32::MAX)) as u32;
        let mut xmin = usize::MAX;
        let mut ymin = usize::MAX;
        for p in &self.blob {
            xmin = xmin.min(p.x);
            ymin = ymin.min(p.y);
        }
        let corner = (xmin, ymin);
        self.moments.clear();
        if !self.parameters.split || self.blob.len() < 3 || self.one_maximum(corner) {
            let mut m = Moments::new();
            for p in &self.blob {
                m.add(p, corner, threshold);
            }
            if let Some(target) = self.target(&m, corner) {
                let pixels = if PIXELS {
                    self.blob.iter().map(|p| (p.x as u32, p.y as u32)).collect()
                } else {
                    Vec::new()
                };
                found.push((target, pixels));
            }
            return;
        }
        self.split(corner);
        // Accumulate each pixel into its particle.
        self.slot.clear();
        self.slot.resize(self.regions.len(), NONE);
        for rank in 0..self.blob.len() {
            let root = self.find(self.region_of[rank]) as usize;
            if self.slot[root] == NONE {
                self.slot[root] = self.moments.len() as u32;
                self.moments.push(Moments::new());
            }
            let p = self.blob[rank];
            self.moments[self.slot[root] as usize].add(&p, corner, threshold);
        }
        // Each particle's pixels, when asked for; else empty vectors, which
        // do not allocate.
        let mut pixels: Vec<Vec<(u32, u32)>> = vec![Vec::new(); self.moments.len()];
        if PIXELS {
            for rank in 0..self.blob.len() {
                let root = self.find(self.region_of[rank]) as usize;
                let p = self.blob[rank];
                pixels[self.slot[root] as usize].push((p.x as u32, p.y as u32));
            }
        }
        for (m, own) in self.moments.iter().zip(pixels) {
            if let Some(target) = self.target(m, corner) {
                found.push((target, own));
            }
        }
    }

    /// Whether flooding the blob would start only one particle: whether
    /// exactly one pixel has no neighbour that comes before it in flooding
    /// order (brighter, or as bright and earlier in raster order). Most
    /// blobs are single particles, and this spares them the sort.
    fn one_maximum(&mut self, corner: (usize, usize)) -> bool {
        let (box_width, box_height) = self.bounding_box(corner);
        self.grid.clear();
        self.grid.resize(box_width * box_height, 0);
        for p in &self.blob {
            self.grid[(p.y - corner.1) * box_width + (p.x - corner.0)] = p.level;
        }
        let mut maxima = 0;
        for p in &self.blob {
            let (bx, by) = (p.x - corner.0, p.y - corner.1);
            let mut first = true;
            'neighbours: for ny in by.saturating_sub(1)..=(by + 1).min(box_height - 1) {
                for nx in bx.saturating_sub(1)..=(bx + 1).min(box_width - 1) {
                    let level = self.grid[ny * box_width + nx];
                    // Raster order: rows above, or this row to the left.
                    let earlier = (ny, nx) < (by, bx);
                    if level > p.level || (level == p.level && earlier) {
                        first = false;
                        break 'neighbours;
                    }
                }
            }
            if first {
                maxima += 1;
                if maxima > 1 {
                    return false;
                }
            }
        }
        true
    }

    /// Width and height of the blob's bounding box, whose top-left corner is
    /// `corner`.
    fn bounding_box(&self, corner: (usize, usize)) -> (usize, usize) {
        let (mut xmax, mut ymax) = (0, 0);
        for p in &self.blob {
            xmax = xmax.max(p.x);
            ymax = ymax.max(p.y);
        }
        (xmax - corner.0 + 1, ymax - corner.1 + 1)
    }

    /// Step 3: floods the blob from its brightest pixel down, leaving each
    /// pixel's region in `region_of` (indexed by rank in `blob`, which is
    /// sorted bright to dark).
    fn split(&mut self, corner: (usize, usize)) {
        let depth = (u64::from(self.parameters.split_depth) * G::LEVEL_SCALE)
            .min(u64::from(u32::MAX)) as u32;
        // Bright to dark; equal values in raster order, so that the result
        // does not depend on where the blob lies in the image.
        self.blob.sort_unstable_by(|a, b| {
            b.level
                .cmp(&a.level)
                .then(a.y.cmp(&b.y))
                .then(a.x.cmp(&b.x))
        });
        let (box_width, box_height) = self.bounding_box(corner);
        self.grid.clear();
        self.grid.resize(box_width * box_height, NONE);
        self.region_of.clear();
        self.region_of.resize(self.blob.len(), NONE);
        self.regions.clear();
        for rank in 0..self.blob.len() {
            let p = self.blob[rank];
            let (bx, by) = (p.x - corner.0, p.y - corner.1);
            // Visited neighbours (all at least as bright): rank and region root.
            let mut neighbours = [(NONE, NONE); 8];
            let mut count = 0;
            for ny in by.saturating_sub(1)..=(by + 1).min(box_height - 1) {
                for nx in bx.saturating_sub(1)..=(bx + 1).min(box_width - 1) {
                    let q = self.grid[ny * box_width + nx];
                    if q != NONE {
                        neighbours[count] = (q, self.find(self.region_of[q as usize]));
                        count += 1;
                    }
                }
            }
            let neighbours = &neighbours[..count];
            let Some(&(brightest, _)) = neighbours.iter().min_by_key(|(q, _)| *q) else {
                // A local maximum: a new particle.
                self.region_of[rank] = self.regions.len() as u32;
                self.regions.push(Region {
                    parent: self.regions.len() as u32,
                    peak: p.level,
                });
                self.grid[by * box_width + bx] = rank as u32;
                continue;
            };
            if neighbours.iter().any(|&(_, root)| root != neighbours[0].1) {
                self.merge_insignificant(neighbours, p.level, depth);
            }
            // A saddle pixel goes to the particle of its brightest neighbour.
            self.region_of[rank] = self.find(self.region_of[brightest as usize]);
            self.grid[by * box_width + bx] = rank as u32;
        }
    }

    /// At a pixel of grey value `level` where several particles meet: a
    /// particle whose peak rises no more than `depth` above it is noise on a
    /// neighbour, and is merged into the particle of the brightest neighbour
    /// that is significant (or, if none is, into the highest one).
    fn merge_insignificant(&mut self, neighbours: &[(u32, u32)], level: u32, depth: u32) {
        let significant = |regions: &[Region], root: u32| {
            regions[root as usize].peak.saturating_sub(level) > depth
        };
        let anchor = neighbours
            .iter()
            .filter(|&&(_, root)| significant(&self.regions, root))
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
            if root != anchor && !significant(&self.regions, root) {
                self.regions[root as usize].parent = anchor;
                let peak = self.regions[root as usize].peak;
                let anchor_region = &mut self.regions[anchor as usize];
                anchor_region.peak = anchor_region.peak.max(peak);
            }
        }
    }

    /// The root of a region, halving paths on the way.
    fn find(&mut self, mut region: u32) -> u32 {
        while self.regions[region as usize].parent != region {
            let grandparent = self.regions[self.regions[region as usize].parent as usize].parent;
            self.regions[region as usize].parent = grandparent;
            region = grandparent;
        }
        region
    }

    /// Step 4: the target of a particle's moments, if it passes the filters
    /// and does not touch the image border.
    fn target(&self, m: &Moments, corner: (usize, usize)) -> Option<Target> {
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
            && sumg >= p.min_sumg;
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::rng;
    use rand::Rng;

    /// The filtered, thresholded levels by the definition: every window
    /// summed pixel by pixel.
    fn reference_levels(
        pixels: &[u16],
        width: usize,
        height: usize,
        r: usize,
        t: u64,
        scale: u64,
    ) -> Vec<u16> {
        let mut out = vec![0; width * height];
        for y in 0..height {
            for x in 0..width {
                let g = u64::from(pixels[y * width + x]);
                // Radius 0: no filter, a background of 0.
                let (s, c) = if r == 0 {
                    (0, 1)
                } else {
                    let mut s = 0;
                    let mut c = 0;
                    for wy in y.saturating_sub(r)..=(y + r).min(height - 1) {
                        for wx in x.saturating_sub(r)..=(x + r).min(width - 1) {
                            s += u64::from(pixels[wy * width + wx]);
                            c += 1;
                        }
                    }
                    (s, c)
                };
                // filtered = g - s/c > t, times scale, rounded, above t.
                if g * c > s + t * c {
                    let d = (g * c - s) * scale;
                    out[y * width + x] = ((2 * d + c) / (2 * c)).max(t * scale + 1) as u16;
                }
            }
        }
        out
    }

    #[test]
    fn highpass_matches_its_definition() {
        let mut rng = rng(11);
        for (width, height, r) in [
            (17, 13, 0),
            (17, 13, 1),
            (17, 13, 3),
            (5, 9, 4),
            (9, 5, 7),
            (3, 3, 40),
            (1, 7, 2),
            (8, 1, 2),
            (1, 1, 1),
        ] {
            for max in [255u16, 65535] {
                let pixels: Vec<u16> = (0..width * height)
                    .map(|_| rng.random_range(0..=max))
                    .collect();
                let t = u64::from(max / 20);
                let parameters = DetectionParameters {
                    threshold: t as u16,
                    highpass_radius: r as u32,
                    ..DetectionParameters::default()
                };
                let scale = if max == 255 { 257 } else { 1 };
                let expected = reference_levels(&pixels, width, height, r, t, scale);
                let got: Vec<u16> = if max == 255 {
                    let eight: Vec<u8> = pixels.iter().map(|&v| v as u8).collect();
                    let mut d = Detector::new(&eight, width, height, &parameters);
                    d.highpass_threshold();
                    d.levels
                } else {
                    let mut d = Detector::new(&pixels, width, height, &parameters);
                    d.highpass_threshold();
                    d.levels
                };
                assert_eq!(got, expected, "{width}x{height}, r {r}, max {max}");
            }
        }
    }

    fn image(width: u32, rows: &[&[u8]]) -> GreyImage {
        let pixels: Vec<u8> = rows.iter().flat_map(|r| r.iter().copied()).collect();
        GreyImage::from_u8(width, rows.len() as u32, pixels).unwrap()
    }

    fn unfiltered() -> DetectionParameters {
        DetectionParameters {
            threshold: 10,
            highpass_radius: 0,
            min_pixels: 1,
            split_depth: 5,
            ..DetectionParameters::default()
        }
    }

    #[test]
    fn centroid_weights_grey_values_above_the_threshold() {
        // Weights 30 - 10 and 50 - 10: x = 1.5 + 40 / 60 = 2.1667 (pixel
        // centres at i + 0.5).
        let targets = detect(
            &image(5, &[&[0, 0, 0, 0, 0], &[0, 30, 50, 0, 0], &[0, 0, 0, 0, 0]]),
            &unfiltered(),
        );
        assert_eq!(targets.len(), 1);
        let t = targets[0];
        assert!((t.x - (1.5 + 40.0 / 60.0)).abs() < 1e-12, "{t:?}");
        assert!((t.y - 1.5).abs() < 1e-12);
        assert_eq!((t.n, t.nx, t.ny, t.sumg), (2, 2, 1, 80));
    }

    #[test]
    fn overlapping_particles_split_at_the_grey_value_minimum() {
        let rows: &[&[u8]] = &[
            &[0, 0, 0, 0, 0, 0, 0, 0, 0],
            &[0, 20, 40, 20, 15, 30, 60, 30, 0],
            &[0, 40, 90, 40, 25, 50, 120, 50, 0],
            &[0, 20, 40, 20, 15, 30, 60, 30, 0],
            &[0, 0, 0, 0, 0, 0, 0, 0, 0],
        ];
        let split = detect(&image(9, rows), &unfiltered());
        assert_eq!(split.len(), 2, "{split:?}");
        // Column 4 is the valley; its pixels join the brighter neighbour on
        // the right (30/50/30 beats 20/40/20).
        assert_eq!((split[0].n, split[1].n), (9, 12));
        let plain = detect(
            &image(9, rows),
            &DetectionParameters {
                split: false,
                ..unfiltered()
            },
        );
        assert_eq!(plain.len(), 1);
        assert_eq!(plain[0].n, 21);
    }

    #[test]
    fn shallow_dips_are_noise_not_a_second_particle() {
        // The right maximum rises 4 above the saddle (36 at column 3): at
        // depth 5 it is noise on one particle, at depth 3 a second one.
        let rows: &[&[u8]] = &[
            &[0, 0, 0, 0, 0, 0, 0],
            &[0, 20, 30, 20, 25, 20, 0],
            &[0, 30, 90, 36, 40, 30, 0],
            &[0, 20, 30, 20, 25, 20, 0],
            &[0, 0, 0, 0, 0, 0, 0],
        ];
        assert_eq!(detect(&image(7, rows), &unfiltered()).len(), 1);
        let deep = DetectionParameters {
            split_depth: 3,
            ..unfiltered()
        };
        assert_eq!(detect(&image(7, rows), &deep).len(), 2);
    }

    #[test]
    fn targets_touching_the_border_and_filtered_ones_are_dropped() {
        let rows: &[&[u8]] = &[
            &[0, 0, 0, 0, 0, 0, 0],
            &[50, 0, 0, 0, 0, 0, 0],
            &[0, 0, 0, 60, 0, 0, 0],
            &[0, 0, 0, 60, 0, 0, 0],
            &[0, 0, 0, 0, 0, 0, 0],
        ];
        assert_eq!(detect(&image(7, rows), &unfiltered()).len(), 1);
        for filter in [
            DetectionParameters {
                min_pixels: 3,
                ..unfiltered()
            },
            DetectionParameters {
                max_ny: 1,
                ..unfiltered()
            },
            DetectionParameters {
                min_nx: 2,
                ..unfiltered()
            },
            DetectionParameters {
                min_sumg: 121,
                ..unfiltered()
            },
        ] {
            assert!(detect(&image(7, rows), &filter).is_empty(), "{filter:?}");
        }
    }

    #[test]
    fn any_parameters_on_any_image_are_safe() {
        let tiny = GreyImage::from_u8(1, 1, vec![255]).unwrap();
        let flat = GreyImage::from_u16(4, 3, vec![65535; 12]).unwrap();
        for parameters in [
            DetectionParameters::default(),
            DetectionParameters {
                threshold: 0,
                highpass_radius: u32::MAX,
                min_pixels: 0,
                ..DetectionParameters::default()
            },
            DetectionParameters {
                threshold: u16::MAX,
                min_pixels: 9,
                max_pixels: 1,
                ..DetectionParameters::default()
            },
        ] {
            assert!(detect(&tiny, &parameters).is_empty());
            assert!(detect(&flat, &parameters).is_empty());
        }
    }

    #[test]
    fn parameters_read_partial_json_and_reject_unknown_fields() {
        let p: DetectionParameters =
            serde_json::from_str(r#"{"threshold": 30, "min_pixels": 4}"#).unwrap();
        assert_eq!(p.threshold, 30);
        assert_eq!(p.min_pixels, 4);
        assert_eq!(p.max_pixels, DetectionParameters::default().max_pixels);
        assert!(serde_json::from_str::<DetectionParameters>(r#"{"treshold": 30}"#).is_err());
        let bad = DetectionParameters {
            min_pixels: 9,
            max_pixels: 4,
            ..p
        };
        let message = bad.validate().unwrap_err().to_string();
        assert!(
            message.starts_with("min_pixels: 9 is larger than max_pixels (4)"),
            "{message}"
        );
        assert!(DetectionParameters::default().validate().is_ok());
    }

    #[test]
    fn cameras_are_detected_with_their_own_parameters() {
        let rows: &[&[u8]] = &[&[0, 0, 0], &[0, 40, 0], &[0, 0, 0]];
        let frame = image(3, rows);
        let low = unfiltered();
        let high = DetectionParameters {
            threshold: 50,
            ..unfiltered()
        };
        let found = detect_cameras(&[(&frame, &low), (&frame, &high)]);
        assert_eq!(found.iter().map(Vec::len).collect::<Vec<_>>(), vec![1, 0]);
    }
}
