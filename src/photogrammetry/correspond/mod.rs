//! Stereo correspondences: which particle images in 2..N cameras belong to
//! one particle, and where that particle is (design paper, section 6:
//! establishment of correspondences by epipolar geometry with three and
//! more cameras; 3D coordinates by spatial intersection, section 4.3).
//!
//! The search, for a frame of targets per camera:
//!
//! 1. Every target's ray into the object medium is traced once (Eq. 13-17).
//!    Targets of each camera go into a uniform grid (a spatial index, with
//!    the targets stored in cell order) for searches around a point, and,
//!    per camera pair, into a grid of thin sectors along the epipolar
//!    curves for the bands (`pencil`): no search scans all targets.
//! 2. **Seed pairs**, one stage each: camera pairs `(i, j)` chosen so that
//!    every set of three cameras contains one of them (the cameras split
//!    into two halves, all pairs within each half: 2 pairs for 4 cameras
//!    instead of 6). Each still unused target of camera i has its ray cut by
//!    the observation volume; the segment between the near and far points is
//!    projected into camera j as a bent curve (a parabola or polyline within
//!    a tenth of the tolerance of the true curve) and widened by the
//!    tolerance: the epipolar band. Its candidates come from an index of
//!    camera j's targets in thin sectors along the curves (`pencil`).
//!    The tolerance is the band's upper bound, not its width: a band wider
//!    than [`NARROWEST_BAND_PX`] is first probed on about a hundred seed
//!    targets spread over the image, whose best groups give the frame's
//!    image noise, and the search then runs in the band that noise needs
//!    (3.5 standard deviations of a true pair's epipolar distance, at
//!    least [`NARROWEST_BAND_PX`]; `Search::first_stage`). A wider band
//!    finds nothing true more, as no member may miss by more than 3 sigma,
//!    but its candidates grow with its width and their completions with
//!    its square. Where the frame's noise fills the band (a rough
//!    calibration), the band stays.
//! 3. **Completion.** Each candidate pair's rays meet (nearly) in a 3D
//!    point; its image in every other camera (on the first target's
//!    epipolar curve there) is searched within `COMPLETION_RADIUS` (3)
//!    band half-widths, and a target joins if its ray meets the pair's
//!    within the band. A camera with several such targets gives several
//!    candidate groups; members that do not fit together are dropped worst
//!    first.
//! 4. **Selection**, best first: larger groups before smaller (a fourth
//!    camera cuts the ambiguities the design paper's Table 2 counts by at
//!    least an order of magnitude), then by the rays' spread in pixels; each
//!    target is used at most once. The first stage's groups (each seed
//!    target's best) give the frame's image noise, from which the
//!    acceptance threshold follows (`Search::estimate_noise`, 2..3 sigma
//!    whatever the band): a member that misses by more is dropped and its
//!    group falls back to the smaller one (a quadruplet whose fourth ray
//!    misses becomes the triplet). Then targets are exchanged between
//!    accepted groups where that fits both better (near-coincident images).
//! 5. **Pairs**, when two cameras suffice (`min_cameras = 2`): among the
//!    targets still unused, a pair is accepted only when each target is the
//!    other's single candidate in its band.
//! 6. Every accepted group's point by least-squares intersection
//!    ([`intersect_from`](super::intersect::intersect_from)), with standard deviations and residuals; a group
//!    whose largest residual exceeds the acceptance is dropped.
//!
//! Memory grows linearly with the targets, and the work with the targets
//! times the (small) number of band candidates. The inputs are bounded by
//! what the physics and the machine allow: at most [`MAX_CAMERAS`]
//! cameras, at most one target per 2x2 pixels of a camera's sensor and
//! [`MAX_TARGETS_PER_CAMERA`] ([`max_targets`]), a
//! tolerance no wider than the sensor and a volume the cameras see
//! ([`Matcher::new`]).
//!
//! The files follow the seams of the method: `matcher.rs`, the
//! [`Matcher`] (preparation per calibration, seed pairs, the checks of a
//! frame); `grid.rs`, one camera's targets with their rays (step 1);
//! `epipolar.rs`, the epipolar curves through the walls and the
//! distance to them; `pencil.rs`, the band index; `search/`, steps 2 to 6.

mod epipolar;
mod grid;
mod matcher;
mod pencil;
mod search;

use nalgebra::{Point2, Point3, Vector3};
use serde::{Deserialize, Serialize};

use super::camera::{Camera, Ray, Sensor};
use super::intersect::ray_midpoint;
use super::volume::Volume;

pub use matcher::{Matcher, NARROWEST_BAND_PX};

