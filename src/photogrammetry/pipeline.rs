//! The frame pipeline: the images of all cameras at one time step to 3D
//! particles (design paper, section 6: detection, correspondences,
//! spatial intersection).
//!
//! 1. Every image is checked against its camera's sensor, so that targets
//!    are never measured in the wrong pixel grid.
//! 2. **Detection** (section 6.1, [`super::detect_cameras`]): the targets of each
//!    image, cameras in parallel, each with its own parameters (cameras see
//!    the light sheet at different brightness, so their thresholds differ),
//!    after its background and mask if it has any
//!    ([`FramePipeline::with_preprocessing`]).
//! 3. **Correspondences and intersection** (sections 6.2 and 4.3,
//!    [`Matcher`]): which targets of different cameras image one particle,
//!    and where that particle is.
//!
//! A [`FramePipeline`] is prepared once per calibration and parameters (the
//! matcher builds its refraction tables then) and processes any number of
//! frames; it holds no state between frames, so one pipeline can serve
//! several threads.
//!
//! [`FramePipeline::process`] takes all images at once and detects them in
//! parallel. Where memory matters more than one frame's latency (the
//! service's workers), a caller decodes and detects one camera at a time
//! ([`FramePipeline::detect_camera`]), keeping only its targets, and then
//! matches ([`FramePipeline::match_targets`]): at most one decoded image is
//! alive at a time. Both stop between cameras and in the matcher's loops
//! once a [`Cancel`] token fires.

use rayon::prelude::*;

use super::camera::Camera;
use super::cancel::{Cancel, Cancelled};
use super::correspond::{
    max_targets, MatchError, Matcher, MatchingParameters, Particle, MAX_TARGETS_PER_CAMERA,
};
use super::detect::{
    detect_within, DetectError, DetectionParameters, InvalidDetectionParameters, PreprocessError,
    Preprocessing,
};
use super::image::{GreyImage, SensorMismatch};
use super::target::Target;
use super::volume::Volume;

/// The detection parameters of a frame's cameras.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FrameDetection {
    /// The same parameters for every camera.
    AllCameras(DetectionParameters),
    /// One set per camera, in camera order.
    PerCamera(Vec<DetectionParameters>),
}

impl From<DetectionParameters> for FrameDetection {
    fn from(parameters: DetectionParameters) -> Self {
        FrameDetection::AllCameras(parameters)
    }
}

/// Why a pipeline cannot be prepared, or a frame not processed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PipelineError {
    /// Per-camera detection parameters whose count is not the cameras'.
    #[error(
        "got detection parameters for {given} cameras, but the calibration has {cameras}; \
         give one set per camera, in camera order, or one set for all"
    )]
    DetectionCount {
        /// Parameter sets given.
        given: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// Detection parameters that contradict each other.
    #[error("invalid detection parameters for camera {camera}")]
    Detection {
        /// The camera (0-based) whose parameters are invalid.
        camera: usize,
        /// What is wrong.
        #[source]
        source: InvalidDetectionParameters,
    },
    /// A frame whose image count is not the cameras'.
    #[error(
        "got {images} images, but the calibration has {cameras} cameras; \
         give one image per camera, in camera order"
    )]
    ImageCount {
        /// Images given.
        images: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// An image that does not fit its camera's sensor.
    #[error("the image of camera {camera} does not fit its sensor")]
    Sensor {
        /// The camera (0-based).
        camera: usize,
        /// The sizes that differ.
        #[source]
        source: SensorMismatch,
    },
    /// The matching parameters are invalid, or matching failed.
    #[error(transparent)]
    Matching(#[from] MatchError),
    /// A camera index beyond the calibration's cameras.
    #[error("camera {camera} does not exist; the calibration has {cameras} cameras")]
    NoCamera {
        /// The camera asked for (0-based).
        camera: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// Per-camera preprocessing whose count is not the cameras'.
    #[error(
        "got backgrounds/masks for {given} cameras, but the calibration has {cameras}; \
         give one per camera, in camera order"
    )]
    PreprocessingCount {
        /// Preprocessing sets given.
        given: usize,
        /// Cameras in the calibration.
        cameras: usize,
    },
    /// A background or mask that does not fit its camera's images.
    #[error("the background or mask of camera {camera} does not fit its images")]
    Preprocess {
        /// The camera (0-based).
        camera: usize,
        /// What does not fit.
        #[source]
        source: PreprocessError,
    },
    /// A camera's image with more targets than its sensor can hold
    /// ([`max_targets`]): detection stopped as soon as it passed the limit.
    #[error(
        "camera {camera}: detection found more than {limit} targets, the limit for its sensor \
         (at most one particle image per 2x2 pixels, and at most {MAX_TARGETS_PER_CAMERA} per \
         camera), and stopped; raise the detection threshold, min_pixels or min_snr so that \
         noise is not taken for particles"
    )]
    TooManyTargets {
        /// The camera (0-based).
        camera: usize,
        /// The limit, [`max_targets`] of its sensor.
        limit: usize,
    },
    /// The work was stopped before detection ended.
    #[error("detection {0}")]
    Cancelled(#[from] Cancelled),
}

