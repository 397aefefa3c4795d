//! The pure photogrammetric core: synchronous, deterministic, no I/O.
//!
//! Implements the mathematical model of Maas, Gruen, Papantoniou (1993),
//! section 4: the collinearity condition with 16 parameters per camera
//! ([`camera`]), the multimedia geometry through plane-parallel walls
//! ([`media`]), least-squares spatial intersection ([`mod@intersect`]), the
//! particle images of a frame ([`target`]), and the simulator that provides
//! ground truth ([`simulate`]); and section 6.1's particle detection in grey
//! images ([`image`], [`mod@detect`], with the sub-pixel estimators of
//! [`centroid`]); correspondences ([`correspond`]); and
//! the frame pipeline that runs detection and correspondences on the images
//! of one time step ([`pipeline`]), and the image splitter that cuts one
//! sensor's image into the views of several cameras ([`splitter`]);
//! section 5's system calibration by resection on control points
//! ([`mod@calibrate`]); volume self-calibration from the particles
//! ([`selfcal`]); tracking in object space after the companion paper,
//! Malik, Dracos and Papantoniou (1993), Part II ([`track`]); and for dense
//! seeding, iterative particle reconstruction ([`ipr`]) and its scoring
//! against the truth ([`score`]). [`statistics`] holds the χ² quantile
//! their tests share; `levenberg_marquardt` the one damped least-squares
//! driver of the calibration's and the bundle adjustment.
//!
//! This module never imports the service's shell (no async runtime, web
//! framework, SQL or OpenAPI crates; ARCHITECTURE.md's invariant greps for
//! their names): inputs and outputs are plain structs and nalgebra types.

pub mod background;
pub mod calibrate;
pub mod camera;
pub mod cancel;
pub mod centroid;
pub mod correspond;
pub mod detect;
pub mod health;
pub mod image;
pub mod intersect;
pub mod ipr;
pub(crate) mod levenberg_marquardt;
pub mod media;
pub mod pipeline;
pub mod score;
pub mod selfcal;
pub mod simulate;
pub mod splitter;
pub mod statistics;
pub mod target;
pub mod track;
pub mod volume;

pub use background::{BackgroundBuilder, BackgroundError, BackgroundMode};
pub use camera::{
    check_camera_name, Camera, CameraParameters, Distortion, Exterior, Interior, ProjectionError,
    Ray, Sensor, MAX_CAMERA_NAME_LEN, MAX_SENSOR_PIXELS, MAX_SENSOR_SIDE,
};
pub use cancel::{Cancel, Cancelled, StopOnDrop};
pub use centroid::Centroid;
pub use detect::{
    detect, detect_cameras, detect_preprocessed, detect_within, DetectError, DetectionParameters,
    InvalidDetectionParameters, PreprocessError, Preprocessing, TooManyTargets,
};
pub use image::{BitDepth, GreyImage, GreyPixels, ImageError, Mask, SensorMismatch};
pub use intersect::{intersect, Intersection, IntersectionError, Observation};
pub use media::{Media, MediaGeometry, Wall};
pub use pipeline::{FrameDetection, FramePipeline, FrameResult, PipelineError};
pub use splitter::{Splitter, SplitterError, SplitterLayout};
pub use target::Target;
pub use volume::Volume;