/// The most cameras a rig may have: 16.
///
/// The method needs 2 cameras and gains little beyond 4 (the design
/// paper's Table 2: a fourth camera cuts the ambiguities by an order of
/// magnitude); rigs people build have 2..8 (the simulator's range). Twice
/// the largest leaves margin. Preparation grows with the square of the
/// cameras (an epipolar geometry per ordered pair, refraction tables per
/// camera) and every per-point answer with the cameras, so the limit also
/// bounds those: 16 cameras are 240 camera pairs.
pub const MAX_CAMERAS: usize = 16;

/// Default epipolar band half-width (px).
pub const DEFAULT_TOLERANCE_PX: f64 = 1.0;

/// Optional similarity criteria: a candidate's size and brightness must be
/// within these factors of the target it is matched with (where both are
/// known).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Similarity {
    /// Largest ratio of pixel counts (>= 1).
    pub max_size_ratio: f64,
    /// Largest ratio of grey-value sums (>= 1).
    pub max_brightness_ratio: f64,
}

/// How to match.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MatchingParameters {
    /// Half-width of the widest epipolar band, and the largest accepted
    /// residual of a particle's intersection (px). An upper bound: members
    /// are accepted only within 2..3 sigma of the image noise the frame
    /// shows, and a band wider than that noise needs is narrowed to it
    /// (see the module doc, step 2).
    pub tolerance: f64,
    /// The observation volume; `None` for the region all cameras look at
    /// (see [`default_volume`]).
    pub volume: Option<Volume>,
    /// The fewest cameras that must see a particle (2..N).
    pub min_cameras: usize,
    /// Similarity criteria, if any.
    pub similarity: Option<Similarity>,
}

impl Default for MatchingParameters {
    fn default() -> Self {
        MatchingParameters {
            tolerance: DEFAULT_TOLERANCE_PX,
            volume: None,
            min_cameras: 2,
            similarity: None,
        }
    }
}

