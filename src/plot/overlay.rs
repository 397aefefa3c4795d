//! A camera's frame with its targets and the particles' reprojections.
//!
//! The camera image at its own scale (one picture pixel a sensor pixel;
//! or a black sensor when the image is not at hand), each detected target
//! (section 6.1) ringed: matched targets (used by a particle, section 6.2)
//! in blue, unmatched ones in magenta, larger and thicker, so they stand
//! out; each particle's reprojection into this camera (collinearity with
//! the multimedia model, Eq. 1-12) as a hollow "+" (the particle's image
//! shows in its centre) coloured by how many cameras saw it ([`super::cameras_colour`]). A legend strip under the image.

use image::Rgb;
use nalgebra::Point3;

use super::{
    cameras_colour, check_size, render, text_height, text_width, Colour, Draw, PlotError,
    PlotFormat, BLACK, WHITE,
};
use crate::photogrammetry::image::GreyImage;
use crate::photogrammetry::{Camera, Target};

/// A matched target's ring.
pub const MATCHED: Colour = Rgb([40, 150, 255]);
/// An unmatched target's ring.
pub const UNMATCHED: Colour = Rgb([255, 0, 255]);
/// A blank sensor's colour (no image).
pub const BLANK: Colour = Rgb([0, 0, 0]);
/// A matched target's ring radius (pixels).
pub const MATCHED_RADIUS: f64 = 5.0;
/// An unmatched target's ring radius.
pub const UNMATCHED_RADIUS: f64 = 7.0;
/// A reprojection's "+": its arms reach from `CROSS.0` to `CROSS.1` pixels
/// from the point, so the particle's image shows in its hollow centre.
pub const CROSS: (f64, f64) = (1.5, 3.0);
/// The legend's height under the image.
pub const LEGEND: u32 = 84;

const MATCHED_WIDTH: f64 = 1.5;
const UNMATCHED_WIDTH: f64 = 2.0;

/// A particle's image in the camera drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reprojection {
    /// Where it projects (camera px); `None` where the projection fails.
    pub pixel: Option<(f64, f64)>,
    /// How many cameras saw it.
    pub cameras: usize,
}

/// What an overlay shows.
#[derive(Clone, Debug)]
pub struct Overlay<'a> {
    /// A line above the legend: which frame and camera.
    pub title: String,
    /// The sensor (pixels).
    pub sensor: (u32, u32),
    /// The camera's image, if at hand (of the sensor's size).
    pub image: Option<&'a GreyImage>,
    /// The camera's targets.
    pub targets: &'a [Target],
    /// Per target, whether a particle uses it.
    pub matched: Vec<bool>,
    /// The particles' reprojections.
    pub reprojections: Vec<Reprojection>,
}

impl<'a> Overlay<'a> {
    /// The overlay of camera `index` (`camera`) of a frame: its targets,
    /// and the particles given by their positions and per camera their
    /// target (`None` for none), projected into it.
    pub fn new<'p>(
        camera: &Camera,
        index: usize,
        targets: &'a [Target],
        particles: impl IntoIterator<Item = (Point3<f64>, &'p [Option<usize>])>,
        image: Option<&'a GreyImage>,
    ) -> Overlay<'a> {
        let mut matched = vec![false; targets.len()];
        let reprojections = particles
            .into_iter()
            .map(|(position, seen)| {
                if let Some(Some(t)) = seen.get(index) {
                    if let Some(m) = matched.get_mut(*t) {
                        *m = true;
                    }
                }
                Reprojection {
                    pixel: camera.project(&position).ok().map(|p| (p.x, p.y)),
                    cameras: seen.iter().flatten().count(),
                }
            })
            .collect();
        let sensor = camera.sensor();
        Overlay {
            title: String::new(),
            sensor: (sensor.width, sensor.height),
            image,
            targets,
            matched,
            reprojections,
        }
    }

    /// The picture's size: the sensor's, at least 480 wide, and the legend.
    pub fn size(&self) -> Result<(u32, u32), PlotError> {
        check_size(
            u64::from(self.sensor.0.max(480)),
            u64::from(self.sensor.1) + u64::from(LEGEND),
        )
    }

    /// The unmatched targets.
    pub fn unmatched(&self) -> usize {
        self.matched.iter().filter(|m| !**m).count()
    }
}

/// The drawing point of a camera pixel position (px): the picture is at
/// the sensor's scale.
pub fn point(x_px: f64, y_px: f64) -> (f64, f64) {
    (x_px - 0.5, y_px - 0.5)
}

/// The overlay as a picture's bytes.
pub fn overlay_plot(overlay: &Overlay<'_>, format: PlotFormat) -> Result<Vec<u8>, PlotError> {
    let size = overlay.size()?;
    if let Some(image) = overlay.image {
        if (image.width(), image.height()) != overlay.sensor {
            return Err(PlotError::Missing(format!(
                "the image is {}x{} pixels but the camera's sensor {}x{}",
                image.width(),
                image.height(),
                overlay.sensor.0,
                overlay.sensor.1
            )));
        }
    }
    render(format, size, |d| draw_overlay(d, overlay))
}

