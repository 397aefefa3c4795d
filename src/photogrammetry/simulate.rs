//! Synthetic experiments: the ground truth for tests and benchmarks.
//!
//! A rig of 2..8 cameras looks at an observation volume inside a water tank
//! through the tank's walls (or, for air experiments, at a volume in air).
//! Particles are drawn uniformly in the volume, projected exactly with the
//! camera model, and their image coordinates disturbed by Gaussian noise of a
//! chosen standard deviation. Everything is seeded, so a test sees the same
//! experiment every run.
//!
//! For the detector (section 6.1) the simulator also renders camera images
//! ([`render`], [`render_frame`]): each particle is a Gaussian spot of a
//! chosen diameter, integrated over the pixel area, on a sloping background,
//! with photon (Poisson) and read (Gaussian) noise, quantised to 8 or 16
//! bits. The exact image coordinates of every particle come back as ground
//! truth. [`render_scene`] puts the particles in front of a
//! [`StructuredBackground`] (glare streaks, bright static objects,
//! vignetting, hot pixels, an illumination drift over frames; the
//! `background` submodule): what real recordings add, and what the
//! detector's high-pass filter (section 6.1) or a background subtraction
//! must remove.
//!
//! For tracking, the `flow` submodule moves particles through analytic
//! flows (a Burgers vortex, a Taylor-Green vortex, uniform shear) frame by
//! frame, with their exact velocities and accelerations ([`Flow`],
//! [`Seeding`]).

use nalgebra::{Matrix3, Point2, Point3, Vector2, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal, Poisson};

use super::calibrate::{ControlPoint, MarkObservation};
use super::camera::{
    rotation_angles, Camera, CameraParameters, Distortion, Exterior, Interior, Sensor,
};
use super::correspond::Particle;
use super::image::{BitDepth, GreyImage};
use super::intersect::Observation;
use super::media::{Media, MediaGeometry, Wall};
use super::target::Target;
use super::volume::Volume;

mod background;
pub mod flow;
pub mod wand;
pub use background::{BackgroundField, StructuredBackground};
pub use flow::{Flow, FlowError, FlowKind, Seeding, Tracer, TracerState};

/// A box-shaped water tank centred on the origin.
#[derive(Clone, Debug, PartialEq)]
pub struct Tank {
    /// Distance from the origin to the water-side surface of the side walls
    /// normal to X and to Z (mm).
    pub half_width: Vector2<f64>,
    /// The walls, from the water outward.
    pub walls: Vec<Wall>,
    /// Index outside the tank.
    pub n_air: f64,
    /// Index of the water.
    pub n_object: f64,
}

impl Tank {
    /// Water behind a 10 mm glass wall, water-side surfaces 100 mm from the centre.
    pub fn glass_walled() -> Tank {
        Tank {
            half_width: Vector2::new(100.0, 100.0),
            walls: vec![Wall {
                n: 1.49,
                thickness: 10.0,
            }],
            n_air: 1.0,
            n_object: 1.333,
        }
    }

    /// The media of a camera at `position`: it looks through the side wall
    /// whose outward normal best matches its direction from the centre.
    pub fn media_for(&self, position: &Vector3<f64>) -> Media {
        let glass_vector = if position.x.abs() > position.z.abs() {
            Vector3::new(self.half_width.x * position.x.signum(), 0.0, 0.0)
        } else {
            Vector3::new(0.0, 0.0, self.half_width.y * position.z.signum())
        };
        Media {
            n_air: self.n_air,
            walls: self.walls.clone(),
            n_object: self.n_object,
            glass_vector,
        }
    }
}

