//! Particles and trajectories in object space, in three orthographic
//! views side by side: XY (X right, Y up), XZ (X right, Z up) and YZ (Y
//! right, Z up), all on one scale (mm per pixel) so that the views agree.
//!
//! A frame's particles (the intersected points, section 4.3) are discs
//! coloured by how many cameras saw them ([`super::cameras_colour`]); a
//! sequence's trajectories (Malik, Dracos, Papantoniou 1993) are lines
//! between consecutive points, each segment coloured by its speed (the
//! mean of the fitted velocities' lengths at its ends, where the fit gives
//! both, else its length over the frames it spans), on a colour scale up
//! to the 98th percentile of the speeds.

use nalgebra::{Point3, Vector3};

use super::{
    cameras_colour, check_size, format_value, render, speed_colour, text_height, text_width, Draw,
    PlotError, PlotFormat, BLACK, GREY,
};

/// A view's side (pixels).
pub const PANEL: i64 = 400;
const MARGIN: i64 = 20;
const GAP: i64 = 50;
const PAD: f64 = 12.0;

/// The three views.
pub const VIEWS: [(&str, usize, usize); 3] = [("XY", 0, 1), ("XZ", 0, 2), ("YZ", 1, 2)];

/// Where the views are.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewsLayout {
    /// The picture's width.
    pub width: u32,
    /// Its height.
    pub height: u32,
    /// The smallest corner of the points' box (mm).
    pub min: Point3<f64>,
    /// The largest corner.
    pub max: Point3<f64>,
    /// Pixels per mm.
    pub scale: f64,
    top: i64,
}

impl ViewsLayout {
    /// The layout for points within `min..max` (mm).
    pub fn new(min: Point3<f64>, max: Point3<f64>) -> ViewsLayout {
        let (min, max) = if min.iter().chain(max.iter()).all(|v| v.is_finite()) {
            (min, max)
        } else {
            (Point3::origin(), Point3::new(1.0, 1.0, 1.0))
        };
        let extent = (max - min).max().max(1e-9);
        let top = MARGIN + text_height(2) as i64 + 3 * (text_height(1) as i64 + 6) + 20;
        ViewsLayout {
            width: (2 * MARGIN + 3 * PANEL + 2 * GAP) as u32,
            height: (top + PANEL + 3 * (text_height(1) as i64 + 6) + MARGIN) as u32,
            min,
            max,
            scale: (PANEL as f64 - 2.0 * PAD) / extent,
            top,
        }
    }

    /// The layout for these points (their bounding box).
    pub fn of(points: impl Iterator<Item = Point3<f64>>) -> ViewsLayout {
        let mut min = Point3::new(f64::INFINITY, f64::INFINITY, f64::INFINITY);
        let mut max = Point3::new(f64::NEG_INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        for p in points.filter(|p| p.iter().all(|v| v.is_finite())) {
            min = min.inf(&p);
            max = max.sup(&p);
        }
        ViewsLayout::new(min, max)
    }

    /// The top-left corner of view `view` (0 XY, 1 XZ, 2 YZ).
    pub fn panel(&self, view: usize) -> (i64, i64) {
        (MARGIN + view as i64 * (PANEL + GAP), self.top)
    }

    /// Where a point (mm) is drawn in view `view`.
    pub fn point(&self, view: usize, p: &Point3<f64>) -> (f64, f64) {
        let (_, a, b) = VIEWS[view];
        let (x0, y0) = self.panel(view);
        let centre = |k: usize| (self.min[k] + self.max[k]) / 2.0;
        let half = PANEL as f64 / 2.0;
        (
            x0 as f64 + half + (p[a] - centre(a)) * self.scale,
            y0 as f64 + half - (p[b] - centre(b)) * self.scale,
        )
    }

    /// Draws the title lines, the views' frames and their axes' ranges.
    fn frame(&self, d: &mut dyn Draw, title: &str, lines: &[String]) {
        let line = text_height(1) as i64 + 6;
        let mut y = MARGIN;
        d.text(MARGIN, y, title, 2, BLACK);
        y += text_height(2) as i64 + 8;
        for text in lines {
            d.text(MARGIN, y, text, 1, BLACK);
            y += line;
        }
        let names = ["X", "Y", "Z"];
        for (view, (name, a, b)) in VIEWS.iter().enumerate() {
            let (x0, y0) = self.panel(view);
            d.rect(x0, y0, PANEL, PANEL, GREY);
            d.text(x0, y0 - line, name, 1, BLACK);
            let range = |k: usize| {
                let half = PANEL as f64 / 2.0 / self.scale;
                let c = (self.min[k] + self.max[k]) / 2.0;
                (c - half, c + half)
            };
            let (a0, a1) = range(*a);
            let (b0, b1) = range(*b);
            let below = y0 + PANEL + 4;
            d.text(
                x0,
                below,
                &format!("{} {}", names[*a], format_value(a0)),
                1,
                BLACK,
            );
            let right = format!("{} MM", format_value(a1));
            d.text(
                x0 + PANEL - text_width(&right, 1) as i64,
                below,
                &right,
                1,
                BLACK,
            );
            d.text(
                x0,
                below + line,
                &format!(
                    "{} {}..{} MM (UP)",
                    names[*b],
                    format_value(b0),
                    format_value(b1)
                ),
                1,
                BLACK,
            );
        }
    }
}

/// A particle to draw: its position and the cameras that saw it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParticlePoint {
    /// Position (mm).
    pub position: Point3<f64>,
    /// How many cameras saw it (0: unknown).
    pub cameras: usize,
}

