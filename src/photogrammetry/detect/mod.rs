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
//!    depend on `r`. The default radius is 25, OpenPTV's and pyptv's (see
//!    "Defaults on a real recording" below).
//! 2. **Threshold segmentation** ([`DetectionParameters::threshold`], one per
//!    camera): a pixel belongs to a particle image if its filtered grey value
//!    is larger than the threshold; blobs are 4-connected (pixels join by an
//!    edge only), as OpenPTV's, see "OpenPTV's segmentation" below.
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
//!    found, so a maximum that does not rise far enough above the saddle
//!    where it meets a brighter particle is merged into that particle
//!    instead. How far is [`DetectionParameters::split_depth`]: `Some(d)`
//!    is an absolute depth of `d` grey levels (OpenPTV's `discont`, which
//!    the paper's "empirically determined limit" is, set per experiment);
//!    `None`, the default, is an automatic rule for when no experiment has
//!    determined it: the rise must exceed both a fifth
//!    ([`AUTO_SPLIT_FRACTION`]) of the maximum's own height above the
//!    threshold, and 3 times ([`AUTO_SPLIT_NOISE`]) the image's noise
//!    level; and the maximum's cap, the `n` pixels of its particle that
//!    are brighter than the saddle, must hold a volume above the saddle
//!    (the sum of their levels less `n` times the saddle's) of more than
//!    4 ([`AUTO_SPLIT_CAP`]) times `sigma sqrt(n)`, the noise of a sum of
//!    `n` pixels (the noise floor is [`AUTO_SPLIT_NOISE_STRUCTURED`], 25
//!    sigma, in frames whose particle images have structure of their own:
//!    see "Structured particle images" below). The first keeps the ripples of a bright extended
//!    structure (a reflection streak, whose ripples are shallow next to its
//!    height) in one target; the second keeps noise from splitting faint
//!    particles; the third asks that the bump as a whole, not only its
//!    peak pixel, stand out of the noise (the peak test sees one pixel, 3
//!    sigma; a bump of a few pixels that each rise a sigma or two above
//!    the saddle passes it on its brightest pixel alone, and is what the
//!    ripples of real, irregular particle images are). A sum of `n` noise
//!    pixels exceeds `4 sigma sqrt(n)` with a probability of about 3e-5;
//!    the cap's pixels are selected by being above the saddle, so noise
//!    passes more often than that, which is why the constant is no
//!    smaller. It is no larger because touching rendered particles are
//!    lost: of the pairs merged at 0.02 ppp (`detect_accuracy.rs`, which
//!    asserts half) 52.3% are recovered without the test, 51.8% with 4,
//!    50.2% with 5 and 48.5% with 6; with 12 (`min_snr`'s value) only
//!    46% of those at 0.01 ppp.
//!    The noise level `sigma` is the image's after the high-pass filter,
//!    estimated on every frame before the filter runs (only when a rule
//!    needs it): the filtered value, signed, of a sparse subsample of at
//!    most about 2^14 pixels (32 rows spread over the image, every 4th pixel
//!    of a 1280-pixel row; `noise_steps`), and `sigma = 1.4826
//!    (median - q25)`, the robust standard deviation of the sample's lower
//!    half (`noise_sigma`). Particles only add to the filtered values, so
//!    the lower half is the background's: the pixel noise, and also the
//!    faint structure the filter leaves at the particles' scale (out of
//!    focus particles, scattered light), which makes spurious maxima and
//!    blobs just as noise does. On the real test_cavity recording the
//!    difference of neighbouring pixels (what the rule used before) says
//!    about 1.05 grey levels, the filtered image 2.6-3.2 (radius 10); on
//!    rendered frames of white noise both are the noise's sigma. Measured
//!    (`tests/photogrammetry`): a larger fraction parts fewer
//!    touching rendered particles; at 1/3, half the merged pairs of
//!    `detect_accuracy.rs` at 0.02 ppp are no longer recovered and at 1/4
//!    recall at 0.005 ppp in front of bright structure
//!    (`structured_background.rs`) falls below 0.95; at 1/5 both hold,
//!    while false targets on that structure without background subtraction
//!    fall from 64% to 36% of the particles at 0.001 ppp (depth 4). The rules
//!    cannot part two particles whose sum has one maximum: with Gaussian
//!    images that happens below about one image diameter of separation
//!    (for 2.5 px particles, `tests/photogrammetry/detect_accuracy.rs` splits 98-100% of
//!    pairs 2.5 px or more apart, about 70% at 2..2.5 px, none below
//!    1.5 px).
//!
//! **OpenPTV's segmentation** ([`DetectionParameters::split_depth`]
//! `Some(d)`, OpenPTV's `discont`, what `ptv experiment import` sets).
//! OpenPTV's `targ_rec` (liboptv `src/segmentation.c`) scans the filtered
//! image in raster order; a pixel above the threshold that is at least as
//! bright as its 8 neighbours starts a target, which grows breadth first
//! over the 4 edge neighbours (`x4`/`y4`), taking a pixel above the
//! threshold unless it, or one of its own 4 neighbours, is more than
//! `discont` above the pixel it is reached from; taken pixels are removed,
//! so what a target could not climb to starts a later one. Two pixels that
//! touch only at a corner are never joined. On the real test_cavity
//! recording (`tests/photogrammetry/real_recording.rs`, 16 images against
//! optv 0.3.2's targets) the 4-connected blobs are what makes ours agree:
//! with 8-connected blobs 82.7% of OpenPTV's targets have one of ours within
//! 0.5 px (79-88% per image), most of the rest a target of ours holding
//! theirs plus pixels joined at a corner; with 4-connected blobs 88.4%
//! (85.0-93.4% per image) and about the same share of ours. So blobs are
//! 4-connected (with the automatic rule too, since the defaults were
//! measured on this recording, below); within a blob the split still
//! compares all 8 neighbours (as `targ_rec`'s test for a starting maximum
//! does), with `d` as the depth. The rest of `targ_rec` is not copied: its growth
//! depends on the raster order (a particle is parted where growth from the
//! maximum above it cannot climb), and its centroid weights `g - t` use the
//! filtered value after truncating the subtracted mean to a whole grey
//! level (up to one grey level more weight on every pixel, which pulls the
//! centroid towards the middle of the pixel set); ours keep the fraction.
//! Its box filter (`fast_box_blur`) near the border averages a window
//! shrunk symmetrically around the pixel where ours clips it, and the
//! threshold test `g - floor(mean) > t` is ours, `g - mean > t`, in
//! integers: `targ_rec` run on our filtered image finds 99.3% of its own
//! targets (cameras 2 and 3, frame 10001), so the filter is not changed. A
//! 4-connected segmentation can part pixels that touch at a corner into
//! separate targets, so targets of fewer than 4 pixels can be denser than
//! one per 2x2 pixels ([`max_targets`](super::correspond::max_targets)
//! holds from 4 pixels on; the significance test leaves such noise out).
//!
//! 4. **Centroids**: the grey value weighted centre of gravity of each
//!    particle's pixels, with weights `g - threshold` as in OpenPTV's
//!    `targ_rec` (a pixel at the threshold weighs nothing, so a pixel that
//!    crosses it moves the centroid continuously). Filters on pixel count,
//!    extent and sum of grey values follow, and targets touching the image
//!    border are dropped (their centroid is cut off). `sumg` is the sum of
//!    the filtered grey values, in the image's grey levels. With
//!    [`DetectionParameters::centroid`] [`Centroid::Gaussian`] the position
//!    is instead a 3-point Gaussian fit per axis around the particle's
//!    brightest pixel, falling back on the weighted centroid per axis where
//!    it does not apply ([`super::centroid`]).
//! 5. **Significance** ([`DetectionParameters::min_snr`], default
//!    [`DEFAULT_MIN_SNR`] = 12): a target's sum of grey over its `n` pixels
//!    must be at least `min_snr · sigma · sqrt(n)`, with the noise level
//!    `sigma` above. `sumg / (sigma sqrt n)` is the signal-to-noise ratio
//!    of the target's integrated brightness (the noise of a sum of `n`
//!    pixels is `sigma sqrt n`), and it also bounds how far noise moves the
//!    weighted centroid: about `sigma sqrt(n) rho / sumg` per axis for
//!    pixels at an rms distance `rho` from it, so at 12 a 2.5 px particle
//!    (`rho` about 1 px) has a centroid within about 0.08 px, the precision
//!    the correspondence search and the intersection are built for. It is
//!    relative to the image, so it holds for 8- and 16-bit images, dark and
//!    bright backgrounds and any gain, where an absolute `min_sumg` is one
//!    camera's. On pure noise it leaves nothing: a blob of `n` pixels
//!    above a threshold of `t sigma` has `sumg` about `(t + 0.4) sigma n`,
//!    so at `t = 1.5` it needs 40 connected pixels, which noise so far
//!    below the percolation threshold does not make (unit test
//!    `pure_noise_gives_no_targets_by_default`: none on 512² frames at
//!    threshold 1.5, 2 and 3.3 sigma, 8- and 16-bit, where without it
//!    every cluster of 2 pixels is a target). Rendered particles (peaks
//!    80..200 over noise of about 1.5 grey levels) are far above it: recall
//!    on the rendered tests moves by less than 0.001. OpenPTV has no such
//!    test; an imported experiment sets 0 and keeps its `min_sumg`.
//!
//! **Structured particle images.** On ideal images (the renderer's
//! Gaussian spots) a blob with two maxima is two particles whose images
//! overlap. Real particle images have structure of their own: out of
//! focus they are rings and crescents, in motion streaks, through
//! aberrations irregular, and their maxima look like pairs to every test
//! above (on the test_cavity recording, the relative rise, the saddle's
//! and the peaks' ratios of the splits the 3 sigma rule accepted had the
//! same distributions as those of touching rendered pairs; only their
//! signal-to-noise ratio was lower, a median rise of 13 sigma against 37).
//! No rule for one blob tells them apart, but the frame as a whole does:
//! chance overlaps are rare at the densities PTV works at, and a frame
//! whose splits are many more than its overlaps explain has structured
//! images. So the automatic rule defers the blobs with several maxima
//! until the frame is searched, splits them with the 3 sigma floor, and
//! compares the targets the splits added, `k`, with the overlaps expected
//! of particles placed at random: with `N` targets over the image's `P`
//! pixels (the mask's, if any), and `a` the median pixel count of the
//! targets (as split with the 3 sigma floor), two images touch when their centres
//! are closer than `d = 2 sqrt(a / pi) + 1` (a diameter and the pixel
//! between), which happens to `N (1 - exp(-N pi d^2 / P))` of them, in
//! pairs: `E` is half that. If `k > 4 E` ([`STRUCTURED_SPLITS`]), by more
//! than the noise of a count (`3 sqrt(4 E) + 3`: 3 sigma of a Poisson count
//! of that mean, and a few splits where `E` is near 0, so that a lone
//! touching pair is still parted), the blobs
//! are split again with a noise floor of 25 sigma
//! ([`AUTO_SPLIT_NOISE_STRUCTURED`]), about twice the median rise of
//! those structured splits: what parts a blob is then a dip few ripples
//! reach, as OpenPTV's `discont` is set per experiment. Measured, `k / E`:
//! on rendered frames of ideal (Gaussian) particle images 2.1 to 2.3 for
//! 2.5 px at 0.001 to 0.02 particles per pixel, 2.4 and 2.6 for 3.5 px
//! at about 0.002 and 0.009, 2.8 for 4 px and 3.3 for 6 px at about 0.005
//! (`ptv simulate`), and 0.4 to 1.8 in front of structure
//! (`examples/detection_report.rs`); 5.1 to 7.4 on the test_cavity
//! recording's 16 images, 7.3 on the rings of the unit test
//! `rings_stay_whole_where_overlaps_cannot_explain_their_maxima`, and 8.9
//! to 9.9 on rendered frames whose glare streaks are not subtracted (their
//! ripples). 4 lies between, with margins of 1.2 to 1.3 on each side: the
//! estimate of `E` is rough (the reach from a median area, pairs only),
//! and it is the ratio's size, not its exact value, that tells the two
//! kinds of frame apart. The deferred blobs keep their levels; their
//! pixels' keys, sorted, are kept too while they fit in an eighth of the
//! image's pixels (at most 2^20 keys), and the rest are flooded again from
//! their first pixel at the end of the frame; in a
//! structured frame, those in which some saddle kept particles apart are
//! split a second time (where every saddle merged what it met, the higher
//! floor merges the same, and the target stands). On frames without blobs
//! of several maxima nothing changes; on the real recording's frames the
//! second split is most of the extra time (`benches/detect.rs`).
//!
//! **Defaults on a real recording** (`tests/photogrammetry/real_recording.rs`,
//! `examples/detection_report.rs`; test_cavity frames 10001-10004, cameras
//! 1-4, against OpenPTV 0.3.2 with the experiment's own parameters;
//! `DetectionParameters::default()` only). Issue 13 asks for at most 1.25
//! times OpenPTV's count and at least 80% of its targets found within
//! 0.5 px. The defaults reach 1.21x and 81.7% (per image 0.96-1.46x and
//! 75.9-88.8%). The way there, over the 16 images:
//!
//! | defaults | ours / OpenPTV's | theirs found |
//! | --- | ---: | ---: |
//! | radius 10, 8-connected blobs, 3 sigma rule (before) | 2.55x | 74.1% |
//! | radius 25 | 1.81x | 76.8% |
//! | and 4-connected blobs | 1.79x | 77.3% |
//! | and the rule for structured frames at 20 sigma | 1.25x | 82.2% |
//! | at 25 sigma (the default) | 1.21x | 81.7% |
//! | at 30 sigma | 1.19x | 80.9% |
//!
//! Without splitting at all: 1.76x and 73.7% at radius 10, 1.13x and 79.0%
//! at radius 25 with 4-connected blobs. The radius matters most because
//! OpenPTV's own targets were found at 25 (pyptv's default too): 14% of
//! them are streaks of more than 30 pixels whose centroid depends on the
//! filter, and at radius 30 only 75.4% are found. A larger floor
//! everywhere instead of per frame (20 sigma: 1.25x, 82.2%) costs the
//! rendered frames their touching pairs: at 0.005 particles per pixel,
//! recall in front of bright structure after median subtraction falls to
//! 0.949 (`structured_background.rs` asserts issue 13's 0.95), and fewer
//! than 95% of the pairs 2.5 px or more apart are parted
//! (`detect_accuracy.rs`); with the rule per frame both tests pass
//! unchanged (0.950; 98-100%). What radius 25 costs: on rendered frames
//! with bright objects over a quarter of the image and no background
//! subtraction (`structured_background.rs`), recall falls from 0.90, 0.86
//! and 0.83 to 0.54, 0.58 and 0.59 at 0.001, 0.005 and 0.01 particles per
//! pixel (false targets from 36%, 13% and 9% to 7%, 20% and 17%): the
//! larger window follows the objects' edges less closely. With the
//! background subtracted, the remedy for such frames, nothing changes
//! (recall 0.989, 0.950, 0.912).
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
//! takes time linear in its pixels (`benches/detect.rs`). The filter runs a
//! row at a time, and blobs are found a few rows behind it while those
//! rows are still in cache (the noise level, when a rule needs it, is
//! estimated before, on its sparse sample); most of the filter's test runs 32 pixels at a
//! time in 32-bit arithmetic, which the compiler vectorises, and the
//! background is subtracted a row at a time in the samples' own type.
//! On x86-64 CPUs with AVX2 the detection runs in a copy compiled for it
//! (chosen at run time), whose vector loops take twice the pixels per
//! instruction. The filter marks the blocks of 64 pixels that hold a pixel
//! above the threshold, and only those are searched for blobs.
//! Filtered values
//! are kept in 16-bit grey levels (8-bit values times 257), so the fraction
//! of the subtracted mean survives in the centroid weights, and an 8-bit
//! image and its 16-bit copy give the same targets. All of it is integer
//! arithmetic with ties broken in raster order, so results are exact and
//! repeatable: translating an image by whole pixels translates every
//! centroid by exactly that. [`detect_cameras`] detects the frames of
//! several cameras in parallel.
//!
//! # Memory
//!
//! Detection's scratch is bounded per pixel of the image, whatever the
//! image holds: at most **21 bytes a pixel** with an absolute split depth
//! and **33** with the automatic rule (plus a few bytes a row and a
//! column), 1.3 and 2.1 GiB for the largest sensor
//! ([`MAX_SENSOR_PIXELS`](super::camera::MAX_SENSOR_PIXELS), 2^26 px),
//! besides the image itself and the targets found (40 bytes each, at most
//! twice that while their vector grows and is sorted; with the automatic
//! rule, also the targets of the deferred blobs' first split while the
//! frame is weighed, and 4 bytes a target for their sizes). It is made of:
//! the filtered levels (2 bytes a pixel); the blob being measured, each
//! pixel packed with its level in one `u64` that is the flood's queue,
//! then sorted into flooding order, then re-keyed by particle (8 bytes a
//! pixel above the threshold, reserved as the filter goes, never more than
//! 8 bytes a pixel filtered); for a blob that is split, its
//! bounding box's map of regions (4 bytes a cell) and a union-find node and
//! a particle number per local maximum (12 bytes; reserved by a count of
//! the pixels with no brighter edge neighbour, at most one per 2 pixels: 6
//! bytes a pixel); with the automatic split rule also its cap's pixel
//! count and sum (8 bytes more a maximum, 4 a pixel), and for the blobs
//! deferred to the end of the frame (whose levels stay in place and are
//! flooded again from their first pixel) a mark a pixel (one bit) and
//! their first pixels (8 bytes a blob of at least 3 pixels, at most twice
//! that while the vector grows: 5.3 bytes a pixel), and the sorted keys
//! of the first of them with their bounding boxes (at most an eighth of
//! the pixels' keys and 16 MiB: 2 bytes a pixel). The blob's keys are
//! sorted by radix from 256 pixels up to an eighth of the image's pixels
//! (and 2^20), with a scratch of 8 bytes a key (a byte a pixel, 8 MiB at
//! most), and in place beyond.
//! With a target limit ([`detect_within`], which the frame pipeline calls
//! with [`max_targets`](super::correspond::max_targets) of the camera's
//! sensor), the targets found never exceed it by more than one blob's:
//! detection stops as soon as it is passed ([`TooManyTargets`]), so a
//! hostile frame (a 1-pixel checkerboard at threshold 1 would make 33.5
//! million targets of an 8192x8192 sensor) costs its scratch and the
//! limit's 40 bytes a target, not 40 bytes a pixel. With the automatic
//! split rule the deferred blobs' first split is counted, not kept, once
//! the frame is past the limit.
//! Particles are measured one at a time. The worst case is an image whose
//! pixels are all above the threshold in one noisy blob; a test in this
//! module counts the allocations of such an image and holds them to the
//! bound. A particle image (a few percent of the pixels above the threshold,
//! small blobs) needs little more than its 2 bytes a pixel of levels. The
//! noise level's estimate adds about 64 KiB at most (its subsample of
//! about 2^14 filtered values, 4 bytes each) and 8 bytes a column; the
//! blocks' marks one bit per 64 pixels. A detection leaves its levels
//! cleared, and each thread keeps them for its next detection (up to
//! `KEPT_LEVELS`, 2^24 pixels: 32 MiB), so frames of one size after the
//! first need no allocation and no clearing of 2 bytes a pixel.

