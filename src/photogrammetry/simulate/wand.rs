//! Wand sequences with known truth, for wand calibration
//! ([`crate::photogrammetry::selfcal::wand`]): a bar with two marks
//! `length` mm apart at random positions and orientations with both ends
//! inside the volume, imaged by every camera with Gaussian noise, the two
//! marks of each camera in random order (so the calibration must pair
//! them), and optionally a fraction of positions with a gross error (one
//! camera's mark displaced by 5-20 px, as a reflection merged with a mark
//! would).

use nalgebra::{Point2, Point3, Vector2, Vector3};
use rand::Rng;
use rand_distr::{Distribution, UnitSphere};

use super::{ideal_target, observe};
use crate::photogrammetry::camera::Camera;
use crate::photogrammetry::target::Target;
use crate::photogrammetry::volume::Volume;

/// `count` wand positions `[A, B]`, `length` mm apart, centres and
/// directions uniform, both ends inside `volume` (`None` if the wand does
/// not fit in it).
pub fn wand_positions(
    volume: &Volume,
    length: f64,
    count: usize,
    rng: &mut impl Rng,
) -> Option<Vec<[Point3<f64>; 2]>> {
    let extent = volume.max - volume.min;
    if !(length > 0.0 && length < extent.norm()) {
        return None;
    }
    let mut out = Vec::with_capacity(count);
    let mut tries = 0usize;
    while out.len() < count {
        tries += 1;
        if tries > 1000 * count.max(1) {
            return None;
        }
        let centre = Point3::from(Vector3::from_fn(|i, _| {
            rng.random_range(volume.min[i]..=volume.max[i])
        }));
        let d: [f64; 3] = UnitSphere.sample(rng);
        let half = Vector3::from(d) * (length / 2.0);
        let (a, b) = (centre + half, centre - half);
        if volume.contains(&a) && volume.contains(&b) {
            out.push([a, b]);
        }
    }
    Some(out)
}

/// One simulated wand frame: per camera its two targets, and the truth.
#[derive(Clone, Debug, PartialEq)]
pub struct WandFrame {
    /// Per camera the wand's two marks, in random order.
    pub targets: Vec<Vec<Target>>,
    /// Per camera, per target: 0 for end A, 1 for end B.
    pub ends: Vec<Vec<usize>>,
    /// Whether a mark of this frame was displaced (a gross error).
    pub gross: bool,
}

/// The frames of `wands` seen by `cameras`: exact images plus Gaussian
/// noise of `noise_px` per coordinate, shuffled per camera; a fraction
/// `gross_fraction` of frames has one mark of one camera displaced by
/// 5-20 px. A wand whose mark leaves a sensor has fewer targets there.
pub fn wand_frames(
    cameras: &[Camera],
    wands: &[[Point3<f64>; 2]],
    noise_px: f64,
    gross_fraction: f64,
    rng: &mut impl Rng,
) -> Vec<WandFrame> {
    wands
        .iter()
        .map(|w| {
            let images = observe(cameras, &w[..], noise_px, rng);
            let gross = rng.random_bool(gross_fraction.clamp(0.0, 1.0));
            let spoilt =
                gross.then(|| (rng.random_range(0..cameras.len()), rng.random_range(0..2)));
            let mut targets = Vec::with_capacity(cameras.len());
            let mut ends = Vec::with_capacity(cameras.len());
            for (c, pixels) in images.into_iter().enumerate() {
                let mut marks: Vec<(usize, Point2<f64>)> = pixels
                    .into_iter()
                    .enumerate()
                    .filter_map(|(e, p)| p.map(|p| (e, p)))
                    .collect();
                if let Some((sc, se)) = spoilt {
                    if sc == c {
                        if let Some(m) = marks.iter_mut().find(|m| m.0 == se) {
                            let angle = rng.random_range(0.0..std::f64::consts::TAU);
                            let r = rng.random_range(5.0..20.0);
                            m.1 += Vector2::new(angle.cos(), angle.sin()) * r;
                        }
                    }
                }
                if rng.random_bool(0.5) {
                    marks.reverse();
                }
                ends.push(marks.iter().map(|m| m.0).collect());
                targets.push(marks.iter().map(|m| ideal_target(m.1)).collect());
            }
            WandFrame {
                targets,
                ends,
                gross,
            }
        })
        .collect()
}