/// How to build a synthetic rig.
#[derive(Clone, Debug, PartialEq)]
pub struct RigSpec {
    /// Per camera: azimuth about the vertical Y axis, 0 = on the +Z axis (rad).
    pub azimuths: Vec<f64>,
    /// Per camera: elevation above the X-Z plane (rad).
    pub elevations: Vec<f64>,
    /// Distance of every projective centre from the volume's centre (mm).
    pub distance: f64,
    /// The sensor of every camera.
    pub sensor: Sensor,
    /// Principal point (mm) of every camera.
    pub principal_point: Vector2<f64>,
    /// Lens distortion and affine terms of every camera.
    pub distortion: Distortion,
    /// The observation volume, which the cameras look at and fill.
    pub volume: Volume,
    /// The tank, or `None` for an experiment in air.
    pub tank: Option<Tank>,
}

impl RigSpec {
    /// `cameras` cameras on one side of a glass-walled tank, spread over
    /// 80 degrees of azimuth and alternating 15 degrees above and below the
    /// volume, 600 mm away, with 1280x1024 sensors of 12 um pixels: a
    /// typical convergent PTV set-up.
    pub fn convergent(cameras: usize) -> RigSpec {
        let spread = 80f64.to_radians();
        let azimuths = (0..cameras)
            .map(|k| {
                if cameras == 1 {
                    0.0
                } else {
                    spread * (k as f64 / (cameras - 1) as f64 - 0.5)
                }
            })
            .collect();
        let elevations = (0..cameras)
            .map(|k| if k % 2 == 0 { 15f64 } else { -15f64 }.to_radians())
            .collect();
        RigSpec {
            azimuths,
            elevations,
            distance: 600.0,
            sensor: Sensor {
                width: 1280,
                height: 1024,
                pixel_size_x: 0.012,
                pixel_size_y: 0.012,
            },
            principal_point: Vector2::zeros(),
            distortion: Distortion::default(),
            volume: Volume {
                min: Point3::new(-40.0, -40.0, -20.0),
                max: Point3::new(40.0, 40.0, 20.0),
            },
            tank: Some(Tank::glass_walled()),
        }
    }

    /// The convergent rig 250 mm from a 160 x 160 x 140 mm calibration
    /// volume: a deep target seen at close range, so that a single camera's
    /// resection can tell its principal distance from its distance.
    pub fn calibration(cameras: usize) -> RigSpec {
        RigSpec {
            distance: 250.0,
            volume: Volume {
                min: Point3::new(-80.0, -80.0, -70.0),
                max: Point3::new(80.0, 80.0, 70.0),
            },
            ..RigSpec::convergent(cameras)
        }
    }

    /// Builds the cameras: each looks at the volume's centre (through its
    /// wall: the refracted ray of the image centre passes it), x axis
    /// horizontal, with a principal distance that lets the volume fill about
    /// 80% of the sensor's shorter side
    /// (refraction at the walls magnifies it a little more; every point of
    /// the box still images onto every sensor).
    pub fn build(&self) -> Result<Vec<Camera>, super::camera::InvalidCamera> {
        let centre = self.volume.centre();
        let half_sensor = f64::min(
            f64::from(self.sensor.width) * self.sensor.pixel_size_x,
            f64::from(self.sensor.height) * self.sensor.pixel_size_y,
        ) / 2.0;
        let half_angle = (self.volume.radius() / self.distance).asin();
        let c = 0.8 * half_sensor / half_angle.tan();
        self.azimuths
            .iter()
            .zip(&self.elevations)
            .enumerate()
            .map(|(k, (&azimuth, &elevation))| {
                let towards_camera = Vector3::new(
                    azimuth.sin() * elevation.cos(),
                    elevation.sin(),
                    azimuth.cos() * elevation.cos(),
                );
                let position = centre.coords + towards_camera * self.distance;
                let media = match &self.tank {
                    Some(tank) => tank.media_for(&position),
                    None => Media::air(),
                };
                // Aimed as in a lab: along the ray that, refracted by the
                // wall, reaches the volume's centre.
                let aim = match MediaGeometry::new(&media, &position)? {
                    Some(geometry) => geometry
                        .air_direction(&Point3::from(position), &centre)
                        .map_or(-towards_camera, |d| d),
                    None => -towards_camera,
                };
                let (omega, phi, kappa) = rotation_angles(&look_at(&-aim));
                Camera::new(CameraParameters {
                    name: format!("cam{}", k + 1),
                    sensor: self.sensor.clone(),
                    exterior: Exterior {
                        position,
                        omega,
                        phi,
                        kappa,
                    },
                    interior: Interior {
                        c,
                        xh: self.principal_point.x,
                        yh: self.principal_point.y,
                    },
                    distortion: self.distortion.clone(),
                    media,
                })
            })
            .collect()
    }
}