// Over 800 lines: a third is the module documentation above, the rest the
// public API and the frame's driver (`Detector::run`); each step is in a
// submodule below.
mod centroid;
mod highpass;
mod noise;
mod segment;
mod split;
#[cfg(test)]
pub(crate) mod tests;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::centroid::Centroid;
use super::image::{GreyImage, GreyPixels, Mask};
use super::target::Target;
use highpass::HighPass;
use segment::TRAIL;
use split::{Region, StoredBlob};

/// The automatic split rule ([`DetectionParameters::split_depth`] `None`):
/// a maximum is a particle of its own only if it rises above the saddle by
/// more than this fraction (numerator, denominator) of its height above the
/// threshold.
pub const AUTO_SPLIT_FRACTION: (u32, u32) = (1, 5);

/// The automatic split rule: a maximum is a particle of its own only if it
/// rises above the saddle by more than this many times the image's noise
/// level (tenths: 30 is 3 sigma).
pub const AUTO_SPLIT_NOISE: u64 = 30;

/// The automatic split rule: a maximum is a particle of its own only if
/// its cap, the `n` pixels of its particle brighter than the saddle, holds
/// a volume above the saddle (the sum of their levels less `n` times the
/// saddle's) of more than this many times `sigma sqrt(n)`, the noise of a
/// sum of `n` pixels (tenths: 40 is 4). A significance test on the bump
/// as a whole, where [`AUTO_SPLIT_NOISE`] tests its peak pixel alone (see
/// the module documentation).
pub const AUTO_SPLIT_CAP: u64 = 40;