/// Why matching cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MatchError {
    /// Fewer than two cameras.
    #[error("matching needs at least 2 cameras, the calibration has {0}")]
    TooFewCameras(usize),
    /// More than [`MAX_CAMERAS`] cameras.
    #[error(
        "matching takes at most {MAX_CAMERAS} cameras (MAX_CAMERAS), the calibration has {0}; \
         match a subset of the cameras"
    )]
    TooManyCameras(usize),
    /// A target list per camera is expected.
    #[error("got targets for {targets} cameras, but the calibration has {cameras}; give one target list per camera, in camera order")]
    CameraCount {
        /// Target lists given.
        targets: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// The tolerance must be positive and finite.
    #[error("the tolerance must be a positive number of pixels, got {0}")]
    Tolerance(f64),
    /// A tolerance wider than a camera's sensor: a band that covers the
    /// whole image selects nothing.
    #[error(
        "the tolerance of {} px is wider than the sensor of camera {camera} (its diagonal, \
         {diagonal:.0} px, is the limit): an epipolar band that wide covers the whole image; \
         give the image measurement's uncertainty, typically 0.2..2 px",
        readable(*.tolerance)
    )]
    ToleranceTooWide {
        /// The tolerance given (px).
        tolerance: f64,
        /// The camera (0-based) with the smallest sensor.
        camera: usize,
        /// Its sensor's diagonal (px).
        diagonal: f64,
    },
    /// No volume was given, and the cameras have no common view to take one
    /// from (see [`default_volume`]).
    #[error(
        "no observation volume was given, and the cameras have no common field of view to take \
         as one: their optical axes are parallel, or fewer than two of them reach the object \
         space; give the volume (--volume xmin,xmax,ymin,ymax,zmin,zmax, mm)"
    )]
    NoDefaultVolume,
    /// The volume is empty or not finite.
    #[error(
        "the observation volume is empty: every minimum must be below its maximum, got \
         x {}..{}, y {}..{}, z {}..{} mm",
        .0.min.x, .0.max.x, .0.min.y, .0.max.y, .0.min.z, .0.max.z
    )]
    EmptyVolume(Volume),
    /// A volume that reaches far beyond the region the cameras see.
    #[error(
        "the observation volume reaches {axis} = {} mm, beyond {VOLUME_REACH} times the region \
         the cameras see ({region}); give a volume around the particles, within {axis} \
         {low:.1}..{high:.1} mm, or none to use that region",
        readable(*.value)
    )]
    VolumeTooLarge {
        /// The axis: `x`, `y` or `z`.
        axis: char,
        /// The bound that reaches too far (mm).
        value: f64,
        /// The region the volume is compared with, described.
        region: String,
        /// The lowest bound allowed on this axis (mm).
        low: f64,
        /// The highest bound allowed on this axis (mm).
        high: f64,
    },
    /// A volume that no two cameras see.
    #[error(
        "no two cameras see the observation volume x {}..{}, y {}..{}, z {}..{} mm (the \
         region they see: {region}); give a volume inside their common field of view, or none \
         to use that region",
        .volume.min.x, .volume.max.x, .volume.min.y, .volume.max.y, .volume.min.z, .volume.max.z
    )]
    VolumeNotSeen {
        /// The volume given.
        volume: Volume,
        /// The region the cameras see, described.
        region: String,
    },
    /// More targets in one camera than its sensor can hold.
    #[error(
        "camera {camera} has {count} targets, more than the limit of {limit} for its sensor: \
         at most one particle image per 2x2 pixels, and at most {MAX_TARGETS_PER_CAMERA} per \
         camera (MAX_TARGETS_PER_CAMERA); give this camera's targets of one frame, or raise \
         the detection threshold"
    )]
    TooManyTargets {
        /// The camera (0-based).
        camera: usize,
        /// Its targets.
        count: usize,
        /// The limit, [`max_targets`] of its sensor.
        limit: usize,
    },
    /// `min_cameras` out of range.
    #[error("min_cameras must be between 2 and the number of cameras ({cameras}), got {min}")]
    MinCameras {
        /// The value given.
        min: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// A similarity ratio below 1.
    #[error("similarity ratios must be at least 1, got size {0} and brightness {1}")]
    Similarity(f64, f64),
    /// A target with a non-finite position.
    #[error("camera {camera}, target {index}: its position is not a finite number")]
    InvalidTarget {
        /// The camera.
        camera: usize,
        /// The target's index in its list.
        index: usize,
    },
    /// The search was stopped ([`Matcher::match_frame_until`]).
    #[error("matching {0}")]
    Cancelled(#[from] crate::photogrammetry::cancel::Cancelled),
}

/// A number for a message: as it is, or in exponent form when huge.
pub(crate) fn readable(value: f64) -> String {
    if value.abs() < 1e7 {
        format!("{value}")
    } else {
        format!("{value:e}")
    }
}

/// How many times the region the cameras see a volume's bounds may reach:
/// 100. A given volume is usually a little larger or smaller than that
/// region (the tank, the light sheet), never a hundred times: each
/// finite bound must lie within the region scaled 100 times about its
/// centre. Beyond that a volume is a typo or a placeholder (±1e300 mm
/// leaves the epipolar segments too long to sample, and found nothing).
pub const VOLUME_REACH: f64 = 100.0;

/// The most targets any camera may have in one frame, whatever its
/// sensor: 2^20 (1,048,576), what the machine allows.
///
/// Matching holds about 250 bytes per target (measured: 8 cameras x
/// 100,000 targets peaked at 213 MB, the parsed files included), so this
/// is about 256 MiB per camera and 4 GiB for [`MAX_CAMERAS`]. It is 0.25
/// particles per pixel of a 4 Mpx sensor, denser than any frame that can
/// be matched (PTV works to about 0.05 particles per pixel, iterative
/// methods to 0.1); larger sensors reach it only with frames that dense.
pub const MAX_TARGETS_PER_CAMERA: usize = 1 << 20;

/// The most targets a camera of this sensor can have in one frame:
/// one per 2x2 pixels, `ceil(width / 2) * ceil(height / 2)`, and at most
/// [`MAX_TARGETS_PER_CAMERA`].
///
/// A particle image is at least one pixel, and two particle images are
/// told apart only with a pixel between them. The detector's blobs are
/// 4-connected, as OpenPTV's, and pixels touching at a corner can be
/// separate targets: the bound holds for targets of at least 4 pixels
/// (OpenPTV experiments' usual `nnmin`), each blob being its own pixels;
/// smaller targets of a noise checkerboard (which the default significance
/// test, `min_snr`, leaves out) can exceed it, and such a frame is refused
/// ([`MatchError::TooManyTargets`]) rather than matched. A list with more
/// targets is not one frame of particles of this sensor. (Real frames are
/// far sparser: 0.005..0.05 particles per pixel.)
pub fn max_targets(sensor: &Sensor) -> usize {
    max_targets_of(sensor.width, sensor.height)
}

/// [`max_targets`] of an image of `width` x `height` pixels (a
/// calibration image's marks are bounded the same way).
pub fn max_targets_of(width: u32, height: u32) -> usize {
    let half = |side: u32| side.div_ceil(2) as usize;
    (half(width) * half(height)).min(MAX_TARGETS_PER_CAMERA)
}

/// A particle found in the frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Particle {
    /// Position (mm).
    pub position: Point3<f64>,
    /// Standard deviations of X, Y, Z from the intersection (mm).
    pub sigma: Vector3<f64>,
    /// Root mean square reprojection residual (px).
    pub rms_px: f64,
    /// Per camera, the index of its target, `None` where it has none.
    pub targets: Vec<Option<usize>>,
}