/// The rotation of a camera whose axis points along `-towards_camera`, with
/// its x axis horizontal (perpendicular to world Y).
fn look_at(towards_camera: &Vector3<f64>) -> Matrix3<f64> {
    let z = towards_camera.normalize();
    let x = Vector3::y().cross(&z);
    // Looking straight down or up: any horizontal x will do.
    let x = if x.norm() < 1e-9 {
        Vector3::x()
    } else {
        x.normalize()
    };
    let y = z.cross(&x);
    Matrix3::from_columns(&[x, y, z])
}

/// `count` particles drawn uniformly in `volume`.
pub fn particles(volume: &Volume, count: usize, rng: &mut impl Rng) -> Vec<Point3<f64>> {
    (0..count)
        .map(|_| {
            Point3::from(Vector3::from_fn(|i, _| {
                rng.random_range(volume.min[i]..=volume.max[i])
            }))
        })
        .collect()
}

/// The image of every point in every camera, `[camera][point]`, with
/// Gaussian noise of `noise_px` (pixels, per coordinate); `None` where the
/// point does not image onto that camera's sensor.
pub fn observe(
    cameras: &[Camera],
    points: &[Point3<f64>],
    noise_px: f64,
    rng: &mut impl Rng,
) -> Vec<Vec<Option<Point2<f64>>>> {
    let noise = Normal::new(0.0, noise_px.max(0.0)).expect("standard deviation is non-negative");
    cameras
        .iter()
        .map(|camera| {
            points
                .iter()
                .map(|point| {
                    let pixel = camera.project(point).ok()?;
                    let noisy = pixel + Vector2::new(noise.sample(rng), noise.sample(rng));
                    camera.sensor().contains(noisy).then_some(noisy)
                })
                .collect()
        })
        .collect()
}

/// The observations of one point in every camera that sees it, from the
/// output of [`observe`].
pub fn observations_of(images: &[Vec<Option<Point2<f64>>>], point: usize) -> Vec<Observation> {
    images
        .iter()
        .enumerate()
        .filter_map(|(camera, pixels)| pixels[point].map(|pixel| Observation { camera, pixel }))
        .collect()
}

/// How particles look in a rendered camera image.
///
/// A particle is the Gaussian `A exp(-r² / 2σ²)` around its exact image
/// position, averaged over each pixel's area (so a pixel's value is what a
/// sensor with 100% fill factor records), with the e⁻² diameter `4σ` and a
/// peak `A` drawn uniformly per particle and camera. The background is a
/// plane; then every pixel gets photon noise (Poisson in electrons) and read
/// noise (Gaussian), and is rounded and clipped to the bit depth's range.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderSpec {
    /// Particle image diameter (px): the e⁻² diameter `4σ` of the Gaussian.
    pub diameter: f64,
    /// Smallest peak `A` (grey levels above the background).
    pub peak_min: f64,
    /// Largest peak `A`.
    pub peak_max: f64,
    /// Background grey value at the image's centre.
    pub background: f64,
    /// Background slope (grey levels per pixel) along x and y.
    pub gradient: Vector2<f64>,
    /// Sensor gain (electrons per grey level) for photon noise; 0 for none.
    pub electrons_per_grey: f64,
    /// Read noise, standard deviation in grey levels.
    pub read_noise: f64,
    /// 8 or 16 bits per pixel.
    pub bit_depth: BitDepth,
}