/// Detects camera `camera`'s targets (of sensor `model`) within its
/// sensor's target limit, which the matcher would refuse anyway.
fn detect_limited(
    camera: usize,
    model: &Camera,
    image: &GreyImage,
    preprocessing: &Preprocessing,
    parameters: &DetectionParameters,
) -> Result<Vec<Target>, PipelineError> {
    let limit = max_targets(model.sensor());
    detect_within(image, preprocessing, parameters, limit).map_err(|error| match error {
        DetectError::Preprocess(source) => PipelineError::Preprocess { camera, source },
        DetectError::TooManyTargets(_) => PipelineError::TooManyTargets { camera, limit },
    })
}

/// What one frame gives.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameResult {
    /// Per camera, its targets, in the order [`super::detect()`] returns
    /// them; the particles' target indices refer to these lists.
    pub targets: Vec<Vec<Target>>,
    /// The particles found.
    pub particles: Vec<Particle>,
}

/// Detection and matching prepared for one calibration and one set of
/// parameters.
#[derive(Clone, Debug)]
pub struct FramePipeline {
    /// Per camera, its detection parameters.
    detection: Vec<DetectionParameters>,
    /// Per camera, its background and mask (none until
    /// [`FramePipeline::with_preprocessing`]).
    preprocessing: Vec<Preprocessing>,
    /// The prepared correspondence search, which holds the cameras.
    matcher: Matcher,
}

impl FramePipeline {
    /// Validates the parameters and prepares the cameras for matching.
    pub fn new(
        cameras: &[Camera],
        detection: &FrameDetection,
        matching: &MatchingParameters,
    ) -> Result<FramePipeline, PipelineError> {
        let detection = match detection {
            FrameDetection::AllCameras(parameters) => vec![parameters.clone(); cameras.len()],
            FrameDetection::PerCamera(list) if list.len() == cameras.len() => list.clone(),
            FrameDetection::PerCamera(list) => {
                return Err(PipelineError::DetectionCount {
                    given: list.len(),
                    cameras: cameras.len(),
                })
            }
        };
        for (camera, parameters) in detection.iter().enumerate() {
            parameters
                .validate()
                .map_err(|source| PipelineError::Detection { camera, source })?;
        }
        let matcher = Matcher::new(cameras, matching)?;
        let preprocessing = vec![Preprocessing::default(); detection.len()];
        Ok(FramePipeline {
            detection,
            preprocessing,
            matcher,
        })
    }

    /// The pipeline with a background and mask per camera (camera order),
    /// each checked against its camera's sensor; [`FramePipeline::process`]
    /// and [`FramePipeline::detect_camera`] apply them.
    pub fn with_preprocessing(
        mut self,
        per_camera: Vec<Preprocessing>,
    ) -> Result<FramePipeline, PipelineError> {
        let cameras = self.cameras();
        if per_camera.len() != cameras.len() {
            return Err(PipelineError::PreprocessingCount {
                given: per_camera.len(),
                cameras: cameras.len(),
            });
        }
        for (camera, (preprocessing, model)) in per_camera.iter().zip(cameras).enumerate() {
            let sensor = model.sensor();
            preprocessing
                .check_size(sensor.width, sensor.height)
                .map_err(|source| PipelineError::Preprocess { camera, source })?;
        }
        self.preprocessing = per_camera;
        Ok(self)
    }