/// The automatic split rule in a frame whose particle images have structure
/// of their own ([`STRUCTURED_SPLITS`]): a maximum is a particle of its own
/// only if it rises above the saddle by more than this many times the
/// image's noise level (tenths: 250 is 25 sigma), in place of
/// [`AUTO_SPLIT_NOISE`] (see the module documentation).
pub const AUTO_SPLIT_NOISE_STRUCTURED: u64 = 250;

/// The automatic split rule: a frame's particle images have structure of
/// their own when its splits part more than this many times the targets
/// that chance overlaps of particle images explain (see the module
/// documentation).
pub const STRUCTURED_SPLITS: f64 = 4.0;

/// The default of [`DetectionParameters::min_snr`]: a target's sum of grey
/// must be at least this many times the noise of a sum over its pixels
/// (see the module documentation).
pub const DEFAULT_MIN_SNR: u16 = 12;

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
    /// rises are taken as noise on one particle. `Some(d)` is this absolute
    /// depth (OpenPTV's `discont`; see the module documentation, "OpenPTV's
    /// segmentation"); `None` (the default, `null` in JSON) is
    /// the automatic rule: the rise must exceed both a fraction
    /// ([`AUTO_SPLIT_FRACTION`]) of the maximum's own height above the
    /// threshold and [`AUTO_SPLIT_NOISE`] times the image's noise level
    /// ([`AUTO_SPLIT_NOISE_STRUCTURED`] in a frame whose particle images
    /// have structure of their own), and the maximum's pixels above the
    /// saddle must hold a volume above it that stands out of the noise
    /// ([`AUTO_SPLIT_CAP`]; see the module documentation, "Structured
    /// particle images").
    pub split_depth: Option<u16>,
    /// How a target's position is estimated from its pixels: the weighted
    /// centroid (the default, OpenPTV's) or a Gaussian fit
    /// ([`super::centroid`]).
    pub centroid: Centroid,
    /// The smallest signal-to-noise ratio of a target: its sum of grey
    /// `sumg` over its `n` pixels must be at least `min_snr · sigma · sqrt
    /// n`, `sigma` being the image's noise level after the high-pass
    /// filter, estimated on every frame (see the module documentation). 0
    /// turns the test off (OpenPTV has none: an imported experiment sets
    /// 0 and keeps its `min_sumg`).
    pub min_snr: u16,
}