impl RenderSpec {
    /// A typical 8-bit PTV image: particles of `diameter` px with peaks of
    /// 80..200 grey levels, a background of 20 rising by 0.02 and 0.01 grey
    /// levels per pixel along x and y, photon noise at 50 electrons per grey
    /// level and 1 grey level of read noise.
    pub fn eight_bit(diameter: f64) -> RenderSpec {
        RenderSpec {
            diameter,
            peak_min: 80.0,
            peak_max: 200.0,
            background: 20.0,
            gradient: Vector2::new(0.02, 0.01),
            electrons_per_grey: 50.0,
            read_noise: 1.0,
            bit_depth: BitDepth::Eight,
        }
    }

    /// The same scene as [`RenderSpec::eight_bit`] seen by a 16-bit camera:
    /// every grey value times 257 (so 255 maps to 65535), the same noise in
    /// electrons.
    pub fn sixteen_bit(diameter: f64) -> RenderSpec {
        let eight = RenderSpec::eight_bit(diameter);
        RenderSpec {
            peak_min: eight.peak_min * 257.0,
            peak_max: eight.peak_max * 257.0,
            background: eight.background * 257.0,
            gradient: eight.gradient * 257.0,
            electrons_per_grey: eight.electrons_per_grey / 257.0,
            read_noise: eight.read_noise * 257.0,
            bit_depth: BitDepth::Sixteen,
            ..eight
        }
    }

    /// The Gaussian's standard deviation (px).
    pub fn sigma(&self) -> f64 {
        self.diameter / 4.0
    }
}

/// The error function, by Abramowitz and Stegun 7.1.26 (absolute error
/// below 1.5e-7, far below a grey level at any bit depth).
fn erf(x: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let y = 1.0 - poly * (-x * x).exp();
    y.copysign(x)
}

/// The mean over pixels `first..first + count` (along one axis) of
/// `exp(-(u - centre)² / 2σ²)`: the Gaussian integrated over each pixel.
fn pixel_profile(first: i64, count: usize, centre: f64, sigma: f64, out: &mut Vec<f64>) {
    let scale = 1.0 / (sigma * std::f64::consts::SQRT_2);
    let norm = sigma * (std::f64::consts::PI / 2.0).sqrt();
    out.clear();
    let mut low = erf((first as f64 - centre) * scale);
    for k in 0..count {
        let high = erf((first as f64 + k as f64 + 1.0 - centre) * scale);
        out.push(norm * (high - low));
        low = high;
    }
}

/// Renders particles at exact pixel positions (the camera model's pixel
/// convention) into a `width` x `height` image. Particles off the image or
/// with non-finite positions leave no trace; a zero size gives a 1x1 image;
/// a non-finite or empty peak range gives every particle `peak_min`.
pub fn render(
    width: u32,
    height: u32,
    positions: &[Point2<f64>],
    spec: &RenderSpec,
    rng: &mut impl Rng,
) -> GreyImage {
    render_with(width, height, positions, spec, None, rng)
}

/// [`render`] in front of a structured background, at frame `frame` of a
/// sequence (which sets the illumination drift's gain), with the field's
/// size. The particles and the plane background are rendered as by
/// [`render`]; the field's streaks and objects are added to the plane, the
/// whole scene is multiplied by the vignetting and the drift's gain, the
/// sensor noise follows, and the hot pixels are set to the largest grey
/// value last. With [`StructuredBackground::none`] the image is exactly
/// [`render`]'s for the same random numbers.
pub fn render_scene(
    field: &BackgroundField,
    frame: u64,
    positions: &[Point2<f64>],
    spec: &RenderSpec,
    rng: &mut impl Rng,
) -> GreyImage {
    let gain = field.spec().gain(frame);
    render_with(
        field.width(),
        field.height(),
        positions,
        spec,
        Some((field, gain)),
        rng,
    )
}