/// A frame's particles in three views: the picture's bytes.
pub fn particles_plot(
    title: &str,
    particles: &[ParticlePoint],
    format: PlotFormat,
) -> Result<Vec<u8>, PlotError> {
    let layout = ViewsLayout::of(particles.iter().map(|p| p.position));
    check_size(layout.width as u64, layout.height as u64)?;
    render(format, (layout.width, layout.height), |d| {
        draw_particles(d, title, particles, &layout)
    })
}

/// Draws particles laid out by `layout`.
pub fn draw_particles(
    d: &mut dyn Draw,
    title: &str,
    particles: &[ParticlePoint],
    layout: &ViewsLayout,
) {
    let mut counts = [0usize; 6];
    for p in particles {
        counts[p.cameras.min(5)] += 1;
    }
    let by = counts
        .iter()
        .enumerate()
        .filter(|(_, n)| **n > 0)
        .map(|(c, n)| match c {
            0 | 1 => format!("{n} UNKNOWN"),
            5 => format!("{n} BY 5+"),
            c => format!("{n} BY {c}"),
        })
        .collect::<Vec<_>>()
        .join(", ");
    layout.frame(
        d,
        title,
        &[
            format!("{} PARTICLES, SEEN BY CAMERAS: {by}", particles.len()),
            "COLOUR: 2 ORANGE, 3 YELLOW, 4 GREEN, 5+ CYAN".to_owned(),
        ],
    );
    // The best-seen particles on top.
    let mut order: Vec<&ParticlePoint> = particles.iter().collect();
    order.sort_by_key(|p| p.cameras);
    for view in 0..3 {
        for p in &order {
            let (x, y) = layout.point(view, &p.position);
            d.disc(x, y, 1.5, cameras_colour(p.cameras));
        }
    }
}

/// A trajectory's point to draw.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrajectoryPoint {
    /// The frame.
    pub frame: i64,
    /// Position (mm).
    pub position: Point3<f64>,
    /// Velocity (mm per frame), where the fit gives one.
    pub velocity: Option<Vector3<f64>>,
}

/// A segment's speed (mm per frame): the mean of its ends' fitted speeds,
/// else its length over the frames it spans.
pub fn segment_speed(a: &TrajectoryPoint, b: &TrajectoryPoint) -> f64 {
    match (a.velocity, b.velocity) {
        (Some(u), Some(v)) => (u.norm() + v.norm()) / 2.0,
        _ => (b.position - a.position).norm() / (b.frame - a.frame).max(1) as f64,
    }
}

/// The top of the speed colour scale: the 98th percentile of the
/// segments' speeds (a few wrong links do not wash the scale out).
pub fn speed_scale(trajectories: &[Vec<TrajectoryPoint>]) -> f64 {
    let mut speeds: Vec<f64> = trajectories
        .iter()
        .flat_map(|t| t.windows(2).map(|w| segment_speed(&w[0], &w[1])))
        .filter(|s| s.is_finite())
        .collect();
    if speeds.is_empty() {
        return 1.0;
    }
    speeds.sort_by(f64::total_cmp);
    let top = speeds[((speeds.len() - 1) as f64 * 0.98).round() as usize];
    if top > 0.0 {
        top
    } else {
        1.0
    }
}