impl Default for DetectionParameters {
    fn default() -> Self {
        DetectionParameters {
            threshold: 10,
            highpass_radius: 25,
            min_pixels: 2,
            max_pixels: 500,
            min_nx: 1,
            max_nx: 50,
            min_ny: 1,
            max_ny: 50,
            min_sumg: 0,
            split: true,
            split_depth: None,
            centroid: Centroid::Weighted,
            min_snr: DEFAULT_MIN_SNR,
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
    detect_with_pixels_if::<false>(image, &NO_PREPROCESSING, parameters, usize::MAX)
        .map_or_else(|_| unreachable!("no target limit"), |found| found.0)
}

/// Why [`detect_within`] stopped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DetectError {
    /// The background or mask does not fit the frame.
    #[error(transparent)]
    Preprocess(#[from] PreprocessError),
    /// The frame has more targets than the limit: detection stopped as
    /// soon as it was passed.
    #[error(transparent)]
    TooManyTargets(#[from] TooManyTargets),
}

/// More targets than a detection's limit: it stopped as soon as the limit
/// was passed, so the count is not known.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error(
    "detection found more than {limit} targets and stopped; raise the threshold, min_pixels or \
     min_snr so that noise is not taken for particles"
)]
pub struct TooManyTargets {
    /// The limit.
    pub limit: usize,
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
    let (targets, pixels) =
        detect_with_pixels_if::<true>(image, &NO_PREPROCESSING, parameters, usize::MAX)
            .unwrap_or_else(|_| unreachable!("no target limit"));
    targets
        .into_iter()
        .zip(pixels)
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

/// What is done to a camera's frames before the high-pass filter: a
/// background subtracted (an image of the view without particles, e.g. the
/// mean or minimum of many frames: reflections and static bright objects
/// disappear) and a mask of the pixels to use. Both are per camera and
/// must have its frames' size; the background also their bit depth.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Preprocessing {
    /// Subtracted from every frame, pixel by pixel, saturating at 0.
    pub background: Option<GreyImage>,
    /// Only the pixels it uses can be part of a target.
    pub mask: Option<Mask>,
}

/// A background or mask that does not fit the frame it is applied to.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PreprocessError {
    /// The background's size is not the frame's.
    #[error(
        "the background is {width}x{height} pixels but the frame is \
         {expected_width}x{expected_height}; use a background recorded with this camera"
    )]
    BackgroundSize {
        /// Background width.
        width: u32,
        /// Background height.
        height: u32,
        /// Frame width.
        expected_width: u32,
        /// Frame height.
        expected_height: u32,
    },
    /// The background's bit depth is not the frame's.
    #[error(
        "the background has {bits}-bit samples but the frame {expected_bits}-bit ones; \
         use a background saved in the frames' bit depth"
    )]
    BackgroundDepth {
        /// Background bits per sample.
        bits: u32,
        /// Frame bits per sample.
        expected_bits: u32,
    },
    /// The mask's size is not the frame's.
    #[error(
        "the mask is {width}x{height} pixels but the frame is \
         {expected_width}x{expected_height}; use a mask of this camera's image size"
    )]
    MaskSize {
        /// Mask width.
        width: u32,
        /// Mask height.
        height: u32,
        /// Frame width.
        expected_width: u32,
        /// Frame height.
        expected_height: u32,
    },
}

