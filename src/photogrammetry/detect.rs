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
//! kinds of frame apart. The deferred blobs keep their levels and are
//! flooded again from their first pixel at the end of the frame; in a
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
//! image holds: at most **20 bytes a pixel** with an absolute split depth
//! and **30** with the automatic rule (plus a few bytes a row and a
//! column), 1.25 and 1.9 GiB for the largest sensor
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
//! that while the vector grows: 5.3 bytes a pixel).
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

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::centroid::{self, Centroid, PeakSamples};
use super::image::{GreyImage, GreyPixels, Mask};
use super::target::Target;

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
        // Stable, as before: targets at the same position keep their order.
        targets.sort_by(order);
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

/// The level of a pixel whose filtered value `g - s/c` exceeds the
/// threshold `t`, given `d = g c - s` and the window size `c`:
/// `round(k d / c)` with `k = LEVEL_SCALE`, kept above `k t` (so its weight
/// is at least 1). It is at most `k g`, which fits in 16 bits.
#[inline]
fn level_above<G: Grey>(d: u64, c: u64, threshold: u64) -> u16 {
    let scale = G::LEVEL_SCALE;
    let level = (2 * d * scale + c) / (2 * c);
    level.max(threshold * scale + 1).min(u64::from(u16::MAX)) as u16
}