fn render_with(
    width: u32,
    height: u32,
    positions: &[Point2<f64>],
    spec: &RenderSpec,
    scene: Option<(&BackgroundField, f64)>,
    rng: &mut impl Rng,
) -> GreyImage {
    let (width, height) = (width.max(1), height.max(1));
    let (w, h) = (width as usize, height as usize);
    let centre = Vector2::new(f64::from(width) / 2.0, f64::from(height) / 2.0);
    let mut signal: Vec<f64> = (0..w * h)
        .map(|i| {
            let pixel = Vector2::new((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
            spec.background + spec.gradient.dot(&(pixel - centre))
        })
        .collect();
    let sigma = spec.sigma().max(1e-3);
    let reach = 4.0 * sigma + 1.0;
    let (mut along_x, mut along_y) = (Vec::new(), Vec::new());
    for position in positions {
        let (low, high) = (
            spec.peak_min.min(spec.peak_max),
            spec.peak_min.max(spec.peak_max),
        );
        let peak = if high > low && low.is_finite() && high.is_finite() {
            rng.random_range(low..=high)
        } else {
            low
        };
        if !position.x.is_finite() || !position.y.is_finite() {
            continue;
        }
        let x0 = ((position.x - reach).floor().max(0.0) as i64).min(w as i64);
        let x1 = ((position.x + reach).ceil().max(0.0) as i64).min(w as i64);
        let y0 = ((position.y - reach).floor().max(0.0) as i64).min(h as i64);
        let y1 = ((position.y + reach).ceil().max(0.0) as i64).min(h as i64);
        if x1 <= x0 || y1 <= y0 {
            continue;
        }
        pixel_profile(x0, (x1 - x0) as usize, position.x, sigma, &mut along_x);
        pixel_profile(y0, (y1 - y0) as usize, position.y, sigma, &mut along_y);
        for (j, fy) in along_y.iter().enumerate() {
            let row = (y0 as usize + j) * w + x0 as usize;
            for (value, fx) in signal[row..row + along_x.len()].iter_mut().zip(&along_x) {
                *value += peak * fx * fy;
            }
        }
    }
    if let Some((field, gain)) = scene {
        for (i, (value, added)) in signal.iter_mut().zip(field.additive()).enumerate() {
            *value = (*value + added) * field.vignette(i) * gain;
        }
    }
    let read = Normal::new(0.0, spec.read_noise.max(0.0)).ok();
    let max = f64::from(spec.bit_depth.max_value());
    let quantised = signal.into_iter().map(|mean| {
        let mut value = mean.max(0.0);
        if spec.electrons_per_grey > 0.0 && value > 0.0 {
            if let Ok(photons) = Poisson::new(value * spec.electrons_per_grey) {
                value = photons.sample(rng) / spec.electrons_per_grey;
            }
        }
        if let Some(read) = &read {
            value += read.sample(rng);
        }
        value.round().clamp(0.0, max)
    });
    let mut quantised: Vec<f64> = quantised.collect();
    if let Some((field, _)) = scene {
        for &i in field.hot_pixels() {
            if let Some(value) = quantised.get_mut(i) {
                *value = max;
            }
        }
    }
    let image = match spec.bit_depth {
        BitDepth::Eight => GreyImage::from_u8(
            width,
            height,
            quantised.into_iter().map(|v| v as u8).collect(),
        ),
        BitDepth::Sixteen => GreyImage::from_u16(
            width,
            height,
            quantised.into_iter().map(|v| v as u16).collect(),
        ),
    };
    image.expect("the samples fill the image, whose sides are at least 1")
}

/// One camera's rendered image and the exact image position of every point
/// (`None` where the point does not image onto the sensor).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedImage {
    /// The image.
    pub image: GreyImage,
    /// Per point: its exact pixel position, the ground truth for detection.
    pub truth: Vec<Option<Point2<f64>>>,
}

/// Renders the particles `points` into every camera's image, one image per
/// camera, with the sensor's size.
pub fn render_frame(
    cameras: &[Camera],
    points: &[Point3<f64>],
    spec: &RenderSpec,
    rng: &mut impl Rng,
) -> Vec<RenderedImage> {
    cameras
        .iter()
        .map(|camera| {
            let sensor = camera.sensor();
            let pixels: Vec<Option<Point2<f64>>> = points
                .iter()
                .map(|point| camera.project(point).ok())
                .collect();
            let visible: Vec<Point2<f64>> = pixels.iter().flatten().copied().collect();
            let image = render(sensor.width, sensor.height, &visible, spec, rng);
            let truth = pixels
                .into_iter()
                .map(|pixel| pixel.filter(|&p| sensor.contains(p)))
                .collect();
            RenderedImage { image, truth }
        })
        .collect()
}

/// A seeded random number generator, so that experiments repeat.
pub fn rng(seed: u64) -> StdRng {
    StdRng::seed_from_u64(seed)
}

/// One frame of targets per camera, as a detector would deliver it, with
/// the truth: `truth[c][t]` is the particle that target `t` of camera `c`
/// images.
#[derive(Clone, Debug, PartialEq)]
pub struct TargetFrame {
    /// Per camera, its targets in random order.
    pub targets: Vec<Vec<Target>>,
    /// Per camera and target, the index of the particle it images.
    pub truth: Vec<Vec<usize>>,
}

/// A target at `p` with the shape of a small particle image (9 pixels,
/// 3x3, sum of grey 900): what `target_frame` and tests give the
/// correspondences, which read only the position.
pub fn ideal_target(p: Point2<f64>) -> Target {
    Target {
        x: p.x,
        y: p.y,
        n: 9,
        nx: 3,
        ny: 3,
        sumg: 900,
    }
}

/// The targets of `points` in every camera: exact images plus Gaussian
/// noise of `noise_px`, each image lost with probability `drop_fraction`
/// (mimicking overlaps and weak particles), shuffled per camera so that the
/// order tells nothing.
pub fn target_frame(
    cameras: &[Camera],
    points: &[Point3<f64>],
    noise_px: f64,
    drop_fraction: f64,
    rng: &mut impl Rng,
) -> TargetFrame {
    use rand::seq::SliceRandom;
    let images = observe(cameras, points, noise_px, rng);
    let mut targets = Vec::with_capacity(cameras.len());
    let mut truth = Vec::with_capacity(cameras.len());
    for pixels in images {
        let mut kept: Vec<(usize, Point2<f64>)> = pixels
            .into_iter()
            .enumerate()
            .filter_map(|(j, pixel)| pixel.map(|p| (j, p)))
            .filter(|_| !rng.random_bool(drop_fraction.clamp(0.0, 1.0)))
            .collect();
        kept.shuffle(rng);
        truth.push(kept.iter().map(|(j, _)| *j).collect());
        targets.push(kept.iter().map(|(_, p)| ideal_target(*p)).collect());
    }
    TargetFrame { targets, truth }
}

/// How matched particles compare with the truth of a [`TargetFrame`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MatchScore {
    /// Particles whose targets all image the same true particle.
    pub correct: usize,
    /// Particles whose targets image different true particles.
    pub ghosts: usize,
    /// Root mean square 3D error of the correct particles (mm).
    pub rms_error: f64,
    /// Mean reported standard deviation (the root mean square of
    /// sigma_x, sigma_y, sigma_z) of the correct particles (mm).
    pub mean_sigma: f64,
    /// Largest 3D error of the correct particles (mm).
    pub max_error: f64,
    /// Particles found, by the number of cameras that see them (index =
    /// camera count).
    pub by_cameras: Vec<usize>,
}