impl Preprocessing {
    /// Whether it does nothing.
    pub fn is_empty(&self) -> bool {
        self.background.is_none() && self.mask.is_none()
    }

    /// Checks the background's and the mask's size against frames of
    /// `width` x `height` pixels (a camera's sensor).
    pub fn check_size(&self, width: u32, height: u32) -> Result<(), PreprocessError> {
        if let Some(background) = &self.background {
            if (background.width(), background.height()) != (width, height) {
                return Err(PreprocessError::BackgroundSize {
                    width: background.width(),
                    height: background.height(),
                    expected_width: width,
                    expected_height: height,
                });
            }
        }
        if let Some(mask) = &self.mask {
            if (mask.width(), mask.height()) != (width, height) {
                return Err(PreprocessError::MaskSize {
                    width: mask.width(),
                    height: mask.height(),
                    expected_width: width,
                    expected_height: height,
                });
            }
        }
        Ok(())
    }

    /// Checks that it fits `image`: sizes, and the background's bit depth.
    pub fn check(&self, image: &GreyImage) -> Result<(), PreprocessError> {
        self.check_size(image.width(), image.height())?;
        if let Some(background) = &self.background {
            if background.bit_depth() != image.bit_depth() {
                return Err(PreprocessError::BackgroundDepth {
                    bits: background.bit_depth().bits(),
                    expected_bits: image.bit_depth().bits(),
                });
            }
        }
        Ok(())
    }
}

/// [`detect`] after `preprocessing`: the background is subtracted
/// (saturating at 0) as the filter reads the samples, before the high-pass
/// filter and the threshold, and masked-out pixels are never above the
/// threshold. Errors if the background or mask does not fit the image.
pub fn detect_preprocessed(
    image: &GreyImage,
    preprocessing: &Preprocessing,
    parameters: &DetectionParameters,
) -> Result<Vec<Target>, PreprocessError> {
    preprocessing.check(image)?;
    Ok(
        detect_with_pixels_if::<false>(image, preprocessing, parameters, usize::MAX)
            .unwrap_or_else(|_| unreachable!("no target limit"))
            .0,
    )
}