/// One row of [`HighPass`]'s filter: the window sum of column
/// `x` is the sum of `column_sums` over columns `x-r ..= x+r` (clipped), of
/// `rows * columns` pixels. Keeps the level of every pixel above the
/// threshold in `out`.
fn filter_row<G: Grey>(
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
fn filter_row_narrow<G: Grey>(
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
fn run_above<G: Grey>(pixels: &[G], upper: &[u32], lower: &[u32], c: u32, tc: u32) -> u32 {
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
const NARROW_RUN: usize = 32;

/// The hot loop of [`filter_row`]'s interior: from pixel `k` on, slides the
/// window sum `s` one column at a time (column `k`'s window gains
/// `entering[k]` and loses `leaving[k]`) until a pixel's `g c` exceeds
/// `s + t c`, and returns that pixel (or the row's end). Apart from the
/// caller, so that everything it needs stays in registers: one add on the
/// running sum's dependency chain, a multiply and a compare per pixel.
#[allow(clippy::too_many_arguments)]
#[inline(never)]
fn next_above<G: Grey>(
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

/// Rows between the last row [`HighPass`] has filtered and the last row in
/// which [`Detector::run`] looks for blobs' first pixels: room for a
/// particle image to end before the filter's frontier.
const TRAIL: usize = 8;

/// "No region / not yet visited" in the splitting step.
const NONE: u32 = u32::MAX;

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

/// One maximum's particle while a blob is flooded (a union-find node).
#[derive(Clone, Copy, Debug)]
struct Region {
    parent: u32,
    /// The grey value of its maximum.
    peak: u32,
}

/// The sums a target's centroid and filters need; one particle's at a time.
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
    fn add(&mut self, (x, y): (usize, usize), level: u32, corner: (usize, usize), threshold: u32) {
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

/// When a fainter maximum is a particle of its own (in levels).
#[derive(Clone, Copy)]
enum SplitRule {
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

/// Rows on which the noise level is sampled (fewer on shorter images).
const NOISE_ROWS: usize = 32;

/// Samples of the noise level, at most: a quantile-based sigma of `N`
/// samples has a relative standard error of about `1.2 / sqrt(N)`, 1.2% at
/// 10,000, far below what the rules need.
const NOISE_SAMPLES: usize = 1 << 14;

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
fn noise_steps(width: usize, height: usize) -> (usize, usize, usize) {
    let rows = NOISE_ROWS.min(height);
    let row_step = height / rows;
    let column_step = (rows * width).div_ceil(NOISE_SAMPLES).max(1);
    (row_step / 2, row_step, column_step)
}

/// Appends to `out` the high-pass filtered value, signed and in levels
/// (`LEVEL_SCALE` times grey levels, rounded down), of every
/// `column_step`-th pixel of `row`, with the window sums of
/// [`filter_row`] (`column_sums` over `rows` rows, radius `r`; `row` less
/// the background if any). `prefix`
/// is scratch (the running sums of `column_sums`). One pass of additions
/// over the row, on a sampled row only.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn sample_filtered_row<G: Grey>(
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
fn noise_sigma(samples: &mut [i32]) -> u32 {
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

/// Splits pixel indices `y * width + x` into column and row without an
/// integer division (tens of cycles, and the blob steps need a pixel's
/// position several times): the row is the index times `1 / width` in
/// `f64`, corrected by one where rounding put it on the wrong side of a row
/// start. Indices are below 2^32 (a [`GreyImage`]'s limit), exact in `f64`,
/// and the product's relative error (2^-52) is far below one row, so one
/// correction step is always enough.
#[derive(Clone, Copy, Debug)]
struct Rows {
    width: usize,
    inverse: f64,
}

impl Rows {
    fn new(width: usize) -> Rows {
        Rows {
            width,
            inverse: 1.0 / width as f64,
        }
    }

    #[inline(always)]
    fn position(self, p: usize) -> (usize, usize) {
        let mut y = (p as f64 * self.inverse) as usize;
        if y * self.width > p {
            y -= 1;
        } else if (y + 1) * self.width <= p {
            y += 1;
        }
        (p - y * self.width, y)
    }
}

/// Row `row` of an image `width` pixels wide, less the background's if
/// any, saturating at 0: the image's own row, or the difference written
/// into `scratch` (one row long).
#[inline(always)]
fn subtracted_row<'s, G: Grey>(
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
struct RowOut<'a> {
    /// The row's levels.
    levels: &'a mut [u16],
    /// The row's first pixel (`y * width`).
    start: usize,
    marks: &'a mut [u64],
    above: &'a mut usize,
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
struct HighPass<'a, G: Grey> {
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
    fn new(detector: &Detector<'a, G>) -> Self {
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
    fn next_row(
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
    /// The blocks of 64 pixels that hold levels (see [`RowOut`]).
    marks: Vec<u64>,
    /// How many pixels are above the threshold.
    above: usize,
    /// The blob being measured, as [`key`]s: first the flood's queue (the
    /// pixels before `head` have been expanded), then sorted into flooding
    /// order, then re-keyed by particle to measure them one at a time.
    blob: Vec<u64>,
    /// Splitting: per cell of the blob's bounding box, the region of its
    /// pixel once visited, else `NONE`.
    grid: Vec<u32>,
    regions: Vec<Region>,
    /// The automatic split rule: per region, its pixels so far and the sum
    /// of their levels (saturating), the "cap" above the level being
    /// flooded.
    caps: Vec<(u32, u32)>,
    /// Measuring: per region root, its particle's number in the blob.
    slot: Vec<u32>,
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
            grid: Vec::new(),
            regions: Vec::new(),
            caps: Vec::new(),
            slot: Vec::new(),
            noise: 0,
            split_noise: AUTO_SPLIT_NOISE,
            deferred: Vec::new(),
            deferred_marks: Vec::new(),
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
    /// row filter's loops ([`HighPass::next_row`], [`subtracted_row`],
    /// [`filter_row_narrow`]) are inlined here, so their vector code works
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

    /// The image's noise level after the high-pass filter: [`noise_sigma`]
    /// of the filtered values on the sample grid of [`noise_steps`]. It is
    /// computed ahead of the filter, so that blobs can be measured while the
    /// filter runs: the window sums of the sampled rows come from column
    /// sums carried from one sampled row's window to the next (rows between
    /// windows are skipped), at most one pass of additions in and one out
    /// over the image, and only the sampled pixels are divided.
    #[inline(always)]
    fn sample_noise(&self) -> u32 {
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
    /// ([`DetectionParameters::min_snr`]) or the automatic split rule.
    fn wants_noise(&self) -> bool {
        let p = self.parameters;
        p.min_snr > 0 || (p.split && p.split_depth.is_none())
    }

    /// Finds the blobs whose first pixel (in raster order) is at `*scan`
    /// or after and before `end`, and measures each; `*scan` follows. With
    /// `frontier`, the last row filtered so far, a blob that reaches it is
    /// left for later: the search stops at its first pixel and returns its
    /// row.
    fn find_blobs<const PIXELS: bool>(
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
    fn reserve_blob(&mut self, frontier: Option<usize>) {
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

    /// Steps 1 and 2 for the whole image at once: fills `levels` and
    /// `above` (see [`HighPass`]).
    #[cfg(test)]
    fn highpass_threshold(&mut self) {
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

    /// Collects the blob of `seed` (4-connected: pixels join by an edge)
    /// into `blob`, breadth first with `blob` itself as
    /// the queue, and returns its last pixel (the largest index). Pixels are
    /// taken out of `levels` while it runs (so none is taken twice) and put
    /// back at the end, for the measuring step to read.
    fn flood(&mut self, seed: usize) -> usize {
        let (width, height) = (self.width, self.height);
        self.blob.clear();
        self.take(seed);
        let mut head = 0;
        let mut last = seed;
        while head < self.blob.len() {
            let p = key_index(self.blob[head]);
            head += 1;
            last = last.max(p);
            let (x, y) = self.position(p);
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
        last
    }

    /// Moves pixel `q` into the blob if it is above the threshold and not
    /// taken yet.
    #[inline(always)]
    fn take(&mut self, q: usize) {
        let level = self.levels[q];
        if level != 0 {
            self.levels[q] = 0;
            // Within the capacity reserved in `run`: no reallocation.
            self.blob.push(key(level, q));
        }
    }

    /// Column and row of pixel index `p` (see [`Rows`]).
    #[inline(always)]
    fn position(&self, p: usize) -> (usize, usize) {
        self.rows.position(p)
    }

    /// Steps 3 and 4 for the blob in `blob`: splits it, measures each
    /// particle and keeps those that pass the filters. Returns false for a
    /// blob deferred to the end of the frame (its levels must stay).
    fn measure_blob<const PIXELS: bool>(&mut self, found: &mut Found) -> bool {
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
            return false;
        }
        self.split_and_measure::<PIXELS>(corner, size, threshold, found);
        true
    }

    /// Whether pixel `p` belongs to a deferred blob.
    #[inline(always)]
    fn is_deferred(&self, p: usize) -> bool {
        !self.deferred_marks.is_empty() && (self.deferred_marks[p >> 6] >> (p & 63)) & 1 == 1
    }

    /// Whether blobs with several maxima wait for the whole frame: with the
    /// automatic split rule.
    fn defers(&self) -> bool {
        self.parameters.split && self.parameters.split_depth.is_none()
    }

    /// The automatic split rule's blobs with several maxima, deferred by
    /// [`Detector::measure_blob`]: split with [`AUTO_SPLIT_NOISE`]; if
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
    fn split_deferred<const PIXELS: bool>(
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
        Ok(())
    }

    /// Floods deferred blob number `blob` from its seed, splits it and
    /// measures its particles (its levels stay).
    fn measure_deferred<const PIXELS: bool>(&mut self, blob: usize, found: &mut Found) {
        self.flood(self.deferred[blob]);
        let (corner, size) = self.blob_box();
        self.split_and_measure::<PIXELS>(corner, size, self.threshold_level(), found);
    }

    /// The threshold in levels (16-bit grey levels).
    fn threshold_level(&self) -> u32 {
        (u64::from(self.parameters.threshold) * G::LEVEL_SCALE).min(u64::from(u32::MAX)) as u32
    }

    /// The bounding box of the blob in `blob`: its corner (column, row) and
    /// size.
    fn blob_box(&self) -> ((usize, usize), (usize, usize)) {
        let (mut xmin, mut ymin, mut xmax, mut ymax) = (usize::MAX, usize::MAX, 0, 0);
        for &k in &self.blob {
            let (x, y) = self.position(key_index(k));
            xmin = xmin.min(x);
            ymin = ymin.min(y);
            xmax = xmax.max(x);
            ymax = ymax.max(y);
        }
        ((xmin, ymin), (xmax - xmin + 1, ymax - ymin + 1))
    }

    /// Whether the frame's particle images have structure of their own:
    /// its splits parted `parted` targets more than its blobs, of `targets`
    /// in all, and chance overlaps explain far fewer (see the module
    /// documentation, "Structured particle images").
    fn structured(&mut self, targets: usize, parted: usize) -> bool {
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
    fn split_and_measure<const PIXELS: bool>(
        &mut self,
        corner: (usize, usize),
        size: (usize, usize),
        threshold: u32,
        found: &mut Found,
    ) {
        let maxima = self.count_maxima(usize::MAX);
        self.split(corner, size, maxima);
        // Number the particles in flooding order, and re-key each pixel by
        // its particle: sorted, each particle's pixels are contiguous and
        // particles are measured one at a time, in that order.
        self.slot.clear();
        self.slot.resize(self.regions.len(), NONE);
        let mut particles = 0u32;
        for rank in 0..self.blob.len() {
            let p = key_index(self.blob[rank]);
            let (x, y) = self.position(p);
            let cell = (y - corner.1) * size.0 + (x - corner.0);
            let root = self.find(self.grid[cell]) as usize;
            if self.slot[root] == NONE {
                self.slot[root] = particles;
                particles += 1;
            }
            self.blob[rank] = (u64::from(self.slot[root]) << 32) | p as u64;
        }
        self.blob.sort_unstable();
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

    /// Step 4 for one particle, the pixels `range` of `blob`: its moments,
    /// and its target (with its pixels, when asked for) if it passes the
    /// filters.
    fn measure_particle<const PIXELS: bool>(
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
                (target.x, target.y) = centroid::gaussian_centre(&samples, (target.x, target.y));
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

    /// How many pixels of the blob would start a particle when it is
    /// flooded, counting up to `limit`: those with no neighbour that comes
    /// before them in flooding order (brighter, or as bright and earlier in
    /// raster order). Only the edge neighbours are compared (they are in
    /// the blob if above the threshold; a diagonal neighbour may be in
    /// another blob): left out, the count is at least the particles the
    /// split starts (which compares all 8 neighbours within the blob), so a
    /// count of 1 is still exact. Most blobs are single particles, and
    /// counting to 2 spares them the sort.
    fn count_maxima(&self, limit: usize) -> usize {
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
    fn first_at_border(&self, p: usize, level: u16, (x, y): (usize, usize)) -> bool {
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
    fn split(&mut self, corner: (usize, usize), size: (usize, usize), maxima: usize) {
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
        self.blob.sort_unstable();
        let (box_width, box_height) = size;
        let cells = box_width * box_height;
        // Exact reservations: these grow to the largest blob's needs and no
        // further.
        self.grid.clear();
        self.grid.reserve_exact(cells);
        self.grid.resize(cells, NONE);
        self.regions.clear();
        self.regions.reserve_exact(maxima);
        self.caps.clear();
        if auto {
            self.caps.reserve_exact(maxima);
        }
        self.slot.clear();
        self.slot.reserve_exact(maxima);
        for rank in 0..self.blob.len() {
            let k = self.blob[rank];
            let level = u32::from(key_level(k));
            let (x, y) = self.position(key_index(k));
            let (bx, by) = (x - corner.0, y - corner.1);
            // Visited neighbours (all at least as bright): their cells and
            // region roots. Most pixels see one region only and join it; a
            // saddle, where several meet, needs their keys.
            let (x0, x1) = (bx.saturating_sub(1), (bx + 2).min(box_width));
            let (y0, y1) = (by.saturating_sub(1), (by + 2).min(box_height));
            let mut cells = [(0usize, NONE); 8];
            let mut count = 0;
            let mut several = false;
            for ny in y0..y1 {
                for nx in x0..x1 {
                    let region = self.grid[ny * box_width + nx];
                    if region != NONE {
                        let root = self.find(region);
                        several |= count > 0 && root != cells[0].1;
                        cells[count] = (ny * box_width + nx, root);
                        count += 1;
                    }
                }
            }
            if count == 0 {
                // A local maximum: a new particle.
                self.grid[by * box_width + bx] = self.regions.len() as u32;
                self.regions.push(Region {
                    parent: self.regions.len() as u32,
                    peak: level,
                });
                if auto {
                    self.caps.push((1, level));
                }
                continue;
            }
            let mut brightest = cells[0].1;
            if several {
                let mut neighbours = [(u64::MAX, NONE); 8];
                for (slot, &(cell, root)) in neighbours.iter_mut().zip(&cells[..count]) {
                    let q =
                        (cell / box_width + corner.1) * self.width + cell % box_width + corner.0;
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
            // A saddle pixel goes to the particle of its brightest neighbour.
            let root = self.find(brightest);
            self.grid[by * box_width + bx] = root;
            if auto {
                let cap = &mut self.caps[root as usize];
                *cap = (cap.0 + 1, cap.1.saturating_add(level));
            }
        }
    }

    /// The automatic rule's noise floor in levels: [`AUTO_SPLIT_NOISE`]
    /// (or [`AUTO_SPLIT_NOISE_STRUCTURED`] in a structured frame) times the
    /// image's noise level.
    fn noise_depth(&self) -> u32 {
        (u64::from(self.noise) * self.split_noise / 10).min(u64::from(u32::MAX)) as u32
    }

    /// At a pixel of grey value `level` where several particles meet: a
    /// particle whose peak does not rise enough above it (`rule`) is noise
    /// on a neighbour, and is merged into the particle of the brightest
    /// neighbour that is significant (or, if none is, into the highest one).
    fn merge_insignificant(&mut self, neighbours: &[(u64, u32)], level: u32, rule: SplitRule) {
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
    fn find(&mut self, mut region: u32) -> u32 {
        while self.regions[region as usize].parent != region {
            let grandparent = self.regions[self.regions[region as usize].parent as usize].parent;
            self.regions[region as usize].parent = grandparent;
            region = grandparent;
        }
        region
    }

    /// Whether a particle's sum of grey is at least
    /// [`DetectionParameters::min_snr`] times the noise of a sum over its
    /// pixels: `sumg >= min_snr · sigma · sqrt(n)`, squared in integers.
    fn significant(&self, m: &Moments) -> bool {
        let k = u128::from(self.parameters.min_snr);
        let noise = u128::from(self.noise);
        let sumg = u128::from(m.sumg);
        sumg * sumg >= k * k * noise * noise * u128::from(m.n)
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

    /// The Gaussian centroid's samples ([`super::centroid`]) of the
    /// particle whose keys are `pixels`: its brightest pixel (the first in
    /// raster order of equal ones) and the four beside it, each relative to
    /// the peak's window mean (its level less the difference of the raw
    /// samples). A neighbour is usable if it is inside the image and the
    /// mask, and is not another particle's: with `whole` the particle is
    /// the whole blob, else its keys are sorted (`particle << 32 | index`).
    fn peak_samples(&self, pixels: &[u64], whole: bool) -> PeakSamples {
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

#[cfg(test)]
pub(crate) mod tests {
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

    /// The 32-bit row filter is the 64-bit one wherever it is used: on
    /// random rows and column sums within its range, both give the same
    /// levels (`highpass_matches_its_definition` reaches the 64-bit one only
    /// with windows too large to check pixel by pixel).
    #[test]
    fn the_narrow_row_filter_is_the_wide_one() {
        let mut rng = rng(12);
        for _ in 0..300 {
            let width = rng.random_range(1..80usize);
            let r = rng.random_range(1..12usize);
            let rows = rng.random_range(1..=(2 * r + 1)) as u64;
            let max: u16 = if rng.random_bool(0.5) { 255 } else { 4095 };
            let threshold = u64::from(rng.random_range(0..max / 4));
            let row: Vec<u16> = (0..width).map(|_| rng.random_range(0..=max)).collect();
            let sums: Vec<u32> = (0..width)
                .map(|_| rng.random_range(0..=rows as u32 * u32::from(max)))
                .collect();
            // The row starts at pixel `start` of a larger image: its
            // blocks' marks are the image's.
            let start = rng.random_range(0..200usize);
            let words = (start + width).div_ceil(64 * 64);
            let (mut wide, mut narrow) = (vec![0u16; width], vec![0u16; width]);
            let (mut marks_wide, mut marks_narrow) = (vec![0u64; words], vec![0u64; words]);
            let (mut above_wide, mut above_narrow) = (0, 0);
            let mut out = RowOut {
                levels: &mut wide,
                start,
                marks: &mut marks_wide,
                above: &mut above_wide,
            };
            filter_row(&row, &sums, r, rows, threshold, &mut out);
            let mut prefix = vec![0u32; width + 1];
            let mut out = RowOut {
                levels: &mut narrow,
                start,
                marks: &mut marks_narrow,
                above: &mut above_narrow,
            };
            filter_row_narrow(
                &row,
                &sums,
                &mut prefix,
                r,
                rows as u32,
                threshold as u32,
                &mut out,
            );
            assert_eq!(narrow, wide, "width {width}, r {r}, rows {rows}");
            assert_eq!(above_narrow, above_wide);
            assert_eq!(marks_narrow, marks_wide);
            // A block is marked exactly when it holds a level.
            for block in 0..words * 64 {
                let held = (block * 64..(block + 1) * 64)
                    .any(|p| p >= start && p < start + width && wide[p - start] != 0);
                let marked = marks_wide[block / 64] >> (block % 64) & 1 == 1;
                assert_eq!(marked, held, "block {block}");
            }
        }
    }

    /// Blobs are searched for while the filter is still running, a few
    /// rows behind it: a blob far taller than that gap (here 300 rows, and
    /// a second one beside it, and particles below) is still found whole,
    /// and once.
    #[test]
    fn a_blob_taller_than_the_filter_lead_is_found_whole() {
        let (width, height) = (40usize, 400usize);
        let mut pixels = vec![0u8; width * height];
        for y in 20..320 {
            for x in 10..13 {
                pixels[y * width + x] = 200;
            }
            // A second bar, starting lower and leaning right (two pixels
            // wide, so that its steps join by an edge), then a spot.
            if y >= 30 {
                pixels[y * width + 25 + (y - 30) / 100] = 150;
                pixels[y * width + 26 + (y - 30) / 100] = 150;
            }
        }
        for (x, y) in [(5, 350), (30, 380)] {
            pixels[y * width + x] = 120;
        }
        let image = GreyImage::from_u8(width as u32, height as u32, pixels).unwrap();
        let parameters = DetectionParameters {
            highpass_radius: 0,
            min_pixels: 1,
            max_pixels: 10_000,
            max_nx: 100,
            max_ny: 1000,
            split: false,
            ..DetectionParameters::default()
        };
        let targets = detect(&image, &parameters);
        let sizes: Vec<(u32, u32)> = targets.iter().map(|t| (t.n, t.ny)).collect();
        assert_eq!(
            sizes,
            [(900, 300), (580, 290), (1, 1), (1, 1)],
            "{targets:?}"
        );
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
            split_depth: Some(5),
            ..DetectionParameters::default()
        }
    }

    /// A `width` x `height` frame of Gaussian noise of `sigma` grey levels
    /// around `mean`, 8-bit, and its 16-bit copy (times 257).
    fn noise_frame(width: u32, height: u32, mean: f64, sigma: f64, seed: u64) -> [GreyImage; 2] {
        use rand_distr::{Distribution, Normal};
        let normal = Normal::new(mean, sigma).unwrap();
        let mut rng = rng(seed);
        let pixels: Vec<u8> = (0..width * height)
            .map(|_| normal.sample(&mut rng).round().clamp(0.0, 255.0) as u8)
            .collect();
        let wide: Vec<u16> = pixels.iter().map(|&v| u16::from(v) * 257).collect();
        [
            GreyImage::from_u8(width, height, pixels).unwrap(),
            GreyImage::from_u16(width, height, wide).unwrap(),
        ]
    }

    /// The noise level (grey levels) the detector estimates for `image`.
    fn estimated_noise(image: &GreyImage, parameters: &DetectionParameters) -> f64 {
        let (w, h) = (image.width() as usize, image.height() as usize);
        match image.pixels() {
            GreyPixels::Eight(p) => {
                let mut d = Detector::new(p, w, h, parameters);
                d.highpass_threshold();
                f64::from(d.noise) / 257.0
            }
            GreyPixels::Sixteen(p) => {
                let mut d = Detector::new(p, w, h, parameters);
                d.highpass_threshold();
                f64::from(d.noise) / 257.0
            }
        }
    }

    #[test]
    fn the_noise_level_is_estimated_after_the_filter() {
        // Gaussian noise of sigma around a constant: the filtered value
        // is the noise less its window mean, of standard deviation sigma
        // sqrt(1 + 1/c) (c = 21² pixels: sigma within 0.2%). The estimate
        // uses 8,192 samples of a 1024² frame; a quantile-based sigma from
        // N samples has a relative standard error of about 1.2/sqrt(N)
        // (1.3%), and rounding to whole grey levels adds 1/12 grey level²
        // of variance (at sigma 3, 0.5%): 6% is over 4 standard errors.
        for sigma in [3.0, 6.0, 20.0] {
            let [eight, sixteen] = noise_frame(1024, 1024, 100.0, sigma, 5);
            let parameters = DetectionParameters::default();
            let a = estimated_noise(&eight, &parameters);
            let b = estimated_noise(&sixteen, &parameters);
            assert!((a / sigma - 1.0).abs() < 0.06, "sigma {sigma}: {a}");
            // An 8-bit frame and its 16-bit copy have the same levels.
            assert_eq!(a, b, "sigma {sigma}");
            // Without the filter, the same (the mean is far from 0).
            let unfiltered = DetectionParameters {
                highpass_radius: 0,
                ..parameters.clone()
            };
            let c = estimated_noise(&eight, &unfiltered);
            assert!(
                (c / sigma - 1.0).abs() < 0.06,
                "sigma {sigma}, no filter: {c}"
            );
        }
    }

    #[test]
    fn pure_noise_gives_no_targets_by_default() {
        // The default threshold (10) at 3.3, 2 and 1.5 sigma of the noise:
        // 0.05%, 2.3% and 6.7% of the pixels are above it, in small
        // clusters. A cluster of n such pixels has a mean level of about
        // threshold + 0.4 sigma, so the signal-to-noise test (12 sigma
        // sqrt n) needs n >= 40 of them connected even at 1.5 sigma, which
        // pure noise so far below the percolation threshold (about 59% of
        // the pixels for 4-connected sites) does not make. Without the test,
        // every cluster of 2 or more pixels is a target. The 16-bit copy
        // with the threshold in its units (times 257) is the same test.
        for (sigma, seed) in [(3.0, 1), (5.0, 2), (6.67, 3)] {
            for (image, scale) in noise_frame(512, 512, 100.0, sigma, seed)
                .into_iter()
                .zip([1, 257])
            {
                let defaults = DetectionParameters {
                    threshold: 10 * scale,
                    ..DetectionParameters::default()
                };
                let with = detect(&image, &defaults);
                assert!(with.is_empty(), "sigma {sigma}: {} targets", with.len());
                let without = detect(
                    &image,
                    &DetectionParameters {
                        min_snr: 0,
                        ..defaults
                    },
                );
                if sigma > 4.0 {
                    assert!(without.len() > 100, "sigma {sigma}: {}", without.len());
                }
            }
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
            split_depth: Some(3),
            ..unfiltered()
        };
        assert_eq!(detect(&image(7, rows), &deep).len(), 2);
    }

    #[test]
    fn blobs_join_pixels_by_their_edges_only() {
        // Two 2x2 spots touching at a corner: two 4-connected blobs, as
        // OpenPTV's targ_rec finds, with either split rule (as one
        // 8-connected blob the dimmer spot's corner pixel would join the
        // brighter one, with no saddle between them).
        let rows: &[&[u8]] = &[
            &[0, 0, 0, 0, 0, 0],
            &[0, 50, 50, 0, 0, 0],
            &[0, 50, 50, 0, 0, 0],
            &[0, 0, 0, 60, 60, 0],
            &[0, 0, 0, 60, 60, 0],
            &[0, 0, 0, 0, 0, 0],
        ];
        for split_depth in [None, unfiltered().split_depth] {
            let found = detect(
                &image(6, rows),
                &DetectionParameters {
                    split_depth,
                    ..unfiltered()
                },
            );
            assert_eq!(found.len(), 2, "{split_depth:?}: {found:?}");
            assert_eq!((found[0].x, found[0].y), (2.0, 2.0));
            assert_eq!((found[1].x, found[1].y), (4.0, 4.0));
        }
    }

    #[test]
    fn the_automatic_rule_splits_particles_but_not_ripples_on_a_streak() {
        // A streak at 200 with a ripple rising 20 above a saddle at 180:
        // 20 is less than a fifth of the ripple's 190 above the threshold,
        // so one target (an absolute depth of 4 cuts it in two).
        let streak: &[&[u8]] = &[
            &[0, 0, 0, 0, 0, 0, 0],
            &[0, 150, 150, 150, 150, 150, 0],
            &[0, 200, 180, 200, 150, 100, 0],
            &[0, 150, 150, 150, 150, 150, 0],
            &[0, 0, 0, 0, 0, 0, 0],
        ];
        let auto = DetectionParameters {
            split_depth: None,
            ..unfiltered()
        };
        assert_eq!(detect(&image(7, streak), &auto).len(), 1);
        let absolute = DetectionParameters {
            split_depth: Some(4),
            ..unfiltered()
        };
        assert_eq!(detect(&image(7, streak), &absolute).len(), 2);
        // Two touching particles: the fainter (120) rises 95 above the
        // saddle (25), more than a fifth of its 110 above the threshold.
        let rows: &[&[u8]] = &[
            &[0, 0, 0, 0, 0, 0, 0, 0, 0],
            &[0, 20, 40, 20, 15, 30, 60, 30, 0],
            &[0, 40, 90, 40, 25, 50, 120, 50, 0],
            &[0, 20, 40, 20, 15, 30, 60, 30, 0],
            &[0, 0, 0, 0, 0, 0, 0, 0, 0],
        ];
        assert_eq!(detect(&image(9, rows), &auto).len(), 2);
    }

    #[test]
    fn a_blob_whole_at_the_lower_floor_may_part_at_the_higher_and_is_split_again() {
        // A blob (levels, noise level 10) that is one particle with the 3
        // sigma floor and two with 25 sigma. At 3 sigma the maxima X (400)
        // and X' (200) stay apart at their saddle (150); each then fails
        // the cap test alone where it meets the ridge of P1 (5000) and
        // merges into it. At 25 sigma X' merges into X first, and their
        // union passes the cap test at the ridge. So a structured frame
        // cannot keep the first split's target of every blob that came out
        // whole: only of those where no saddle kept particles apart
        // (`kept_apart`), which this one did.
        let (width, height) = (52usize, 3usize);
        let mut levels = vec![0u16; width * height];
        let mut set = |x: usize, y: usize, level: u16| levels[y * width + x] = level;
        (1..45).for_each(|x| set(x, 0, 140)); // X's shelf
        set(45, 0, 400); // X
        set(46, 0, 150); // the saddle of X and X'
        set(47, 0, 200); // X'
        (48..51).for_each(|x| set(x, 0, 130)); // X''s shelf
        set(1, 1, 140); // where X's shelf meets the ridge
        set(49, 1, 130); // where X''s shelf meets it
        (0..52).for_each(|x| set(x, 2, 1000)); // P1's ridge
        set(25, 2, 5000); // P1
        let pixels = vec![0u8; width * height];
        let parameters = DetectionParameters {
            threshold: 0,
            ..DetectionParameters::default()
        };
        let particles = |floor: u64| {
            let mut detector = Detector::new(&pixels[..], width, height, &parameters);
            detector.levels = levels.clone();
            detector.above = width * height;
            detector.noise = 10;
            detector.split_noise = floor;
            detector.reserve_blob(None);
            detector.flood(2 * width + 25); // P1
            let (corner, size) = detector.blob_box();
            let maxima = detector.count_maxima(usize::MAX);
            detector.split(corner, size, maxima);
            let mut roots: Vec<u32> = (0..detector.blob.len())
                .map(|i| {
                    let (x, y) = detector.position(key_index(detector.blob[i]));
                    let cell = (y - corner.1) * size.0 + (x - corner.0);
                    detector.find(detector.grid[cell])
                })
                .collect();
            roots.sort_unstable();
            roots.dedup();
            (roots.len(), detector.kept_apart)
        };
        assert_eq!(particles(AUTO_SPLIT_NOISE), (1, true));
        assert_eq!(particles(AUTO_SPLIT_NOISE_STRUCTURED).0, 2);
    }

    #[test]
    fn rings_stay_whole_where_overlaps_cannot_explain_their_maxima() {
        // 300 out-of-focus particle images, rings of radius 2.5..4.5 px
        // with two bumps on opposite sides (75 grey levels on the bumps, 45
        // between them, added to a background of 20 with noise of sigma 2),
        // spread 40 px apart: no two touch. Each ring's second bump rises
        // 30 grey levels (about 15 sigma) above the saddle, which the 3
        // sigma floor splits (as an absolute depth of 10 does: 600
        // targets) and the structured frame's 25 sigma does not.
        let (width, height) = (800usize, 600usize);
        let [noise, _] = noise_frame(width as u32, height as u32, 20.0, 2.0, 7);
        let GreyPixels::Eight(mut pixels) = noise.pixels().clone() else {
            unreachable!("an 8-bit frame")
        };
        let mut rings = 0;
        for cy in (20..height - 20).step_by(40) {
            for cx in (20..width - 20).step_by(40) {
                if rings == 300 {
                    break;
                }
                rings += 1;
                for y in cy - 5..=cy + 5 {
                    for x in cx - 5..=cx + 5 {
                        let (dx, dy) = (x as f64 - cx as f64, y as f64 - cy as f64);
                        let r = dx.hypot(dy);
                        if (2.5..=4.5).contains(&r) {
                            let cos2 = (dx * dx - dy * dy) / (r * r);
                            let level = 60.0 + 15.0 * cos2;
                            pixels[y * width + x] =
                                pixels[y * width + x].saturating_add(level as u8);
                        }
                    }
                }
            }
        }
        let image = GreyImage::from_u8(width as u32, height as u32, pixels).unwrap();
        let found = detect(&image, &DetectionParameters::default());
        assert_eq!(found.len(), rings, "the defaults");
        let split = detect(
            &image,
            &DetectionParameters {
                split_depth: Some(10),
                ..DetectionParameters::default()
            },
        );
        assert_eq!(split.len(), 2 * rings, "an absolute depth of 10");
    }

    #[test]
    fn the_automatic_rule_splits_only_at_a_cap_that_stands_out_of_the_noise() {
        // Noise of 5.93 grey levels: its lower quartile lies 0.6745 sigma =
        // 4.0 levels below its median, a whole number, so the estimate
        // (1.4826 times that spread) of 8-bit samples, whose quantiles are
        // whole levels, is 5.93 whatever pixels it samples (with noise of
        // 5 levels the spread, 3.37, rounds to 3 or 4 by the sample, an
        // estimate of 4.45 or 5.93). On it a particle peaking at
        // 240 and, joined to it at a saddle of 190, a second maximum of 212
        // with four more pixels brighter than the saddle. Its peak rises 22
        // above the saddle: more than 3 sigma (17.8) and than a fifth of
        // its 77 above the threshold (15.4), so only the cap test decides.
        // Flat (the four at 196, 192, 196, 196), the cap's volume above the
        // saddle is 22 + 6 + 2 + 6 + 6 = 42, less than 4 sigma sqrt(5) =
        // 53: one target. A full bump (205, 192, 205, 205): 69, two.
        for (cap, expected) in [(196u8, 1), (205, 2)] {
            for (image, scale) in noise_frame(512, 512, 100.0, 5.93, 7)
                .into_iter()
                .zip([1, 257])
            {
                let object: [[u8; 6]; 3] = [
                    [170, 190, 170, 150, cap, cap],
                    [190, 240, 190, 192, 208, cap],
                    [170, 190, 170, 150, 150, 150],
                ];
                let (width, height) = (image.width(), image.height());
                let mut pixels: Vec<u16> = match image.pixels() {
                    GreyPixels::Eight(p) => p.iter().map(|&v| u16::from(v)).collect(),
                    GreyPixels::Sixteen(p) => p.clone(),
                };
                for (r, row) in object.iter().enumerate() {
                    for (c, &v) in row.iter().enumerate() {
                        pixels[(200 + r) * width as usize + 300 + c] = u16::from(v) * scale;
                    }
                }
                let image = if scale == 1 {
                    let eight = pixels.iter().map(|&v| v as u8).collect();
                    GreyImage::from_u8(width, height, eight).unwrap()
                } else {
                    GreyImage::from_u16(width, height, pixels).unwrap()
                };
                let parameters = DetectionParameters {
                    threshold: 135 * scale,
                    highpass_radius: 0,
                    min_pixels: 1,
                    ..DetectionParameters::default()
                };
                let noise = estimated_noise(&image, &parameters);
                assert!((noise - 5.93).abs() < 0.3, "{noise}");
                let targets = detect(&image, &parameters);
                assert_eq!(
                    targets.len(),
                    expected,
                    "cap {cap}, scale {scale}: {targets:?}"
                );
            }
        }
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

    /// Counts the bytes each thread has allocated and not freed, and their
    /// peak, so that a test can measure the scratch of what it calls.
    pub(crate) mod counting {
        use std::alloc::{GlobalAlloc, Layout, System};
        use std::cell::Cell;

        pub struct Counting;

        thread_local! {
            static LIVE: Cell<isize> = const { Cell::new(0) };
            static PEAK: Cell<isize> = const { Cell::new(0) };
        }

        fn note(change: isize) {
            // Ignored while the thread's locals are being torn down.
            let _ = LIVE.try_with(|live| {
                let now = live.get().wrapping_add(change);
                live.set(now);
                let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
            });
        }

        // SAFETY: every call is forwarded to the system allocator as it is;
        // the counting touches only const-initialised thread locals, which
        // do not allocate.
        unsafe impl GlobalAlloc for Counting {
            unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
                let p = unsafe { System.alloc(layout) };
                if !p.is_null() {
                    note(layout.size() as isize);
                }
                p
            }
            unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
                let p = unsafe { System.alloc_zeroed(layout) };
                if !p.is_null() {
                    note(layout.size() as isize);
                }
                p
            }
            unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
                unsafe { System.dealloc(ptr, layout) };
                note(-(layout.size() as isize));
            }
            unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
                let p = unsafe { System.realloc(ptr, layout, new_size) };
                if !p.is_null() {
                    note(new_size as isize - layout.size() as isize);
                }
                p
            }
        }

        #[global_allocator]
        static COUNTING: Counting = Counting;

        /// The peak of this thread's allocated bytes while `f` runs, above
        /// what it held before, and `f`'s result.
        pub fn peak_of<T>(f: impl FnOnce() -> T) -> (usize, T) {
            let start = LIVE.with(Cell::get);
            PEAK.with(|peak| peak.set(start));
            let result = f();
            let peak = PEAK.with(Cell::get);
            ((peak - start).max(0) as usize, result)
        }
    }

    /// The worst case the module documents: bytes of scratch per image
    /// pixel, whatever the image holds (targets aside), with an absolute
    /// split depth and with the automatic rule (which defers the blobs it
    /// splits).
    const SCRATCH_BYTES_PER_PIXEL: usize = 20;
    const SCRATCH_BYTES_PER_PIXEL_AUTO: usize = 30;

    #[test]
    fn scratch_is_bounded_per_pixel_on_a_hostile_image() {
        // Every pixel above the threshold, all in one blob. Low noise (less
        // than the split depth) makes it one particle, too large to be a
        // target; strong noise makes a local maximum about every 9 pixels,
        // most of them particles. Both are the worst case for the flood and
        // the split; the second also for the targets, which are output, not
        // scratch, and are counted at their own size (40 bytes each, at most
        // twice that for the vector's spare capacity and the stable sort's
        // buffer).
        let (width, height) = (2048usize, 2048usize);
        let mut rng = rng(5);
        // An absolute depth splits at every maximum the noise makes. The
        // automatic rule scales its depth to the noise and keeps the blob
        // whole, but defers it to the end of the frame and floods it with
        // a region and a cap reserved for every one of its maxima all the
        // same: the worst case of the scratch.
        for (noise, split_depth, per_pixel) in [
            (3u16, Some(4), SCRATCH_BYTES_PER_PIXEL),
            (4095, Some(4), SCRATCH_BYTES_PER_PIXEL),
            (4095, None, SCRATCH_BYTES_PER_PIXEL_AUTO),
        ] {
            let pixels: Vec<u16> = (0..width * height)
                .map(|_| 40000 + rng.random_range(0..=noise))
                .collect();
            let image = GreyImage::from_u16(width as u32, height as u32, pixels).unwrap();
            let parameters = DetectionParameters {
                threshold: 100,
                highpass_radius: 0,
                min_pixels: 1,
                split_depth,
                ..DetectionParameters::default()
            };
            let (peak, targets) = counting::peak_of(|| detect(&image, &parameters));
            if noise == 3 {
                assert!(targets.is_empty(), "{} targets", targets.len());
            } else if split_depth.is_some() {
                assert!(targets.len() > width * height / 20, "{}", targets.len());
            }
            let output = 2 * targets.len() * std::mem::size_of::<Target>();
            eprintln!(
                "noise {noise}, split depth {split_depth:?}: peak {peak} bytes for {} targets",
                targets.len()
            );
            let bound = per_pixel * width * height + output;
            assert!(
                peak <= bound,
                "noise {noise}, {split_depth:?}: peak {peak} bytes, {:.1} a pixel besides {} targets; bound {bound}",
                (peak - output.min(peak)) as f64 / (width * height) as f64,
                targets.len()
            );
        }
    }

    /// A 40x30 8-bit frame: a dim ramp, with 3x3 spots of peak `peak` at
    /// `spots` (centre column, row).
    fn frame(spots: &[(usize, usize)], peak: u8) -> GreyImage {
        let (width, height) = (40usize, 30usize);
        let mut pixels: Vec<u8> = (0..width * height).map(|i| (i % width) as u8).collect();
        for &(x, y) in spots {
            for (dx, dy, v) in [(0, 0, peak), (1, 0, peak / 2), (0, 1, peak / 2)] {
                for (sx, sy) in [(1, 1), (-1, 1), (1, -1), (-1, -1)] {
                    let (px, py) = ((x as i64 + sx * dx) as usize, (y as i64 + sy * dy) as usize);
                    let p = &mut pixels[py * width + px];
                    *p = (*p).max(v);
                }
            }
        }
        GreyImage::from_u8(width as u32, height as u32, pixels).unwrap()
    }

    fn with_background(background: GreyImage) -> Preprocessing {
        Preprocessing {
            background: Some(background),
            mask: None,
        }
    }

    #[test]
    fn a_background_equal_to_the_frame_leaves_nothing() {
        let image = frame(&[(10, 10), (25, 20)], 200);
        let parameters = DetectionParameters::default();
        assert_eq!(detect(&image, &parameters).len(), 2);
        let found = detect_preprocessed(&image, &with_background(image.clone()), &parameters);
        assert_eq!(found, Ok(Vec::new()));
        // Without the filter too: the difference is 0 everywhere.
        let unfiltered = DetectionParameters {
            highpass_radius: 0,
            ..parameters
        };
        let found = detect_preprocessed(&image, &with_background(image.clone()), &unfiltered);
        assert_eq!(found, Ok(Vec::new()));
    }

    #[test]
    fn a_static_bright_object_in_the_background_disappears() {
        // The background holds a bright object at (30, 8); the frame holds it
        // and a particle. Subtracted, only the particle is left, where it is
        // found without the object. (The filter's window, 21 px across,
        // holds the particle and not the object, whose subtraction changes
        // nothing where the particle is.)
        let parameters = DetectionParameters {
            highpass_radius: 10,
            ..DetectionParameters::default()
        };
        let background = frame(&[(30, 8)], 250);
        let image = frame(&[(30, 8), (12, 20)], 250);
        let alone = detect(&frame(&[(12, 20)], 250), &parameters);
        assert_eq!(detect(&image, &parameters).len(), 2);
        let found = detect_preprocessed(&image, &with_background(background), &parameters).unwrap();
        assert_eq!(found.len(), 1, "{found:?}");
        assert!((found[0].x - alone[0].x).abs() < 1e-9 && (found[0].y - alone[0].y).abs() < 1e-9);
        assert_eq!((found[0].x.floor(), found[0].y.floor()), (12.0, 20.0));
    }

    #[test]
    fn masked_out_pixels_find_nothing() {
        let image = frame(&[(10, 10), (25, 20)], 200);
        // The mask hides the right half of the frame.
        let mask_image = GreyImage::from_u8(
            40,
            30,
            (0..40 * 30).map(|i| u8::from(i % 40 < 20)).collect(),
        )
        .unwrap();
        let preprocessing = Preprocessing {
            background: None,
            mask: Some(Mask::from_image(&mask_image)),
        };
        let found =
            detect_preprocessed(&image, &preprocessing, &DetectionParameters::default()).unwrap();
        assert_eq!(found.len(), 1, "{found:?}");
        assert!(found[0].x < 20.0);
    }

    #[test]
    fn a_background_or_mask_that_does_not_fit_is_an_error() {
        let image = frame(&[(10, 10)], 200);
        let parameters = DetectionParameters::default();
        let small = GreyImage::from_u8(39, 30, vec![0; 39 * 30]).unwrap();
        let error =
            detect_preprocessed(&image, &with_background(small.clone()), &parameters).unwrap_err();
        assert_eq!(
            error.to_string(),
            "the background is 39x30 pixels but the frame is 40x30; \
             use a background recorded with this camera"
        );
        let deep = GreyImage::from_u16(40, 30, vec![0; 40 * 30]).unwrap();
        let error = detect_preprocessed(&image, &with_background(deep), &parameters).unwrap_err();
        assert_eq!(
            error,
            PreprocessError::BackgroundDepth {
                bits: 16,
                expected_bits: 8
            }
        );
        let mask = Preprocessing {
            background: None,
            mask: Some(Mask::from_image(&small)),
        };
        let error = detect_preprocessed(&image, &mask, &parameters).unwrap_err();
        assert!(error
            .to_string()
            .starts_with("the mask is 39x30 pixels but the frame is 40x30"));
    }

    /// A `side` x `side` 8-bit checkerboard of 1-pixel squares, 255 where
    /// `x + y` is even.
    fn checkerboard(side: u32) -> GreyImage {
        let pixels = (0..side * side)
            .map(|p| {
                if (p % side + p / side) % 2 == 0 {
                    255
                } else {
                    0
                }
            })
            .collect();
        GreyImage::from_u8(side, side, pixels).unwrap()
    }

    #[test]
    fn the_target_limit_stops_detection_and_changes_nothing_below_it() {
        let hostile = DetectionParameters {
            threshold: 1,
            min_pixels: 1,
            min_snr: 0,
            ..DetectionParameters::default()
        };
        // Noise at a low threshold: many blobs with several maxima, which
        // the automatic rule defers to the end of the frame (and splits
        // again when the frame is structured), and with a split depth.
        let noisy = DetectionParameters {
            threshold: 8,
            min_snr: 0,
            ..DetectionParameters::default()
        };
        let deep = DetectionParameters {
            split_depth: Some(3),
            ..noisy.clone()
        };
        let [noise, _] = noise_frame(160, 120, 100.0, 20.0, 7);
        for (image, parameters) in [
            (checkerboard(64), &hostile),
            (noise.clone(), &noisy),
            (noise, &deep),
        ] {
            let all = detect(&image, parameters);
            let n = all.len();
            assert!(n > 100, "{n}");
            for limit in [n, n + 1, usize::MAX] {
                let within = detect_within(&image, &NO_PREPROCESSING, parameters, limit);
                assert_eq!(within.as_ref(), Ok(&all), "limit {limit}");
            }
            for limit in [n - 1, n / 2, 1, 0] {
                let error =
                    detect_within(&image, &NO_PREPROCESSING, parameters, limit).unwrap_err();
                assert_eq!(error, DetectError::TooManyTargets(TooManyTargets { limit }));
            }
        }
    }

    #[test]
    fn a_hostile_frame_stops_at_the_limit_without_its_targets() {
        // Every other pixel a target: 2 million of them, 80 MB of targets
        // (and as much again while their vector grows) without a limit.
        let image = checkerboard(2048);
        let parameters = DetectionParameters {
            threshold: 1,
            min_pixels: 1,
            min_snr: 0,
            ..DetectionParameters::default()
        };
        let pixels = 2048 * 2048;
        let (peak, found) =
            counting::peak_of(|| detect_within(&image, &NO_PREPROCESSING, &parameters, 10_000));
        assert_eq!(
            found,
            Err(DetectError::TooManyTargets(TooManyTargets {
                limit: 10_000
            }))
        );
        // The levels (2 bytes a pixel) and the rows' scratch before the
        // stop; the targets found, 10,001 of them, are 400 KB.
        assert!(peak < 3 * pixels, "{peak} bytes");
        let (peak, all) = counting::peak_of(|| detect(&image, &parameters));
        assert!(all.len() > 2_000_000 - 2 * 2048, "{}", all.len());
        assert!(peak > 20 * pixels, "{peak} bytes");
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