    /// Per camera, its background and mask.
    pub fn preprocessing(&self) -> &[Preprocessing] {
        &self.preprocessing
    }

    /// The cameras (with the matcher's refraction tables).
    pub fn cameras(&self) -> &[Camera] {
        self.matcher.cameras()
    }

    /// The observation volume in use.
    pub fn volume(&self) -> &Volume {
        self.matcher.volume()
    }

    /// Per camera, its detection parameters.
    pub fn detection(&self) -> &[DetectionParameters] {
        &self.detection
    }

    /// The prepared correspondence search, for frames whose targets were
    /// detected elsewhere.
    pub fn matcher(&self) -> &Matcher {
        &self.matcher
    }

    /// Detects camera `camera`'s targets in its image, checked against its
    /// sensor first. With [`FramePipeline::match_targets`], a frame one
    /// camera at a time.
    pub fn detect_camera(
        &self,
        camera: usize,
        image: &GreyImage,
    ) -> Result<Vec<Target>, PipelineError> {
        let cameras = self.cameras();
        let model = cameras.get(camera).ok_or(PipelineError::NoCamera {
            camera,
            cameras: cameras.len(),
        })?;
        image
            .check_sensor(model.sensor())
            .map_err(|source| PipelineError::Sensor { camera, source })?;
        detect_limited(
            camera,
            model,
            image,
            &self.preprocessing[camera],
            &self.detection[camera],
        )
    }

    /// Matches a frame's targets, `targets[c]` camera c's (as
    /// [`FramePipeline::detect_camera`] gave them), stopping with
    /// [`MatchError::Cancelled`] once `cancel` fires.
    pub fn match_targets(
        &self,
        targets: Vec<Vec<Target>>,
        cancel: &Cancel,
    ) -> Result<FrameResult, PipelineError> {
        let particles = self.matcher.match_frame_until(&targets, cancel)?;
        Ok(FrameResult { targets, particles })
    }

