//! A run's calibration health over its frames
//! ([`crate::photogrammetry::health`]): per camera, the length of its
//! frame-mean disparity vector's change from the run's baseline (the mean
//! of its first window of frames), one line per camera over the frame
//! numbers, the alarm threshold as a dashed line, and each camera's alarm
//! as a vertical mark at the frame it fired.

use super::views::{tick_label, tick_step};
use super::{
    check_size, render, text_height, text_width, Colour, Draw, PlotError, PlotFormat, BLACK, GREY,
};
use image::Rgb;

/// One camera's series.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CameraSeries {
    /// (frame, mean disparity vector (px)), in frame order: one frame or
    /// the mean over a bin of frames.
    pub points: Vec<(i64, [f64; 2])>,
    /// The baseline (px); before the run has one, the mean of the first
    /// `window` points is used.
    pub baseline: Option<[f64; 2]>,
    /// The frame at which its alarm fired.
    pub alarm: Option<i64>,
}

/// What the picture shows.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct HealthSeries {
    /// The title.
    pub title: String,
    /// The alarm threshold (px).
    pub threshold_px: f64,
    /// Frames per window.
    pub window: usize,
    /// Per camera.
    pub cameras: Vec<CameraSeries>,
}

const WIDTH: i64 = 900;
const HEIGHT: i64 = 440;
const LEFT: i64 = 70;
const RIGHT: i64 = 24;
const TOP: i64 = 56;
const BOTTOM: i64 = 84;
const TICK: i64 = 5;

/// Camera colours, in camera order (then again).
const COLOURS: [Colour; 8] = [
    Rgb([31, 119, 180]),
    Rgb([214, 39, 40]),
    Rgb([44, 160, 44]),
    Rgb([148, 103, 189]),
    Rgb([255, 127, 14]),
    Rgb([23, 190, 207]),
    Rgb([140, 86, 75]),
    Rgb([188, 189, 34]),
];

/// A camera's colour.
pub fn camera_colour(camera: usize) -> Colour {
    COLOURS[camera % COLOURS.len()]
}

/// Per camera, (frame, drift length (px)) from its baseline.
pub fn drifts(series: &HealthSeries) -> Vec<Vec<(i64, f64)>> {
    series
        .cameras
        .iter()
        .map(|c| {
            let base = c.baseline.unwrap_or_else(|| {
                let first = &c.points[..c.points.len().min(series.window.max(1))];
                let n = first.len().max(1) as f64;
                [
                    first.iter().map(|p| p.1[0]).sum::<f64>() / n,
                    first.iter().map(|p| p.1[1]).sum::<f64>() / n,
                ]
            });
            c.points
                .iter()
                .map(|(f, m)| (*f, (m[0] - base[0]).hypot(m[1] - base[1])))
                .collect()
        })
        .collect()
}

