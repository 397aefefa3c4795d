//! Synthetic experiments: the ground truth for tests and benchmarks.
//!
//! A rig of 2..8 cameras looks at an observation volume inside a water tank
//! through the tank's walls (or, for air experiments, at a volume in air).
//! Particles are drawn uniformly in the volume, projected exactly with the
//! camera model, and their image coordinates disturbed by Gaussian noise of a
//! chosen standard deviation. Everything is seeded, so a test sees the same
//! experiment every run.

use nalgebra::{Matrix3, Point2, Point3, Vector2, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use super::camera::{
    rotation_angles, Camera, CameraParameters, Distortion, Exterior, Interior, Sensor,
};
use super::intersect::Observation;
use super::media::{Media, Wall};
use super::volume::Volume;

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

    /// Builds the cameras: each looks at the volume's centre, x axis
    /// horizontal, with a principal distance that lets the volume fill about
    /// half of the sensor's shorter side.
    pub fn build(&self) -> Result<Vec<Camera>, super::camera::InvalidCamera> {
        let centre = self.volume.centre();
        let half_sensor = f64::min(
            f64::from(self.sensor.width) * self.sensor.pixel_size_x,
            f64::from(self.sensor.height) * self.sensor.pixel_size_y,
        ) / 2.0;
        let half_angle = (self.volume.radius() / self.distance).asin();
        let c = 0.5 * half_sensor / half_angle.tan();
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
                let (omega, phi, kappa) = rotation_angles(&look_at(&towards_camera));
                let media = match &self.tank {
                    Some(tank) => tank.media_for(&position),
                    None => Media::air(),
                };
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

/// A seeded random number generator, so that experiments repeat.
pub fn rng(seed: u64) -> StdRng {
    StdRng::seed_from_u64(seed)
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
    fn cameras_look_at_the_volume_centre() {
        let spec = RigSpec::convergent(4);
        for camera in spec.build().unwrap() {
            let pixel = camera.project(&spec.volume.centre()).unwrap();
            let centre = Point2::new(640.0, 512.0);
            // Refraction at an oblique wall shifts the centre a little; it
            // must stay near the middle of the sensor.
            assert!(
                (pixel - centre).norm() < 150.0,
                "{}: {pixel}",
                camera.name()
            );
        }
    }
}