impl MatchScore {
    /// Scores `particles` found in `frame` of `points`.
    pub fn of(particles: &[Particle], frame: &TargetFrame, points: &[Point3<f64>]) -> MatchScore {
        let mut score = MatchScore {
            by_cameras: vec![0; frame.targets.len() + 1],
            ..MatchScore::default()
        };
        let (mut sum_sq, mut sigma_sq) = (0.0, 0.0);
        for particle in particles {
            score.by_cameras[particle.camera_count()] += 1;
            let mut sources = particle
                .targets
                .iter()
                .enumerate()
                .filter_map(|(c, t)| t.map(|t| frame.truth[c][t]));
            let first = sources.next();
            match first {
                Some(j) if sources.all(|other| other == j) => {
                    score.correct += 1;
                    let error = (particle.position - points[j]).norm();
                    sum_sq += error * error;
                    sigma_sq += particle.sigma.norm_squared() / 3.0;
                    score.max_error = score.max_error.max(error);
                }
                _ => score.ghosts += 1,
            }
        }
        if score.correct > 0 {
            // Per axis, to compare with the per-axis sigmas.
            score.rms_error = (sum_sq / (3.0 * score.correct as f64)).sqrt();
            score.mean_sigma = (sigma_sq / score.correct as f64).sqrt();
        }
        score
    }
}