/// [`detect_preprocessed`] with a limit on the targets: once more than
/// `limit` targets have been found, detection stops with
/// [`DetectError::TooManyTargets`] (the rest of the frame is not
/// searched, and the targets found are dropped). Below the limit the
/// targets are [`detect_preprocessed`]'s.
pub fn detect_within(
    image: &GreyImage,
    preprocessing: &Preprocessing,
    parameters: &DetectionParameters,
    limit: usize,
) -> Result<Vec<Target>, DetectError> {
    preprocessing.check(image)?;
    Ok(detect_with_pixels_if::<false>(image, preprocessing, parameters, limit)?.0)
}

/// An empty [`Preprocessing`], for the functions without one.
const NO_PREPROCESSING: Preprocessing = Preprocessing {
    background: None,
    mask: None,
};

/// Detection after `preprocessing`, which fits the image (checked by the
/// caller; one that does not is ignored where it does not fit), stopping
/// once more than `limit` targets are found.
fn detect_with_pixels_if<const PIXELS: bool>(
    image: &GreyImage,
    preprocessing: &Preprocessing,
    parameters: &DetectionParameters,
    limit: usize,
) -> Result<Found, TooManyTargets> {
    // A GreyImage has at least one pixel and its samples fill its size.
    let (width, height) = (image.width() as usize, image.height() as usize);
    let fits = preprocessing.check(image).is_ok();
    let mask = preprocessing.mask.as_ref().filter(|_| fits);
    let background = preprocessing.background.as_ref().filter(|_| fits);
    let (mut targets, pixels) = match image.pixels() {
        GreyPixels::Eight(pixels) => {
            let mut detector = Detector::new(pixels, width, height, parameters);
            detector.mask = mask;
            detector.limit = limit;
            if let Some(GreyPixels::Eight(b)) = background.map(GreyImage::pixels) {
                detector.background = Some(b);
            }
            detector.run::<PIXELS>()?
        }
        GreyPixels::Sixteen(pixels) => {
            let mut detector = Detector::new(pixels, width, height, parameters);
            detector.mask = mask;
            detector.limit = limit;
            if let Some(GreyPixels::Sixteen(b)) = background.map(GreyImage::pixels) {
                detector.background = Some(b);
            }
            detector.run::<PIXELS>()?
        }
    };
    let order = |a: &Target, b: &Target| a.y.total_cmp(&b.y).then(a.x.total_cmp(&b.x));
    Ok(if PIXELS {
        let mut found: Vec<_> = targets.into_iter().zip(pixels).collect();
        found.sort_by(|(a, _), (b, _)| order(a, b));
        found.into_iter().unzip()
    } else {
        // In place (a stable sort takes a scratch of half the targets, 20
        // bytes a pixel of a hostile frame's): targets at the same position
        // are ordered by their other fields, so the order is still one
        // order (only targets equal in every field tie, and those are
        // interchangeable).
        targets.sort_unstable_by(|a, b| {
            order(a, b)
                .then(a.n.cmp(&b.n))
                .then(a.nx.cmp(&b.nx))
                .then(a.ny.cmp(&b.ny))
                .then(a.sumg.cmp(&b.sumg))
        });
        (targets, pixels)
    })
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
    /// The largest grey value.
    const MAX_VALUE: u64;
    /// Black.
    const ZERO: Self;
    /// The grey value.
    fn value(self) -> u32;
    /// The grey value less the background's, saturating at 0, if `BG`;
    /// else the grey value.
    #[inline(always)]
    fn less<const BG: bool>(self, background: Self) -> u32 {
        if BG {
            self.saturating_less(background).value()
        } else {
            self.value()
        }
    }
    /// `self - other`, saturating at 0, in the sample's own type (one
    /// vector instruction for many samples: `psubusb`/`psubusw`).
    fn saturating_less(self, other: Self) -> Self;
}

impl Grey for u8 {
    const LEVEL_SCALE: u64 = 257;
    const MAX_VALUE: u64 = 255;
    const ZERO: Self = 0;
    #[inline(always)]
    fn value(self) -> u32 {
        u32::from(self)
    }
    #[inline(always)]
    fn saturating_less(self, other: Self) -> Self {
        self.saturating_sub(other)
    }
}

impl Grey for u16 {
    const LEVEL_SCALE: u64 = 1;
    const MAX_VALUE: u64 = 65535;
    const ZERO: Self = 0;
    #[inline(always)]
    fn value(self) -> u32 {
        u32::from(self)
    }
    #[inline(always)]
    fn saturating_less(self, other: Self) -> Self {
        self.saturating_sub(other)
    }
}

/// A blob pixel packed in one `u64`: `(65535 - level) << 32 | index`, with
/// `index = y * width + x` (a [`GreyImage`] has at most 2^32 pixels). Sorted
/// ascending, keys run bright to dark and, at equal levels, in raster
/// order: the flooding order of the splitting step.
#[inline(always)]
fn key(level: u16, index: usize) -> u64 {
    (u64::from(u16::MAX - level) << 32) | index as u64
}

/// The pixel index of a [`key`] (also of the keys `slot << 32 | index` of
/// the measuring step).
#[inline(always)]
fn key_index(key: u64) -> usize {
    (key & 0xffff_ffff) as usize
}

/// The level of a [`key`].
#[inline(always)]
fn key_level(key: u64) -> u16 {
    u16::MAX - (key >> 32) as u16
}