/// Trajectories (each in frame order) in three views, coloured by speed:
/// the picture's bytes. `note` is a line under the title (what was
/// left out, ...).
pub fn trajectories_plot(
    title: &str,
    note: &str,
    trajectories: &[Vec<TrajectoryPoint>],
    format: PlotFormat,
) -> Result<Vec<u8>, PlotError> {
    let layout = ViewsLayout::of(trajectories.iter().flatten().map(|p| p.position));
    check_size(layout.width as u64, layout.height as u64)?;
    render(format, (layout.width, layout.height), |d| {
        draw_trajectories(d, title, note, trajectories, &layout)
    })
}

/// Draws trajectories laid out by `layout`.
pub fn draw_trajectories(
    d: &mut dyn Draw,
    title: &str,
    note: &str,
    trajectories: &[Vec<TrajectoryPoint>],
    layout: &ViewsLayout,
) {
    let points: usize = trajectories.iter().map(Vec::len).sum();
    let top = speed_scale(trajectories);
    let mut lines = vec![format!(
        "{} TRAJECTORIES, {points} POINTS; COLOUR: SPEED (MM PER FRAME)",
        trajectories.len()
    )];
    if !note.is_empty() {
        lines.push(note.to_owned());
    }
    layout.frame(d, title, &lines);
    // The colour bar, right of the title.
    let (bx, by) = (layout.width as i64 - MARGIN - 200 - 60, MARGIN + 4);
    d.text(bx - text_width("0 ", 1) as i64, by, "0", 1, BLACK);
    for i in 0..200 {
        d.fill_rect(bx + i, by - 2, 1, 11, speed_colour(i as f64 / 199.0));
    }
    d.text(
        bx + 206,
        by,
        &format!("{} MM/FRAME", format_value(top)),
        1,
        BLACK,
    );
    for view in 0..3 {
        for t in trajectories {
            for w in t.windows(2) {
                let colour = speed_colour(segment_speed(&w[0], &w[1]) / top);
                d.line(
                    layout.point(view, &w[0].position),
                    layout.point(view, &w[1].position),
                    1.0,
                    colour,
                );
            }
            if let [only] = t.as_slice() {
                let (x, y) = layout.point(view, &only.position);
                d.disc(x, y, 1.0, GREY);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn particles_are_drawn_where_they_are_in_each_view() {
        let particles = vec![
            ParticlePoint {
                position: Point3::new(-10.0, 0.0, 5.0),
                cameras: 4,
            },
            ParticlePoint {
                position: Point3::new(10.0, 20.0, -5.0),
                cameras: 2,
            },
        ];
        let png = particles_plot("FRAME 1", &particles, PlotFormat::Png).unwrap();
        let image = image::load_from_memory(&png).unwrap().to_rgb8();
        let layout = ViewsLayout::of(particles.iter().map(|p| p.position));
        assert_eq!(image.dimensions(), (layout.width, layout.height));
        for view in 0..3 {
            for p in &particles {
                let (x, y) = layout.point(view, &p.position);
                assert_eq!(
                    *image.get_pixel(x.round() as u32, y.round() as u32),
                    cameras_colour(p.cameras),
                    "view {view}"
                );
            }
            // Y is up in XY: the second particle (larger Y) is higher.
            let (_, y0) = layout.point(0, &particles[0].position);
            let (_, y1) = layout.point(0, &particles[1].position);
            assert!(y1 < y0);
        }
        // No particles: an empty picture, not a failure.
        assert!(particles_plot("FRAME 2", &[], PlotFormat::Svg).is_ok());
    }

    #[test]
    fn trajectories_are_coloured_by_speed() {
        let point = |frame: i64, x: f64, v: Option<f64>| TrajectoryPoint {
            frame,
            position: Point3::new(x, 0.0, 0.0),
            velocity: v.map(|v| Vector3::new(v, 0.0, 0.0)),
        };
        let slow = vec![point(0, 0.0, Some(1.0)), point(1, 1.0, Some(1.0))];
        let fast = vec![point(0, 0.0, None), point(2, 40.0, None)];
        assert_eq!(segment_speed(&slow[0], &slow[1]), 1.0);
        assert_eq!(segment_speed(&fast[0], &fast[1]), 20.0);
        let all = vec![slow, fast];
        assert_eq!(speed_scale(&all), 20.0);
        let png = trajectories_plot("RUN 1", "", &all, PlotFormat::Png).unwrap();
        let image = image::load_from_memory(&png).unwrap().to_rgb8();
        let layout = ViewsLayout::of(all.iter().flatten().map(|p| p.position));
        let (x, y) = layout.point(0, &Point3::new(30.0, 0.0, 0.0));
        assert_eq!(
            *image.get_pixel(x.round() as u32, y.round() as u32),
            speed_colour(1.0)
        );
    }
}