/// The shape of a simulated calibration target.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TargetShape {
    /// Two parallel grids, in the volume's planes Z = min and Z = max, like
    /// the two-plane frame of the design paper's Fig. 5.
    TwoPlanes,
    /// Points drawn uniformly in the volume.
    Volume,
}

/// A calibration target of `count` control points (ids from 1) spanning
/// `volume`.
pub fn calibration_target(
    shape: TargetShape,
    volume: &Volume,
    count: usize,
    rng: &mut impl Rng,
) -> Vec<ControlPoint> {
    let positions: Vec<Point3<f64>> = match shape {
        TargetShape::Volume => particles(volume, count, rng),
        TargetShape::TwoPlanes => {
            let per_plane = count.div_ceil(2);
            let side = (per_plane as f64).sqrt().ceil().max(2.0) as usize;
            let step = |k: usize, i: usize| {
                volume.min[k] + (volume.max[k] - volume.min[k]) * i as f64 / (side - 1) as f64
            };
            [volume.min.z, volume.max.z]
                .iter()
                .flat_map(|&z| {
                    (0..side * side)
                        .take(per_plane)
                        .map(move |i| Point3::new(step(0, i % side), step(1, i / side), z))
                })
                .take(count)
                .collect()
        }
    };
    positions
        .into_iter()
        .enumerate()
        .map(|(i, position)| ControlPoint {
            id: i as u64 + 1,
            position,
        })
        .collect()
}

/// Random lens and sensor errors of a typical machine-vision lens on a
/// sensor of about 15 mm: radial k1 of 1..3e-4 mm⁻² either sign (5..15 px at
/// the corners), decentering p1, p2 up to 3e-5 mm⁻¹, x scale within 1e-3 of
/// one and shear within 1e-3 rad. Higher radial terms are zero.
pub fn lens_errors(rng: &mut impl Rng) -> Distortion {
    let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
    Distortion {
        k1: sign * rng.random_range(1e-4..3e-4),
        k2: 0.0,
        k3: 0.0,
        p1: rng.random_range(-3e-5..3e-5),
        p2: rng.random_range(-3e-5..3e-5),
        scx: 1.0 + rng.random_range(-1e-3..1e-3),
        shear: rng.random_range(-1e-3..1e-3),
    }
}