impl Particle {
    /// How many cameras see this particle.
    pub fn camera_count(&self) -> usize {
        self.targets.iter().filter(|t| t.is_some()).count()
    }
}

/// The region all cameras look at: a cube around the point nearest to the
/// cameras' optical axes (traced through their walls), whose half-size is
/// the smallest half-width of the cameras' fields of view at that distance.
/// `None` where there is no such point: fewer than two axes reach the
/// object space, or they are parallel.
pub fn default_volume(cameras: &[Camera]) -> Option<Volume> {
    let axes: Vec<Ray> = cameras
        .iter()
        .filter_map(|camera| {
            let sensor = camera.sensor();
            let centre = Point2::new(
                f64::from(sensor.width) / 2.0,
                f64::from(sensor.height) / 2.0,
            );
            camera.ray(centre).ok()
        })
        .collect();
    if axes.len() < 2 {
        return None;
    }
    let centre = ray_midpoint(axes.iter().copied())?;
    let half = cameras
        .iter()
        .map(|camera| {
            let sensor = camera.sensor();
            let half_sensor = f64::min(
                f64::from(sensor.width) * sensor.pixel_size_x,
                f64::from(sensor.height) * sensor.pixel_size_y,
            ) / 2.0;
            (centre - camera.position()).norm() * half_sensor / camera.parameters().interior.c
        })
        .fold(f64::INFINITY, f64::min);
    let extent = Vector3::repeat(half);
    Some(Volume {
        min: centre - extent,
        max: centre + extent,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::{self, RigSpec};
    use proptest::prelude::*;

    proptest! {
        /// The bound of `max_targets` holds for the detector on any image:
        /// random grey values (the densest maxima there are), no filters.
        #[test]
        fn the_detector_never_finds_more_than_max_targets(
            (width, height, pixels) in (1u32..40, 1u32..40).prop_flat_map(|(w, h)| {
                (Just(w), Just(h), prop::collection::vec(any::<u8>(), (w * h) as usize))
            }),
            split_depth in prop::option::of(0u16..3),
        ) {
            use crate::photogrammetry::{detect, DetectionParameters, GreyImage};
            let image = GreyImage::from_u8(width, height, pixels).unwrap();
            // 4-connected blobs: the bound holds from four pixels on.
            let parameters = DetectionParameters {
                threshold: 0,
                highpass_radius: 0,
                min_pixels: 4,
                max_pixels: u32::MAX,
                max_nx: u32::MAX,
                max_ny: u32::MAX,
                min_snr: 0,
                split_depth,
                ..DetectionParameters::default()
            };
            let sensor = Sensor { width, height, pixel_size_x: 0.01, pixel_size_y: 0.01 };
            let found = detect(&image, &parameters).len();
            prop_assert!(found <= max_targets(&sensor), "{found} > {}", max_targets(&sensor));
        }
    }

    #[test]
    fn max_targets_is_one_per_two_by_two_pixels() {
        let sensor = |width, height| Sensor {
            width,
            height,
            pixel_size_x: 0.01,
            pixel_size_y: 0.01,
        };
        assert_eq!(max_targets(&sensor(1280, 1024)), 327_680);
        assert_eq!(max_targets(&sensor(1, 1)), 1);
        assert_eq!(max_targets(&sensor(3, 5)), 6);
        // 2048 x 2048 px hold exactly the machine's limit; larger sensors
        // are capped by it.
        assert_eq!(max_targets(&sensor(2048, 2048)), MAX_TARGETS_PER_CAMERA);
        assert_eq!(max_targets(&sensor(2050, 2048)), MAX_TARGETS_PER_CAMERA);
        assert_eq!(
            max_targets(&sensor(2046, 2048)),
            MAX_TARGETS_PER_CAMERA - 1024
        );
        assert_eq!(max_targets(&sensor(8192, 8192)), MAX_TARGETS_PER_CAMERA);
    }

    #[test]
    fn default_volume_covers_the_simulated_volume() {
        // The simulator aims its cameras at the volume's centre, so their
        // axes meet there and the default volume must hold nearly all of it.
        let spec = RigSpec::convergent(4);
        let volume = default_volume(&spec.build().unwrap()).unwrap();
        assert!(
            (volume.centre() - spec.volume.centre()).norm() < 1e-6,
            "{volume:?}"
        );
        let points = simulate::particles(&spec.volume, 1000, &mut simulate::rng(18));
        let inside = points.iter().filter(|p| volume.contains(p)).count();
        assert!(inside >= 900, "{inside} of 1000 in {volume:?}");
    }
}