    /// Processes one frame: `images[c]` is camera c's image.
    pub fn process(&self, images: &[GreyImage]) -> Result<FrameResult, PipelineError> {
        let cameras = self.cameras();
        if images.len() != cameras.len() {
            return Err(PipelineError::ImageCount {
                images: images.len(),
                cameras: cameras.len(),
            });
        }
        for (camera, (image, model)) in images.iter().zip(cameras).enumerate() {
            image
                .check_sensor(model.sensor())
                .map_err(|source| PipelineError::Sensor { camera, source })?;
        }
        let targets = images
            .par_iter()
            .zip(&self.detection)
            .zip(&self.preprocessing)
            .zip(cameras)
            .enumerate()
            .map(|(camera, (((image, parameters), preprocessing), model))| {
                detect_limited(camera, model, image, preprocessing, parameters)
            })
            .collect::<Result<Vec<_>, _>>()?;
        let particles = self.matcher.match_frame(&targets)?;
        Ok(FrameResult { targets, particles })
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Point3;

    use super::*;
    use crate::photogrammetry::simulate::{self, RenderSpec, RigSpec};

    /// A 4-camera rig and its matching parameters for the whole simulated
    /// volume.
    fn rig() -> (Vec<Camera>, MatchingParameters) {
        let spec = RigSpec::convergent(4);
        let cameras = spec.build().unwrap();
        let matching = MatchingParameters {
            volume: Some(spec.volume),
            ..MatchingParameters::default()
        };
        (cameras, matching)
    }

    fn images(cameras: &[Camera], points: &[Point3<f64>], seed: u64) -> Vec<GreyImage> {
        simulate::render_frame(
            cameras,
            points,
            &RenderSpec::eight_bit(2.5),
            &mut simulate::rng(seed),
        )
        .into_iter()
        .map(|rendered| rendered.image)
        .collect()
    }

    #[test]
    fn rendered_frame_gives_its_particles() {
        let (cameras, matching) = rig();
        let volume = matching.volume.unwrap();
        let points = simulate::particles(&volume, 300, &mut simulate::rng(11));
        let pipeline =
            FramePipeline::new(&cameras, &DetectionParameters::default().into(), &matching)
                .unwrap();
        let result = pipeline.process(&images(&cameras, &points, 12)).unwrap();
        assert_eq!(result.targets.len(), 4);
        // A pixel spans about 0.15 mm in object space here (600 mm away,
        // 12 um pixels, c near 49 mm); isolated particles are detected to a
        // few hundredths of a pixel, so a third of a pixel, 0.05 mm, leaves
        // out only particles whose image overlaps another's in some camera.
        let error = |particle: &Particle| {
            points
                .iter()
                .map(|p| (p - particle.position).norm())
                .fold(f64::INFINITY, f64::min)
        };
        let close = result.particles.iter().filter(|p| error(p) < 0.05).count();
        assert!(
            close >= 294 && result.particles.len() - close <= 3,
            "{close} of {} particles within 0.05 mm of one of 300",
            result.particles.len()
        );
        for particle in &result.particles {
            for (camera, target) in particle.targets.iter().enumerate() {
                assert!(target.map_or(true, |t| t < result.targets[camera].len()));
            }
        }
    }

    #[test]
    fn per_camera_parameters_are_used_per_camera() {
        let (cameras, matching) = rig();
        let points = simulate::particles(&matching.volume.unwrap(), 50, &mut simulate::rng(5));
        let blind = DetectionParameters {
            threshold: u16::MAX,
            ..DetectionParameters::default()
        };
        let mut detection = vec![DetectionParameters::default(); 4];
        detection[2] = blind;
        let pipeline =
            FramePipeline::new(&cameras, &FrameDetection::PerCamera(detection), &matching).unwrap();
        let result = pipeline.process(&images(&cameras, &points, 6)).unwrap();
        assert!(result.targets[2].is_empty());
        assert!(result.targets[0].len() >= 45);
        assert!(result
            .particles
            .iter()
            .all(|p| p.targets[2].is_none() && p.camera_count() >= 2));
        assert!(result.particles.len() >= 40, "{}", result.particles.len());
    }

    #[test]
    fn camera_by_camera_gives_what_process_gives() {
        let (cameras, matching) = rig();
        let points = simulate::particles(&matching.volume.unwrap(), 200, &mut simulate::rng(3));
        let pipeline =
            FramePipeline::new(&cameras, &DetectionParameters::default().into(), &matching)
                .unwrap();
        let frame = images(&cameras, &points, 4);
        let whole = pipeline.process(&frame).unwrap();
        let targets = frame
            .iter()
            .enumerate()
            .map(|(camera, image)| pipeline.detect_camera(camera, image).unwrap())
            .collect();
        let by_camera = pipeline.match_targets(targets, &Cancel::new()).unwrap();
        assert_eq!(by_camera, whole);
        assert!(matches!(
            pipeline.detect_camera(4, &frame[0]),
            Err(PipelineError::NoCamera {
                camera: 4,
                cameras: 4
            })
        ));
        let stopped = Cancel::new();
        stopped.stop();
        assert_eq!(
            pipeline.match_targets(whole.targets, &stopped),
            Err(PipelineError::Matching(MatchError::Cancelled(
                Cancelled::Stopped
            )))
        );
    }

    #[test]
    fn matching_stops_at_the_deadline() {
        // 20,000 particles take a few hundred ms to match here; a 5 ms
        // limit stops the search in its outer loops, long before its end.
        let (cameras, matching) = rig();
        let points = simulate::particles(&matching.volume.unwrap(), 20_000, &mut simulate::rng(8));
        let frame = simulate::target_frame(&cameras, &points, 0.1, 0.0, &mut simulate::rng(9));
        let pipeline =
            FramePipeline::new(&cameras, &DetectionParameters::default().into(), &matching)
                .unwrap();
        let started = std::time::Instant::now();
        let full = pipeline
            .match_targets(frame.targets.clone(), &Cancel::new())
            .unwrap();
        let full_time = started.elapsed();
        assert!(full.particles.len() > 19_000);
        let limit = std::time::Duration::from_millis(5);
        let started = std::time::Instant::now();
        let error = pipeline
            .match_targets(frame.targets, &Cancel::with_limit(limit))
            .unwrap_err();
        let stopped_after = started.elapsed();
        assert_eq!(
            error,
            PipelineError::Matching(MatchError::Cancelled(Cancelled::TimedOut(limit)))
        );
        assert!(
            stopped_after < full_time / 4,
            "stopped after {stopped_after:?}, the whole search takes {full_time:?}"
        );
    }

    #[test]
    fn empty_images_give_no_particles() {
        let (cameras, matching) = rig();
        let pipeline =
            FramePipeline::new(&cameras, &DetectionParameters::default().into(), &matching)
                .unwrap();
        let result = pipeline.process(&images(&cameras, &[], 1)).unwrap();
        assert!(result.particles.is_empty());
        assert_eq!(result.targets, vec![Vec::<Target>::new(); 4]);
    }

    #[test]
    fn backgrounds_are_applied_per_camera_and_checked_against_the_sensor() {
        let (cameras, matching) = rig();
        let volume = matching.volume.unwrap();
        let points = simulate::particles(&volume, 100, &mut simulate::rng(21));
        let frame = images(&cameras, &points, 22);
        let pipeline =
            FramePipeline::new(&cameras, &DetectionParameters::default().into(), &matching)
                .unwrap();
        // Camera 1's background is its frame: it finds nothing; the others
        // find what they find without one.
        let mut per_camera = vec![Preprocessing::default(); 4];
        per_camera[1].background = Some(frame[1].clone());
        let plain = pipeline.process(&frame).unwrap();
        let pipeline = pipeline.with_preprocessing(per_camera.clone()).unwrap();
        let result = pipeline.process(&frame).unwrap();
        assert!(result.targets[1].is_empty());
        assert!(!plain.targets[1].is_empty());
        for camera in [0, 2, 3] {
            assert_eq!(result.targets[camera], plain.targets[camera]);
        }
        assert_eq!(pipeline.detect_camera(1, &frame[1]), Ok(Vec::new()));
        // Wrong count, wrong size.
        let error = pipeline
            .clone()
            .with_preprocessing(per_camera[..3].to_vec());
        assert!(matches!(
            error,
            Err(PipelineError::PreprocessingCount {
                given: 3,
                cameras: 4
            })
        ));
        per_camera[2].background = Some(GreyImage::from_u8(3, 3, vec![0; 9]).unwrap());
        let error = pipeline.with_preprocessing(per_camera).unwrap_err();
        assert!(
            matches!(
                error,
                PipelineError::Preprocess {
                    camera: 2,
                    source: PreprocessError::BackgroundSize { width: 3, .. }
                }
            ),
            "{error:?}"
        );
    }

    #[test]
    fn frames_that_do_not_fit_are_refused() {
        let (cameras, matching) = rig();
        let pipeline =
            FramePipeline::new(&cameras, &DetectionParameters::default().into(), &matching)
                .unwrap();
        let mut frame = images(&cameras, &[], 1);
        frame.pop();
        assert_eq!(
            pipeline.process(&frame).unwrap_err(),
            PipelineError::ImageCount {
                images: 3,
                cameras: 4
            }
        );
        frame.push(GreyImage::from_u8(1280, 1000, vec![0; 1_280_000]).unwrap());
        let error = pipeline.process(&frame).unwrap_err();
        assert!(
            matches!(error, PipelineError::Sensor { camera: 3, .. }),
            "{error:?}"
        );
    }

    #[test]
    fn invalid_parameters_are_refused() {
        let (cameras, matching) = rig();
        let crossed = DetectionParameters {
            min_pixels: 10,
            max_pixels: 5,
            ..DetectionParameters::default()
        };
        let mut per_camera = vec![DetectionParameters::default(); 4];
        per_camera[1] = crossed.clone();
        let error = FramePipeline::new(&cameras, &FrameDetection::PerCamera(per_camera), &matching)
            .unwrap_err();
        assert!(
            matches!(&error, PipelineError::Detection { camera: 1, source } if source.field == "min_pixels"),
            "{error:?}"
        );
        let error = FramePipeline::new(
            &cameras,
            &FrameDetection::PerCamera(vec![DetectionParameters::default(); 3]),
            &matching,
        )
        .unwrap_err();
        assert_eq!(
            error,
            PipelineError::DetectionCount {
                given: 3,
                cameras: 4
            }
        );
        let negative = MatchingParameters {
            tolerance: -1.0,
            ..matching
        };
        let error = FramePipeline::new(&cameras, &DetectionParameters::default().into(), &negative)
            .unwrap_err();
        assert_eq!(error, PipelineError::Matching(MatchError::Tolerance(-1.0)));
    }
}