/// The measured image positions of every control point each camera sees,
/// with Gaussian noise of `noise_px` (as [`observe`]).
pub fn observe_target(
    cameras: &[Camera],
    target: &[ControlPoint],
    noise_px: f64,
    rng: &mut impl Rng,
) -> Vec<Vec<MarkObservation>> {
    let points: Vec<Point3<f64>> = target.iter().map(|p| p.position).collect();
    observe(cameras, &points, noise_px, rng)
        .into_iter()
        .map(|pixels| {
            pixels
                .into_iter()
                .zip(target)
                .filter_map(|(pixel, p)| pixel.map(|pixel| MarkObservation { id: p.id, pixel }))
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn convergent_rig_sees_the_whole_volume() {
        for cameras in 2..=8 {
            let spec = RigSpec::convergent(cameras);
            let rig = spec.build().unwrap();
            let mut rng = rng(7);
            let points = particles(&spec.volume, 500, &mut rng);
            let images = observe(&rig, &points, 0.0, &mut rng);
            for (k, camera) in images.iter().enumerate() {
                assert!(
                    camera.iter().all(Option::is_some),
                    "{cameras} cameras: camera {k} misses points"
                );
            }
        }
    }

    #[test]
    fn erf_matches_known_values() {
        for (x, expected) in [
            (0.0, 0.0),
            (0.5, 0.520_499_877_8),
            (1.0, 0.842_700_792_9),
            (2.0, 0.995_322_265_0),
            (-1.0, -0.842_700_792_9),
        ] {
            assert!((erf(x) - expected).abs() < 2e-7, "erf({x})");
        }
    }

    #[test]
    fn rendered_particle_has_its_intensity_and_centre() {
        // Noise-free, on a zero background: the pixel values must add up to
        // the Gaussian's volume 2 pi sigma^2 A, and their centre of gravity
        // must be the particle's position (sampling a pixel-integrated
        // Gaussian of sigma 0.5 biases it by less than 0.003 px).
        let spec = RenderSpec {
            peak_min: 10_000.0,
            peak_max: 10_000.0,
            background: 0.0,
            gradient: Vector2::zeros(),
            electrons_per_grey: 0.0,
            read_noise: 0.0,
            ..RenderSpec::sixteen_bit(2.0)
        };
        let at = Point2::new(10.3, 9.8);
        let image = render(20, 20, &[at], &spec, &mut rng(1));
        let (mut sum, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for y in 0..20 {
            for x in 0..20 {
                let g = f64::from(image.get(x, y).unwrap());
                sum += g;
                sx += g * (f64::from(x) + 0.5);
                sy += g * (f64::from(y) + 0.5);
            }
        }
        let volume = 2.0 * std::f64::consts::PI * 0.25 * 10_000.0;
        assert!((sum - volume).abs() < 0.005 * volume, "{sum} vs {volume}");
        assert!((sx / sum - at.x).abs() < 0.003 && (sy / sum - at.y).abs() < 0.003);
    }

    #[test]
    fn rendered_frame_reports_exact_projections() {
        let spec = RigSpec::convergent(2);
        let cameras = spec.build().unwrap();
        let mut rng = rng(3);
        let points = particles(&spec.volume, 50, &mut rng);
        let frame = render_frame(&cameras, &points, &RenderSpec::eight_bit(2.5), &mut rng);
        assert_eq!(frame.len(), 2);
        for (camera, rendered) in cameras.iter().zip(&frame) {
            assert_eq!(rendered.image.width(), 1280);
            for (point, truth) in points.iter().zip(&rendered.truth) {
                assert_eq!(*truth, Some(camera.project(point).unwrap()));
            }
        }
    }

    #[test]
    fn cameras_look_at_the_volume_centre() {
        let spec = RigSpec::convergent(4);
        for camera in spec.build().unwrap() {
            let pixel = camera.project(&spec.volume.centre()).unwrap();
            let centre = Point2::new(640.0, 512.0);
            // Aimed through the wall: the centre images exactly there.
            assert!((pixel - centre).norm() < 1e-6, "{}: {pixel}", camera.name());
        }
    }
}