/// Splits pixel indices `y * width + x` into column and row without an
/// integer division (tens of cycles, and the blob steps need a pixel's
/// position several times): the row is the high word of the index times
/// `m = floor((2^64 - 1) / width) + 1`, one multiplication (Granlund and
/// Montgomery 1994, "Division by invariant integers using
/// multiplication"). `m` is `2^64 / width` rounded up (exactly it for a
/// power of two), so `p m / 2^64 = p / width + e` with `0 <= e < p / 2^64
/// < 2^-32` for indices below 2^32 (a [`GreyImage`]'s limit, and what a
/// [`key`] holds); the fraction of `p / width` is at most `1 - 1 / width`
/// and `1 / width > 2^-32`, so the high word is the row exactly. (A
/// width of 1, whose `m` would be `2^64`, has the index as its row.) The
/// `f64` reciprocal this replaces took about 25 instructions, mostly the
/// conversions between `usize` and `f64`.
#[derive(Clone, Copy, Debug)]
struct Rows {
    width: usize,
    magic: u64,
}

impl Rows {
    fn new(width: usize) -> Rows {
        let width = width.max(1);
        Rows {
            width,
            magic: if width == 1 {
                0
            } else {
                u64::MAX / width as u64 + 1
            },
        }
    }

    #[inline(always)]
    fn position(self, p: usize) -> (usize, usize) {
        debug_assert!(p < 1 << 32);
        if self.magic == 0 {
            return (0, p);
        }
        let y = ((u128::from(p as u64) * u128::from(self.magic)) >> 64) as usize;
        (p - y * self.width, y)
    }
}

/// The largest `levels` buffer a thread keeps for its next detection
/// (pixels): 2^24, 32 MiB.
const KEPT_LEVELS: usize = 1 << 24;

thread_local! {
    /// The `levels` of this thread's last detection, all 0 again when it
    /// ended (every blob's levels are cleared once it is measured), so the
    /// next detection on the thread need not allocate and clear 2 bytes a
    /// pixel (about a tenth of a frame's time). Taken out while a
    /// detection runs, so a detection that panics leaves none behind.
    static ZEROED_LEVELS: std::cell::Cell<Vec<u16>> = const { std::cell::Cell::new(Vec::new()) };
}

/// `pixels` levels, all 0: this thread's kept buffer if there is one.
fn zeroed_levels(pixels: usize) -> Vec<u16> {
    let mut levels = ZEROED_LEVELS.take();
    // Shorter: zeros are added; longer: cut (all of it is 0).
    levels.resize(pixels, 0);
    levels
}

/// Keeps `levels` (all 0) for this thread's next detection, if not too
/// large.
fn keep_zeroed_levels(levels: Vec<u16>) {
    if levels.capacity() <= KEPT_LEVELS {
        ZEROED_LEVELS.set(levels);
    }
}

/// Targets, and when asked for, each one's pixels (else no vectors at all).
type Found = (Vec<Target>, Vec<Vec<(u32, u32)>>);