/// Draws the overlay.
pub fn draw_overlay(d: &mut dyn Draw, overlay: &Overlay<'_>) {
    let (w, h) = (overlay.sensor.0 as i64, overlay.sensor.1 as i64);
    match overlay.image {
        Some(image) => d.grey_image(0, 0, image),
        None => d.fill_rect(0, 0, w, h, BLANK),
    }
    for (target, &matched) in overlay.targets.iter().zip(&overlay.matched) {
        if matched {
            let (x, y) = point(target.x, target.y);
            d.ring(x, y, MATCHED_RADIUS, MATCHED_WIDTH, MATCHED);
        }
    }
    for (target, &matched) in overlay.targets.iter().zip(&overlay.matched) {
        if !matched {
            let (x, y) = point(target.x, target.y);
            d.ring(x, y, UNMATCHED_RADIUS, UNMATCHED_WIDTH, UNMATCHED);
        }
    }
    for r in &overlay.reprojections {
        if let Some((x, y)) = r.pixel {
            let (x, y) = point(x, y);
            d.cross(x, y, CROSS, 1.0, cameras_colour(r.cameras));
        }
    }
    // The legend.
    let (width, _) = d.size();
    d.fill_rect(0, h, width as i64, LEGEND as i64, WHITE);
    let line = text_height(1) as i64 + 8;
    let mut y = h + 6;
    d.text(6, y, &overlay.title, 1, BLACK);
    y += line;
    let mut x = 6;
    let key =
        |d: &mut dyn Draw, x: &mut i64, mark: &dyn Fn(&mut dyn Draw, f64, f64), label: &str| {
            mark(d, *x as f64 + 6.0, y as f64 + (text_height(1) / 2) as f64);
            d.text(*x + 16, y, label, 1, BLACK);
            *x += 16 + text_width(label, 1) as i64 + 12;
        };
    key(
        d,
        &mut x,
        &|d, cx, cy| d.ring(cx, cy, 4.0, MATCHED_WIDTH, MATCHED),
        &format!("{} matched", overlay.targets.len() - overlay.unmatched()),
    );
    key(
        d,
        &mut x,
        &|d, cx, cy| d.ring(cx, cy, 5.0, UNMATCHED_WIDTH, UNMATCHED),
        &format!("{} unmatched targets", overlay.unmatched()),
    );
    y += line;
    let mut x = 6;
    let label = format!("{} particles, seen by:", overlay.reprojections.len());
    d.text(x, y, &label, 1, BLACK);
    x += text_width(&label, 1) as i64 + 10;
    for (cameras, name) in [(2, "2"), (3, "3"), (4, "4"), (5, "5+ cameras")] {
        d.cross(
            x as f64 + 4.0,
            y as f64 + (text_height(1) / 2) as f64,
            CROSS,
            1.0,
            cameras_colour(cameras),
        );
        d.text(x + 12, y, name, 1, BLACK);
        x += 12 + text_width(name, 1) as i64 + 10;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate;

    #[test]
    fn marks_lie_on_the_targets() {
        let spec = simulate::RigSpec::convergent(2);
        let cameras = spec.build().unwrap();
        let camera = &cameras[0];
        let sensor = camera.sensor();
        let targets = vec![
            Target {
                x: 100.3,
                y: 80.7,
                n: 9,
                nx: 3,
                ny: 3,
                sumg: 900,
            },
            Target {
                x: 400.0,
                y: 300.2,
                n: 9,
                nx: 3,
                ny: 3,
                sumg: 900,
            },
        ];
        let particle = spec.volume.min + (spec.volume.max - spec.volume.min) / 2.0;
        let seen = [Some(1), Some(0)];
        let overlay = Overlay::new(camera, 0, &targets, [(particle, &seen[..])], None);
        assert_eq!(overlay.matched, vec![false, true]);
        let png = overlay_plot(&overlay, PlotFormat::Png).unwrap();
        let image = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(
            image.dimensions(),
            (sensor.width.max(480), sensor.height + LEGEND)
        );
        let at = |x: f64, y: f64| *image.get_pixel(x.round() as u32, y.round() as u32);
        let (x, y) = point(100.3, 80.7);
        assert_eq!(at(x + UNMATCHED_RADIUS, y), UNMATCHED);
        assert_eq!(at(x, y), BLANK);
        let (x, y) = point(400.0, 300.2);
        assert_eq!(at(x - MATCHED_RADIUS, y), MATCHED);
        let (px, py) = overlay.reprojections[0].pixel.unwrap();
        let (px, py) = point(px, py);
        assert_eq!(at(px + 2.5, py), cameras_colour(2));
        assert_eq!(at(px, py - 2.5), cameras_colour(2));
        assert_eq!(at(px, py), BLANK, "the cross's centre is hollow");
        let (w, h) = overlay.size().unwrap();
        let boxes = crate::plot::TextBoxes::of((w, h), |d| draw_overlay(d, &overlay));
        boxes.assert_fit();
        for (_, (_, top, _, _)) in &boxes.texts {
            assert!(
                *top >= sensor.height as f32,
                "the legend is under the sensor"
            );
        }
        let svg = String::from_utf8(overlay_plot(&overlay, PlotFormat::Svg).unwrap()).unwrap();
        assert_eq!(
            svg.matches("stroke=\"#ff00ff\"").count(),
            2,
            "one ring and its key"
        );
    }
}