/// Draws the picture.
pub fn draw_health(d: &mut dyn Draw, series: &HealthSeries) {
    let lines = drifts(series);
    let frames = lines.iter().flatten().map(|p| p.0);
    let (first, last) = (
        frames.clone().min().unwrap_or(0),
        frames.max().unwrap_or(1).max(1),
    );
    let last = last.max(first + 1);
    let top_value = lines
        .iter()
        .flatten()
        .map(|p| p.1)
        .filter(|v| v.is_finite())
        .fold(series.threshold_px * 1.5, f64::max)
        .max(1e-3);
    let (w, h) = (WIDTH - LEFT - RIGHT, HEIGHT - TOP - BOTTOM);
    let x_of = |f: i64| LEFT as f64 + (f - first) as f64 / (last - first) as f64 * w as f64;
    let y_of = |v: f64| TOP as f64 + h as f64 - v.min(top_value) / top_value * h as f64;
    d.text(16, 12, &series.title, 2, BLACK);
    let subtitle = format!(
        "Change of each camera's mean disparity from its first {} frames (px); alarm above {} px",
        series.window,
        tick_label(series.threshold_px, 0.01)
    );
    d.text(16, 12 + text_height(2) as i64, &subtitle, 1, BLACK);
    d.rect(LEFT, TOP, w + 1, h + 1, GREY);
    // Axes' ticks.
    let ystep = tick_step(top_value, 5);
    let mut v = 0.0;
    while v <= top_value * (1.0 + 1e-9) {
        let y = y_of(v).round() as i64;
        d.fill_rect(LEFT - TICK, y, TICK, 1, BLACK);
        let label = tick_label(v, ystep);
        let tw = text_width(&label, 1) as i64;
        d.text(
            LEFT - TICK - 4 - tw,
            y - text_height(1) as i64 / 2,
            &label,
            1,
            BLACK,
        );
        v += ystep;
    }
    let xstep = tick_step((last - first) as f64, 8).max(1.0);
    let mut f = (first as f64 / xstep).ceil() * xstep;
    while f <= last as f64 {
        let x = x_of(f as i64).round() as i64;
        d.fill_rect(x, TOP + h + 1, 1, TICK, BLACK);
        let label = tick_label(f, xstep);
        let tw = text_width(&label, 1) as i64;
        d.text(x - tw / 2, TOP + h + 1 + TICK + 2, &label, 1, BLACK);
        f += xstep;
    }
    let axis = "frame";
    d.text(
        LEFT + w / 2 - text_width(axis, 1) as i64 / 2,
        TOP + h + TICK + 4 + text_height(1) as i64,
        axis,
        1,
        BLACK,
    );
    // The threshold, dashed.
    let yt = y_of(series.threshold_px);
    let mut x = LEFT as f64;
    while x < (LEFT + w) as f64 {
        d.line((x, yt), ((x + 8.0).min((LEFT + w) as f64), yt), 1.5, BLACK);
        x += 14.0;
    }
    // The cameras' lines and alarms.
    for (camera, points) in lines.iter().enumerate() {
        let colour = camera_colour(camera);
        for pair in points.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            if a.1.is_finite() && b.1.is_finite() {
                d.line((x_of(a.0), y_of(a.1)), (x_of(b.0), y_of(b.1)), 1.5, colour);
            }
        }
        if let [only] = points.as_slice() {
            d.disc(x_of(only.0), y_of(only.1), 2.0, colour);
        }
        if let Some(frame) = series.cameras[camera].alarm {
            let x = x_of(frame.clamp(first, last));
            d.line((x, TOP as f64), (x, (TOP + h) as f64), 2.0, colour);
        }
    }
    // The legend: a swatch and a label per camera, with its alarm.
    let mut x = LEFT;
    let y = HEIGHT - text_height(1) as i64 - 10;
    for (camera, c) in series.cameras.iter().enumerate() {
        let label = match c.alarm {
            Some(frame) => format!("camera {camera}: alarm at frame {frame}"),
            None => format!("camera {camera}"),
        };
        let lw = text_width(&label, 1) as i64;
        if x + 22 + lw > WIDTH - RIGHT {
            break;
        }
        d.fill_rect(
            x,
            y + text_height(1) as i64 / 2 - 2,
            16,
            4,
            camera_colour(camera),
        );
        d.text(x + 20, y, &label, 1, BLACK);
        x += 20 + lw + 24;
    }
}

/// The picture as PNG or SVG.
pub fn health_plot(series: &HealthSeries, format: PlotFormat) -> Result<Vec<u8>, PlotError> {
    let size = check_size(WIDTH as u64, HEIGHT as u64)?;
    render(format, size, |d| draw_health(d, series))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plot::TextBoxes;

    fn series() -> HealthSeries {
        let steady = (0..200).map(|f| (f, [0.01, -0.01])).collect();
        let drifting = (0..200)
            .map(|f| (f, [0.01 * f as f64, 0.0]))
            .collect::<Vec<_>>();
        HealthSeries {
            title: "Sequence 1, calibration 1".into(),
            threshold_px: 0.3,
            window: 50,
            cameras: vec![
                CameraSeries {
                    points: steady,
                    baseline: Some([0.01, -0.01]),
                    alarm: None,
                },
                CameraSeries {
                    points: drifting,
                    baseline: None,
                    alarm: Some(97),
                },
            ],
        }
    }

    #[test]
    fn drifts_are_measured_from_the_baseline_or_the_first_window() {
        let d = drifts(&series());
        assert!(d[0].iter().all(|p| p.1.abs() < 1e-12));
        // No baseline: the first 50 frames' mean, 0.245 px.
        assert!(
            (d[1][199].1 - (1.99 - 0.245)).abs() < 1e-9,
            "{:?}",
            d[1][199]
        );
    }

    #[test]
    fn labels_fit_and_name_the_alarm() {
        let boxes = TextBoxes::of((WIDTH as u32, HEIGHT as u32), |d| draw_health(d, &series()));
        boxes.assert_fit();
        assert!(boxes.has("camera 1: alarm at frame 97"));
        let png = health_plot(&series(), PlotFormat::Png).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        // An empty run draws its axes.
        let empty = HealthSeries {
            window: 50,
            threshold_px: 0.3,
            ..HealthSeries::default()
        };
        assert!(health_plot(&empty, PlotFormat::Svg).is_ok());
    }
}