/// One frame's detection, with the scratch space it reuses from blob to
/// blob. Its memory is bounded per pixel of the image whatever the image
/// holds (see the module's "Memory" section): `levels` (2 bytes a pixel),
/// `blob` (8 bytes a pixel above the threshold; see `reserve_blob`), `grid` (4
/// bytes a cell of the largest split blob's bounding box), `regions` and
/// `slot` (12 bytes a local maximum of the largest split blob, reserved by
/// a count of at most one per 2 pixels), `caps` (8 bytes a maximum, with
/// the automatic rule), and with the automatic rule the deferred blobs'
/// marks (a bit a pixel), seeds (8 bytes a deferred blob, of 3 pixels or
/// more) and the first split's target sizes (4 bytes a target).
struct Detector<'a, G: Grey> {
    pixels: &'a [G],
    width: usize,
    height: usize,
    /// Pixel index to column and row, without a division.
    rows: Rows,
    parameters: &'a DetectionParameters,
    /// Subtracted from the pixels before the filter, if any.
    background: Option<&'a [G]>,
    /// The pixels that may be above the threshold, if not all.
    mask: Option<&'a Mask>,
    /// Levels (high-pass filtered grey values in 16-bit grey levels) of the
    /// pixels above the threshold; 0 elsewhere and once a pixel's blob has
    /// been measured (while a blob is flooded its pixels are 0, while it is
    /// measured they hold their levels again).
    levels: Vec<u16>,
    /// The blocks of 64 pixels that hold levels (see [`RowOut`](highpass::RowOut)).
    marks: Vec<u64>,
    /// How many pixels are above the threshold.
    above: usize,
    /// The blob being measured, as [`key`]s: first the flood's queue (the
    /// pixels before `head` have been expanded), then sorted into flooding
    /// order, then re-keyed by particle to measure them one at a time.
    blob: Vec<u64>,
    /// The radix sort's scratch for the blob's keys (see
    /// [`split::sort_keys`]; a byte a pixel and 8 MiB at most).
    sorted: Vec<u64>,
    /// The bounding box of the blob in `blob` (corner, size), found by its
    /// flood.
    bounds: ((usize, usize), (usize, usize)),
    /// Splitting: per cell of the blob's bounding box and a border of one
    /// cell around it, the region of its pixel once visited, else `NONE`.
    grid: Vec<u32>,
    regions: Vec<Region>,
    /// The automatic split rule: per region, its pixels so far and the sum
    /// of their levels (saturating), the "cap" above the level being
    /// flooded.
    caps: Vec<(u32, u32)>,
    /// Measuring: per region root, its particle's number in the blob.
    slot: Vec<u32>,
    /// Measuring a split blob of few particles: each one's moments (see
    /// [`Detector::split_and_measure`]; at most 1,024).
    moments: Vec<centroid::Moments>,
    /// The image's noise level after the high-pass filter (levels, one
    /// standard deviation), estimated before the filter when a rule needs
    /// it ([`Detector::sample_noise`]); 0 when not needed.
    noise: u32,
    /// The automatic split rule's noise floor in force, in tenths of the
    /// noise level: [`AUTO_SPLIT_NOISE`], or
    /// [`AUTO_SPLIT_NOISE_STRUCTURED`] once the frame is found structured.
    split_noise: u64,
    /// The automatic split rule: the blobs with several maxima, split after
    /// the whole frame has been searched, when the frame's statistics are
    /// known: each one's first pixel, from which it is flooded again, and a
    /// bit a pixel marking their pixels, whose levels stay in `levels`
    /// until then (the search passes them by; allocated with the first).
    deferred: Vec<usize>,
    deferred_marks: Vec<u64>,
    /// The first deferred blobs' keys, sorted, and where each one's are
    /// (see [`Detector::store_deferred`]); the rest are flooded again.
    stored_keys: Vec<u64>,
    stored: Vec<StoredBlob>,
    /// Whether the keys in `blob` are sorted already (a stored blob's).
    presorted: bool,
    /// Whether the last split kept particles apart at some saddle (see
    /// [`Detector::split_deferred`]).
    kept_apart: bool,
    /// The automatic split rule: the pixel counts of the targets found
    /// (with [`AUTO_SPLIT_NOISE`]).
    target_sizes: Vec<u32>,
    /// The most targets the frame may have: detection stops once more are
    /// found ([`TooManyTargets`]).
    limit: usize,
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
            rows: Rows::new(width),
            parameters,
            background: None,
            mask: None,
            levels: Vec::new(),
            marks: Vec::new(),
            above: 0,
            blob: Vec::new(),
            sorted: Vec::new(),
            bounds: ((0, 0), (0, 0)),
            grid: Vec::new(),
            regions: Vec::new(),
            caps: Vec::new(),
            slot: Vec::new(),
            moments: Vec::new(),
            noise: 0,
            split_noise: AUTO_SPLIT_NOISE,
            deferred: Vec::new(),
            deferred_marks: Vec::new(),
            stored_keys: Vec::new(),
            stored: Vec::new(),
            presorted: false,
            kept_apart: false,
            target_sizes: Vec::new(),
            limit: usize::MAX,
        }
    }

    /// Estimates the image's noise level if a rule needs it
    /// ([`Detector::sample_noise`]), then filters the image row by row
    /// ([`HighPass`]) and finds, splits and measures the blobs in the rows
    /// filtered so far, [`TRAIL`] rows behind the filter, while those rows
    /// are still in cache. A blob that
    /// reaches the last filtered row may go on below it: the search pauses
    /// there and tries that blob again once the filter has gone twice as far
    /// below the blob's first row (so a tall blob is flooded at most a few
    /// times, in total less than twice its size), and after the last row
    /// every blob is complete. Blobs are independent of one another, so the
    /// targets do not depend on when their blob is measured.
    fn run<const PIXELS: bool>(self) -> Result<Found, TooManyTargets> {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: `run_avx2` needs AVX2, which this CPU has (just
            // checked).
            return unsafe { self.run_avx2::<PIXELS>() };
        }
        self.run_here::<PIXELS>()
    }

    /// [`Detector::run`] compiled for AVX2 (x86-64 CPUs since 2013): the
    /// row filter's loops ([`HighPass::next_row`], [`subtracted_row`](highpass::subtracted_row),
    /// [`filter_row_narrow`](highpass::filter_row_narrow)) are inlined here, so their vector code works
    /// on 256-bit registers, twice the baseline's 128. The results are the
    /// same: the arithmetic is integer and lane-wise.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn run_avx2<const PIXELS: bool>(self) -> Result<Found, TooManyTargets> {
        self.run_here::<PIXELS>()
    }

    /// [`Detector::run`]'s body, inlined into each of its versions.
    #[inline(always)]
    fn run_here<const PIXELS: bool>(mut self) -> Result<Found, TooManyTargets> {
        let (width, height) = (self.width, self.height);
        self.levels = zeroed_levels(width * height);
        self.marks = vec![0; (width * height).div_ceil(64 * 64)];
        self.above = 0;
        if self.wants_noise() {
            self.noise = self.sample_noise();
        }
        let mut filter = HighPass::new(&self);
        let mut found = (Vec::new(), Vec::new());
        // The next pixel that may be a blob's first, in raster order.
        let mut scan = 0;
        // The search waits until this row is filtered.
        let mut resume = TRAIL;
        while let Some(y) = filter.next_row(&mut self.levels, &mut self.marks, &mut self.above) {
            if y + 1 < height && y >= resume {
                let end = (y + 1 - TRAIL) * width;
                if let Some(first_row) =
                    self.find_blobs::<PIXELS>(&mut scan, end, Some(y), &mut found)
                {
                    resume = y + (y - first_row) + 1;
                }
                self.check_limit(&found)?;
            }
        }
        self.find_blobs::<PIXELS>(&mut scan, width * height, None, &mut found);
        self.check_limit(&found)?;
        self.split_deferred::<PIXELS>(&mut found)?;
        // Every blob has been measured, and its levels set to 0 after.
        debug_assert!(self.levels.iter().all(|&l| l == 0));
        keep_zeroed_levels(std::mem::take(&mut self.levels));
        Ok(found)
    }

    /// Whether `found` is past the limit. (A detection stopped this way
    /// leaves levels behind: its buffer is dropped, not kept.)
    #[inline(always)]
    fn check_limit(&self, found: &Found) -> Result<(), TooManyTargets> {
        if found.0.len() > self.limit {
            return Err(TooManyTargets { limit: self.limit });
        }
        Ok(())
    }
}
