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
/// Right of the last view: room for half of its last tick label.
const RIGHT: i64 = 36;
/// Between a view and the next one's tick labels.
const GAP: i64 = 24;
const PAD: f64 = 12.0;
/// A tick mark's length (pixels, outside the view's frame).
const TICK: i64 = 5;
/// Ticks closer than this to a view's corner are left out, so that the
/// two axes' labels cannot meet at the corner.
const CORNER: f64 = 10.0;

/// The three views.
pub const VIEWS: [(&str, usize, usize); 3] = [("XY", 0, 1), ("XZ", 0, 2), ("YZ", 1, 2)];
const AXES: [&str; 3] = ["x", "y", "z"];

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
    /// The width of the column of a view's vertical tick labels.
    column: i64,
}

/// A round step between ticks for an axis `span` long: 1, 2 or 5 times a
/// power of ten, the smallest that gives at most `most` steps.
pub fn tick_step(span: f64, most: usize) -> f64 {
    if !(span.is_finite() && span > 0.0) {
        return 1.0;
    }
    let raw = span / most.max(1) as f64;
    let power = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * power)
        .find(|v| *v >= raw * (1.0 - 1e-12))
        .unwrap_or(10.0 * power)
}

/// A tick's label: as many decimals as the step needs (a step of 0.05
/// gives two), no more, and no "-0".
pub fn tick_label(value: f64, step: f64) -> String {
    // Steps are 1, 2 or 5 times 10^e: -e decimals below 1.
    let decimals = if step.is_finite() && step > 0.0 && step < 1.0 {
        (-step.log10().floor()).min(12.0) as usize
    } else {
        0
    };
    let text = format!("{value:.decimals$}");
    if text
        .trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        text.trim_start_matches('-').to_owned()
    } else {
        text.replace('-', "−")
    }
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
        let line = text_height(1) as i64 + 6;
        // The title, three lines, the views' names.
        let top = MARGIN + text_height(2) as i64 + 8 + 3 * line + line + 4;
        let mut layout = ViewsLayout {
            width: 0,
            height: (top + PANEL + TICK + 4 + 2 * line + MARGIN) as u32,
            min,
            max,
            scale: (PANEL as f64 - 2.0 * PAD) / extent,
            top,
            column: 0,
        };
        // The widest vertical tick label, or axis name, sets the column.
        layout.column = VIEWS
            .iter()
            .flat_map(|(_, _, b)| {
                let (step, ticks) = layout.ticks(*b);
                ticks.into_iter().map(move |(v, _)| tick_label(v, step))
            })
            .chain(AXES.iter().map(|a| format!("{a} (mm)")))
            .map(|label| text_width(&label, 1) as i64)
            .max()
            .unwrap_or(0)
            + TICK
            + 6;
        layout.width = (layout.panel(2).0 + PANEL + RIGHT) as u32;
        layout
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
        (
            MARGIN + self.column + view as i64 * (PANEL + GAP + self.column),
            self.top,
        )
    }

    /// The range (mm) of axis `k` across a view.
    fn range(&self, k: usize) -> (f64, f64) {
        let half = PANEL as f64 / 2.0 / self.scale;
        let c = (self.min[k] + self.max[k]) / 2.0;
        (c - half, c + half)
    }

    /// The ticks of axis `k`: their step and, for each, its value (mm)
    /// and its distance along the view from the axis' low end (pixels).
    /// The largest round step that gives at least four ticks whose labels
    /// stand apart, else the finest whose labels do (at least two).
    pub fn ticks(&self, k: usize) -> (f64, Vec<(f64, f64)>) {
        let (low, high) = self.range(k);
        let at = |step: f64| {
            let mut ticks = Vec::new();
            let mut i = (low / step).ceil();
            // At most 64 steps looked at: a step too small for the
            // coordinates' precision (i + 1 == i) cannot loop for ever.
            let mut looked = 0;
            while i * step <= high && ticks.len() < 24 && looked < 64 {
                looked += 1;
                let value = i * step;
                let along = (value - low) * self.scale;
                if along >= CORNER && along <= PANEL as f64 - CORNER {
                    ticks.push((value, along));
                }
                i += 1.0;
            }
            ticks
        };
        let apart = |step: f64, ticks: &[(f64, f64)]| {
            let widest = ticks
                .iter()
                .map(|(v, _)| text_width(&tick_label(*v, step), 1))
                .max()
                .unwrap_or(0);
            (widest + 12) as f64 <= step * self.scale
        };
        let mut fallback = None;
        for most in 3..=12 {
            let step = tick_step(high - low, most);
            let ticks = at(step);
            if !apart(step, &ticks) {
                break;
            }
            if ticks.len() >= 4 {
                return (step, ticks);
            }
            if ticks.len() >= 2 {
                fallback = Some((step, ticks));
            }
        }
        fallback.unwrap_or_else(|| {
            let step = tick_step(high - low, 3);
            (step, at(step))
        })
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

    /// Draws the title lines, the views' frames and their axes: ticks
    /// with round values (mm) and the axes' names.
    fn frame(&self, d: &mut dyn Draw, title: &str, lines: &[String]) {
        let h = text_height(1) as i64;
        let line = h + 6;
        let mut y = MARGIN;
        d.text(MARGIN, y, title, 2, BLACK);
        y += text_height(2) as i64 + 8;
        for text in lines {
            d.text(MARGIN, y, text, 1, BLACK);
            y += line;
        }
        for (view, (name, a, b)) in VIEWS.iter().enumerate() {
            let (x0, y0) = self.panel(view);
            d.rect(x0, y0, PANEL, PANEL, GREY);
            d.text(
                x0 + (PANEL - text_width(name, 1) as i64) / 2,
                y0 - line,
                name,
                1,
                BLACK,
            );
            // The horizontal axis: ticks below the frame, labels centred
            // under them, its name under the labels.
            let (step, ticks) = self.ticks(*a);
            for (value, along) in ticks {
                let x = x0 as f64 + along;
                d.line(
                    (x, (y0 + PANEL) as f64),
                    (x, (y0 + PANEL + TICK) as f64),
                    1.0,
                    BLACK,
                );
                let label = tick_label(value, step);
                let w = text_width(&label, 1) as i64;
                d.text(
                    x.round() as i64 - w / 2,
                    y0 + PANEL + TICK + 2,
                    &label,
                    1,
                    BLACK,
                );
            }
            let axis = format!("{} (mm)", AXES[*a]);
            d.text(
                x0 + (PANEL - text_width(&axis, 1) as i64) / 2,
                y0 + PANEL + TICK + 2 + line,
                &axis,
                1,
                BLACK,
            );
            // The vertical axis (up): ticks left of the frame, labels
            // right-aligned to them, its name above the labels.
            let (step, ticks) = self.ticks(*b);
            for (value, along) in ticks {
                let y = (y0 + PANEL) as f64 - along;
                d.line(
                    (x0 as f64 - TICK as f64 - 1.0, y),
                    (x0 as f64 - 1.0, y),
                    1.0,
                    BLACK,
                );
                let label = tick_label(value, step);
                let w = text_width(&label, 1) as i64;
                d.text(
                    x0 - TICK - 4 - w,
                    y.round() as i64 - h / 2,
                    &label,
                    1,
                    BLACK,
                );
            }
            let axis = format!("{} (mm)", AXES[*b]);
            d.text(
                x0 - TICK - 4 - text_width(&axis, 1) as i64,
                y0 - line,
                &axis,
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
            0 | 1 => format!("{n} unknown"),
            5 => format!("{n} by 5+"),
            c => format!("{n} by {c}"),
        })
        .collect::<Vec<_>>()
        .join(", ");
    layout.frame(
        d,
        title,
        &[
            format!("{} particles, seen by cameras: {by}", particles.len()),
            "Colour: 2 orange, 3 yellow, 4 green, 5+ cyan".to_owned(),
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
        "{} trajectories, {points} points; colour: speed (mm per frame)",
        trajectories.len()
    )];
    if !note.is_empty() {
        lines.push(note.to_owned());
    }
    layout.frame(d, title, &lines);
    // The colour bar, right of the title, its label's whole width inside
    // the picture.
    let label = format!("{} mm/frame", format_value(top));
    let bar = 200;
    let bx = layout.width as i64 - RIGHT - text_width(&label, 1) as i64 - 6 - bar;
    let by = MARGIN + 4;
    d.text(bx - text_width("0 ", 1) as i64, by, "0", 1, BLACK);
    for i in 0..bar {
        d.fill_rect(
            bx + i,
            by + 2,
            1,
            text_height(1) as i64 - 4,
            speed_colour(i as f64 / (bar - 1) as f64),
        );
    }
    d.text(bx + bar + 6, by, &label, 1, BLACK);
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

    #[test]
    fn ticks_are_round_and_labelled() {
        assert_eq!(tick_step(100.0, 5), 20.0);
        assert_eq!(tick_step(7.3, 5), 2.0);
        assert_eq!(tick_step(0.37, 5), 0.1);
        assert_eq!(tick_step(f64::NAN, 5), 1.0);
        assert_eq!(tick_label(-20.0, 20.0), "−20");
        assert_eq!(tick_label(-0.0, 20.0), "0");
        assert_eq!(tick_label(0.30000000000000004, 0.1), "0.3");
        assert_eq!(tick_label(1.5, 0.05), "1.50");
        // A view 40 mm across: ticks every 10 mm, at the values' places.
        let layout = ViewsLayout::new(Point3::new(-20.0, -20.0, 0.0), Point3::new(20.0, 20.0, 1.0));
        let (step, ticks) = layout.ticks(0);
        assert_eq!(step, 10.0);
        let values: Vec<f64> = ticks.iter().map(|t| t.0).collect();
        assert_eq!(values, vec![-20.0, -10.0, 0.0, 10.0, 20.0]);
        for (value, along) in ticks {
            let (x, _) = layout.point(0, &Point3::new(value, 0.0, 0.0));
            let x0 = layout.panel(0).0 as f64;
            assert!((x - x0 - along).abs() < 1e-9);
        }
    }

    #[test]
    fn every_label_fits_and_none_overlap() {
        let cases = [
            (
                Point3::new(-20.0, -20.0, -5.0),
                Point3::new(20.0, 25.0, 5.0),
            ),
            (
                Point3::new(-1234.5, 0.0, 1000.0),
                Point3::new(-1100.0, 0.004, 1000.5),
            ),
            (
                Point3::new(0.001, 0.002, 0.003),
                Point3::new(0.0012, 0.0021, 0.0035),
            ),
            (
                Point3::new(-15000.0, -5.0, -7.0),
                Point3::new(15000.0, 5.0, 7.0),
            ),
        ];
        for (min, max) in cases {
            let particles = vec![
                ParticlePoint {
                    position: min,
                    cameras: 4,
                },
                ParticlePoint {
                    position: max,
                    cameras: 2,
                },
            ];
            let layout = ViewsLayout::of(particles.iter().map(|p| p.position));
            let boxes = crate::plot::TextBoxes::of((layout.width, layout.height), |d| {
                draw_particles(d, "Sequence 12345, frame 4294967295", &particles, &layout)
            });
            boxes.assert_fit();
            // Every axis has at least three labelled ticks.
            for k in 0..3 {
                let (step, ticks) = layout.ticks(k);
                assert!(ticks.len() >= 4, "{min} {max}: axis {k}: {ticks:?}");
                for (value, _) in ticks {
                    assert!(boxes.has(&tick_label(value, step)), "{value}");
                }
            }
            let point = |frame, position, speed: f64| TrajectoryPoint {
                frame,
                position,
                velocity: Some(Vector3::new(speed, 0.0, 0.0)),
            };
            let all = vec![vec![point(0, min, 2.577), point(1, max, 2.577)]];
            let note = "The first 1 of 123456 trajectories (at most 200000 points)";
            let boxes = crate::plot::TextBoxes::of((layout.width, layout.height), |d| {
                draw_trajectories(d, "Sequence 12345, tracking run 678", note, &all, &layout)
            });
            boxes.assert_fit();
            assert!(boxes.has("2.577 mm/frame"), "{:?}", boxes.texts);
        }
    }
}
