//! A calibration's residuals as a picture (Maas, Gruen, Papantoniou 1993,
//! section 5: the resection's image residuals `v`, observed minus computed
//! through the collinearity equations with the multimedia model, Eq. 1-12;
//! the check points' deviations after intersection, section 4.3).
//!
//! For one camera: on the left its sensor (scaled to fit), each control
//! point's residual vector as an arrow from where the point was measured,
//! on one scale for the whole panel (the scale bar above it), the points
//! left out as gross errors in red with a ring; on the right a histogram
//! of the used residuals' lengths with their RMS, and the check points'
//! errors (the length of each one's 3D deviation, in mm) with the RMSE per
//! axis. Drawn from [`ResidualReport`], the part of the report's JSON
//! (`ptv calibrate`'s, or a solved calibration's stored report) it needs.

use image::Rgb;
use serde::Deserialize;

use super::{
    format_value, lenient_f64, nice, render, text_height, text_width, Colour, Draw, PlotError,
    PlotFormat, BLACK, GREY,
};

/// A used residual's arrow.
pub const USED: Colour = Rgb([31, 90, 180]);
/// A point left out as a gross error.
pub const EXCLUDED: Colour = Rgb([215, 25, 28]);
/// The sensor panel's background.
pub const SENSOR: Colour = Rgb([246, 246, 246]);
/// The histogram's and the check points' bars.
pub const BAR: Colour = Rgb([120, 150, 200]);

const MARGIN: i64 = 20;
const SENSOR_BOX: f64 = 640.0;
const SIDE_W: i64 = 340;
const SIDE_H: i64 = 200;
/// The longest used residual is drawn this long (pixels).
const LONGEST_ARROW: f64 = 40.0;
/// Excluded residuals are drawn at most this long.
const CAPPED_ARROW: f64 = 120.0;
const BINS: usize = 20;

/// A calibration report's residuals and check points: the fields of its
/// JSON ([`crate::photogrammetry::calibrate::CalibrationReport`]) the
/// picture draws.
#[derive(Clone, Debug, Deserialize)]
pub struct ResidualReport {
    /// Per camera.
    pub cameras: Vec<CameraResiduals>,
    /// The check points, if any were chosen.
    #[serde(default)]
    pub check_points: Option<CheckPoints>,
}

/// One camera's residuals.
#[derive(Clone, Debug, Deserialize)]
pub struct CameraResiduals {
    /// The camera's name.
    pub name: String,
    /// Its sigma0 (px).
    #[serde(deserialize_with = "lenient_f64")]
    pub sigma0_px: f64,
    /// The points used.
    pub residuals: Vec<Residual>,
    /// The points left out as gross errors.
    #[serde(default)]
    pub excluded: Vec<Residual>,
}

/// One point's residual.
#[derive(Clone, Debug, Deserialize)]
pub struct Residual {
    /// The control point.
    pub id: u64,
    /// Residual x (px).
    #[serde(deserialize_with = "lenient_f64")]
    pub x_px: f64,
    /// Residual y (px).
    #[serde(deserialize_with = "lenient_f64")]
    pub y_px: f64,
    /// Where it was measured (px); absent from reports written before
    /// they carried it.
    #[serde(default)]
    pub image_px: Option<[f64; 2]>,
}

/// The check points.
#[derive(Clone, Debug, Deserialize)]
pub struct CheckPoints {
    /// RMSE in X (mm).
    #[serde(deserialize_with = "lenient_f64")]
    pub rmse_x_mm: f64,
    /// RMSE in Y (mm).
    #[serde(deserialize_with = "lenient_f64")]
    pub rmse_y_mm: f64,
    /// RMSE in Z (mm).
    #[serde(deserialize_with = "lenient_f64")]
    pub rmse_z_mm: f64,
    /// `diagonal / rmse`.
    #[serde(deserialize_with = "lenient_f64")]
    pub relative_accuracy: f64,
    /// Per check point.
    pub points: Vec<CheckPoint>,
}

/// One check point's deviation (mm).
#[derive(Clone, Debug, Deserialize)]
pub struct CheckPoint {
    /// The point.
    pub id: u64,
    /// Intersected minus known X.
    #[serde(deserialize_with = "lenient_f64")]
    pub dx: f64,
    /// Y.
    #[serde(deserialize_with = "lenient_f64")]
    pub dy: f64,
    /// Z.
    #[serde(deserialize_with = "lenient_f64")]
    pub dz: f64,
}

impl ResidualReport {
    /// The residuals of a report's JSON text; a self-calibration's report
    /// has none, which the error says.
    pub fn from_json(text: &str, source: &str) -> Result<ResidualReport, PlotError> {
        let value: serde_json::Value =
            serde_json::from_str(text).map_err(|e| PlotError::Input {
                input: source.to_owned(),
                reason: format!("not JSON: {e}"),
            })?;
        if value.get("outcome").is_some() {
            return Err(PlotError::Missing(format!(
                "{source} is a self-calibration's report: it has disparities, not control \
                 point residuals; draw its disparity maps instead (disparity.png, `ptv plot \
                 disparity`)"
            )));
        }
        serde_path_to_error::deserialize(value).map_err(|e| PlotError::Input {
            input: source.to_owned(),
            reason: e.to_string(),
        })
    }
}

/// Where things are in the picture.
#[derive(Clone, Debug, PartialEq)]
pub struct ResidualLayout {
    /// The picture's width.
    pub width: u32,
    /// Its height.
    pub height: u32,
    /// Drawing pixels per sensor pixel.
    pub sensor_scale: f64,
    /// Drawing pixels per pixel of residual.
    pub arrow_scale: f64,
    /// The sensor panel's top-left corner.
    pub sensor_origin: (i64, i64),
    /// The sensor panel's size.
    pub sensor_size: (i64, i64),
    /// The longest used residual (px).
    pub longest_px: f64,
}

impl ResidualLayout {
    /// The layout for a camera's residuals on a sensor of `sensor` pixels.
    pub fn new(camera: &CameraResiduals, sensor: (u32, u32)) -> ResidualLayout {
        let (w, h) = (sensor.0.max(1) as f64, sensor.1.max(1) as f64);
        let sensor_scale = (SENSOR_BOX / w).min(SENSOR_BOX / h);
        let sensor_size = (
            (w * sensor_scale).round() as i64,
            (h * sensor_scale).round() as i64,
        );
        let longest_px = camera
            .residuals
            .iter()
            .map(length)
            .filter(|l| l.is_finite())
            .fold(0.0, f64::max);
        let arrow_scale = LONGEST_ARROW / if longest_px > 0.0 { longest_px } else { 1.0 };
        let top = MARGIN + 2 * text_height(2) as i64 + 3 * text_height(1) as i64 + 40;
        let side = 2 * SIDE_H + 4 * text_height(1) as i64 + 60 + 6 * text_height(1) as i64;
        let width = MARGIN + sensor_size.0 + 60 + SIDE_W + MARGIN;
        let height = top + sensor_size.1.max(side) + MARGIN;
        ResidualLayout {
            width: width.max(720) as u32,
            height: height as u32,
            sensor_scale,
            arrow_scale,
            sensor_origin: (MARGIN, top),
            sensor_size,
            longest_px,
        }
    }

    /// The drawing point of a camera pixel position (px).
    pub fn sensor_point(&self, x_px: f64, y_px: f64) -> (f64, f64) {
        (
            self.sensor_origin.0 as f64 + x_px * self.sensor_scale - 0.5,
            self.sensor_origin.1 as f64 + y_px * self.sensor_scale - 0.5,
        )
    }

    /// Where the arrow of a residual measured at `image_px` ends.
    pub fn arrow_tip(&self, image_px: [f64; 2], residual: (f64, f64)) -> (f64, f64) {
        let (x, y) = self.sensor_point(image_px[0], image_px[1]);
        (
            x + self.arrow_scale * residual.0,
            y + self.arrow_scale * residual.1,
        )
    }
}

fn length(r: &Residual) -> f64 {
    r.x_px.hypot(r.y_px)
}

/// Checks that `report` has camera `camera` with the residuals' image
/// positions; its residuals.
pub fn camera_residuals(
    report: &ResidualReport,
    camera: usize,
) -> Result<&CameraResiduals, PlotError> {
    let cameras = report.cameras.len();
    let residuals = report
        .cameras
        .get(camera)
        .ok_or(PlotError::Camera { camera, cameras })?;
    if residuals
        .residuals
        .iter()
        .chain(&residuals.excluded)
        .any(|r| r.image_px.is_none())
    {
        return Err(PlotError::Missing(format!(
            "the report of camera {} ({}) does not say where its points were measured: it was \
             written before reports kept that; calibrate again to plot its residuals",
            camera, residuals.name
        )));
    }
    Ok(residuals)
}

/// Draws the residuals of camera `camera` of `report` whose sensor is
/// `sensor` pixels: the picture's bytes.
pub fn residual_plot(
    report: &ResidualReport,
    camera: usize,
    sensor: (u32, u32),
    format: PlotFormat,
) -> Result<Vec<u8>, PlotError> {
    let residuals = camera_residuals(report, camera)?;
    let layout = ResidualLayout::new(residuals, sensor);
    super::check_size(layout.width as u64, layout.height as u64)?;
    render(format, (layout.width, layout.height), |d| {
        draw_residuals(d, residuals, report.check_points.as_ref(), sensor, &layout)
    })
}

/// Draws one camera's residuals laid out by `layout`: the title and
/// figures, the arrows on the sensor, and beside them the histogram of
/// their lengths and the check points' errors.
pub fn draw_residuals(
    d: &mut dyn Draw,
    camera: &CameraResiduals,
    check_points: Option<&CheckPoints>,
    sensor: (u32, u32),
    layout: &ResidualLayout,
) {
    let rms = rms(camera.residuals.iter().map(length));
    draw_heading(d, camera, rms, sensor, layout);
    draw_arrows(d, camera, sensor, layout);
    let (sx, sy) = layout.sensor_origin;
    let left = sx + layout.sensor_size.0 + 60;
    let top = draw_length_histogram(d, camera, rms, layout, (left, sy));
    draw_check_points(d, check_points, (left, top));
}

/// The line height of the side panels' text.
fn line_height() -> i64 {
    text_height(1) as i64 + 6
}

/// The title, the camera's figures and the arrows' scale bar.
fn draw_heading(
    d: &mut dyn Draw,
    camera: &CameraResiduals,
    rms: f64,
    sensor: (u32, u32),
    layout: &ResidualLayout,
) {
    let line = line_height();
    let (m, mut y) = (MARGIN, MARGIN);
    d.text(
        m,
        y,
        &format!("Calibration residuals, camera {}", camera.name),
        2,
        BLACK,
    );
    y += text_height(2) as i64 + 8;
    d.text(
        m,
        y,
        &format!(
            "{} points used, σ₀ {} px, RMS {} px, {} left out as gross errors (red, ringed)",
            camera.residuals.len(),
            format_value(camera.sigma0_px),
            format_value(rms),
            camera.excluded.len()
        ),
        1,
        BLACK,
    );
    y += line;
    d.text(
        m,
        y,
        &format!(
            "Arrows: observed minus computed, from where each point was measured on the {}×{} px sensor",
            sensor.0, sensor.1
        ),
        1,
        BLACK,
    );
    y += line + 6;
    // Scale bar.
    let bar = nice(layout.longest_px.max(f64::MIN_POSITIVE));
    let bar_px = bar * layout.arrow_scale;
    d.text(m, y, "Scale:", 1, BLACK);
    let x0 = m as f64 + text_width("Scale: ", 1) as f64;
    d.arrow(
        (x0, y as f64 + 3.0),
        (x0 + bar_px, y as f64 + 3.0),
        2.0,
        6.0,
        USED,
    );
    d.text(
        (x0 + bar_px + 8.0) as i64,
        y,
        &format!("= {} px of residual", format_value(bar)),
        1,
        BLACK,
    );
}

/// The sensor, each used point's residual as an arrow from where it was
/// measured, and the excluded ones ringed, their arrows capped.
fn draw_arrows(
    d: &mut dyn Draw,
    camera: &CameraResiduals,
    sensor: (u32, u32),
    layout: &ResidualLayout,
) {
    let (sx, sy) = layout.sensor_origin;
    let (sw, sh) = layout.sensor_size;
    d.fill_rect(sx, sy, sw, sh, SENSOR);
    d.rect(sx - 1, sy - 1, sw + 2, sh + 2, GREY);
    d.text(sx, sy + sh + 4, "(0, 0)", 1, BLACK);
    let corner = format!("({}, {})", sensor.0, sensor.1);
    d.text(
        sx + sw - text_width(&corner, 1) as i64,
        sy + sh + 4,
        &corner,
        1,
        BLACK,
    );
    for r in &camera.residuals {
        let Some(at) = r.image_px else { continue };
        let from = layout.sensor_point(at[0], at[1]);
        d.arrow(from, layout.arrow_tip(at, (r.x_px, r.y_px)), 1.5, 5.0, USED);
    }
    for r in &camera.excluded {
        let Some(at) = r.image_px else { continue };
        let from = layout.sensor_point(at[0], at[1]);
        let mut tip = layout.arrow_tip(at, (r.x_px, r.y_px));
        let l = (tip.0 - from.0).hypot(tip.1 - from.1);
        if l > CAPPED_ARROW {
            tip = (
                from.0 + (tip.0 - from.0) * CAPPED_ARROW / l,
                from.1 + (tip.1 - from.1) * CAPPED_ARROW / l,
            );
        }
        d.ring(from.0, from.1, 5.0, 1.5, EXCLUDED);
        d.arrow(from, tip, 1.5, 5.0, EXCLUDED);
    }
}

/// The histogram of the used residuals' lengths, its top left corner at
/// `(left, top)`; where the next panel starts.
fn draw_length_histogram(
    d: &mut dyn Draw,
    camera: &CameraResiduals,
    rms: f64,
    layout: &ResidualLayout,
    (left, mut top): (i64, i64),
) -> i64 {
    let line = line_height();
    d.text(left, top, "Residual lengths (px), points used", 1, BLACK);
    top += line;
    let lengths: Vec<f64> = camera
        .residuals
        .iter()
        .map(length)
        .filter(|l| l.is_finite())
        .collect();
    let top_edge = if layout.longest_px > 0.0 {
        layout.longest_px
    } else {
        1.0
    };
    let mut counts = [0usize; BINS];
    for l in &lengths {
        let bin = ((l / top_edge) * BINS as f64).floor() as usize;
        counts[bin.min(BINS - 1)] += 1;
    }
    let most = counts.iter().copied().max().unwrap_or(0).max(1);
    d.rect(left, top, SIDE_W, SIDE_H, GREY);
    let bin_w = SIDE_W as f64 / BINS as f64;
    for (i, &count) in counts.iter().enumerate() {
        let h = (count as f64 / most as f64 * (SIDE_H - 2) as f64).round() as i64;
        let x = left + (i as f64 * bin_w).round() as i64;
        let w = (((i + 1) as f64 * bin_w).round() as i64 - (i as f64 * bin_w).round() as i64 - 1)
            .max(1);
        d.fill_rect(x + 1, top + SIDE_H - 1 - h, w, h, BAR);
    }
    if rms.is_finite() {
        let x = left as f64 + rms / top_edge * SIDE_W as f64;
        d.line(
            (x, top as f64),
            (x, (top + SIDE_H - 1) as f64),
            1.0,
            EXCLUDED,
        );
    }
    d.text(left, top + SIDE_H + 4, "0", 1, BLACK);
    let edge = format!("{} px", format_value(top_edge));
    d.text(
        left + SIDE_W - text_width(&edge, 1) as i64,
        top + SIDE_H + 4,
        &edge,
        1,
        BLACK,
    );
    d.text(
        left,
        top + SIDE_H + 4 + line,
        &format!("Tallest bar: {most} points; red line: RMS"),
        1,
        BLACK,
    );
    top += SIDE_H + 3 * line + 10;
    top
}

/// The check points' 3D errors, one bar each, and their RMSE, with the
/// panel's top left corner at `(left, top)`.
fn draw_check_points(
    d: &mut dyn Draw,
    check_points: Option<&CheckPoints>,
    (left, mut top): (i64, i64),
) {
    let line = line_height();
    d.text(left, top, "Check points: 3D error (mm)", 1, BLACK);
    top += line;
    let Some(check) = check_points.filter(|c| !c.points.is_empty()) else {
        d.rect(left, top, SIDE_W, SIDE_H, GREY);
        d.text(left + 10, top + SIDE_H / 2, "No check points", 1, BLACK);
        return;
    };
    let errors: Vec<f64> = check
        .points
        .iter()
        .map(|p| (p.dx * p.dx + p.dy * p.dy + p.dz * p.dz).sqrt())
        .collect();
    let largest = errors
        .iter()
        .copied()
        .filter(|e| e.is_finite())
        .fold(0.0, f64::max);
    let largest = if largest > 0.0 { largest } else { 1.0 };
    d.rect(left, top, SIDE_W, SIDE_H, GREY);
    let bar_w = (SIDE_W - 2) as f64 / errors.len() as f64;
    for (i, e) in errors.iter().enumerate() {
        if !e.is_finite() {
            continue;
        }
        let h = (e / largest * (SIDE_H - 2) as f64).round() as i64;
        let x0 = left + 1 + (i as f64 * bar_w).round() as i64;
        let x1 = left + 1 + ((i + 1) as f64 * bar_w).round() as i64;
        d.fill_rect(x0, top + SIDE_H - 1 - h, (x1 - x0 - 1).max(1), h, BAR);
    }
    d.text(
        left,
        top + SIDE_H + 4,
        &format!(
            "{} points, largest {} mm",
            errors.len(),
            format_value(largest)
        ),
        1,
        BLACK,
    );
    d.text(
        left,
        top + SIDE_H + 4 + line,
        &format!(
            "RMSE x {}, y {}, z {} mm",
            format_value(check.rmse_x_mm),
            format_value(check.rmse_y_mm),
            format_value(check.rmse_z_mm)
        ),
        1,
        BLACK,
    );
    d.text(
        left,
        top + SIDE_H + 4 + 2 * line,
        &format!(
            "Relative accuracy 1 : {}",
            format_value(check.relative_accuracy.round())
        ),
        1,
        BLACK,
    );
}

fn rms(values: impl Iterator<Item = f64>) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for v in values.filter(|v| v.is_finite()) {
        sum += v * v;
        n += 1;
    }
    if n == 0 {
        f64::NAN
    } else {
        (sum / n as f64).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report_json() -> String {
        serde_json::json!({
            "cameras": [{
                "name": "cam1",
                "sigma0_px": 0.1,
                "residuals": [
                    {"id": 1, "x_px": 0.2, "y_px": 0.0, "image_px": [100.5, 200.5], "test": null},
                    {"id": 2, "x_px": 0.0, "y_px": -0.1, "image_px": [900.0, 700.0], "test": null}
                ],
                "excluded": [{"id": 3, "x_px": 9.0, "y_px": 0.0, "image_px": [500.0, 500.0], "test": 80.0}]
            }],
            "check_points": {
                "count": 2, "rmse_x_mm": 0.01, "rmse_y_mm": 0.02, "rmse_z_mm": null,
                "relative_accuracy": 5000.0,
                "points": [{"id": 7, "dx": 0.01, "dy": 0.0, "dz": 0.0, "cameras": 2}]
            }
        })
        .to_string()
    }

    #[test]
    fn arrows_start_where_points_were_measured() {
        let report = ResidualReport::from_json(&report_json(), "r.json").unwrap();
        let png = residual_plot(&report, 0, (1024, 1024), PlotFormat::Png).unwrap();
        let image = image::load_from_memory(&png).unwrap().to_rgb8();
        let layout = ResidualLayout::new(&report.cameras[0], (1024, 1024));
        assert_eq!(image.dimensions(), (layout.width, layout.height));
        // The longest used residual is LONGEST_ARROW long: its shaft's
        // middle is the arrow colour, and so is the excluded point's ring.
        let from = layout.sensor_point(100.5, 200.5);
        let tip = layout.arrow_tip([100.5, 200.5], (0.2, 0.0));
        assert!((tip.0 - from.0 - LONGEST_ARROW).abs() < 1e-9);
        let mid = ((from.0 + tip.0) / 2.0, from.1);
        assert_eq!(
            *image.get_pixel(mid.0.round() as u32, mid.1.round() as u32),
            USED
        );
        let ring = layout.sensor_point(500.0, 500.0);
        assert_eq!(
            *image.get_pixel(ring.0.round() as u32, (ring.1 - 5.0).round() as u32),
            EXCLUDED
        );
        // Far from every point: the sensor's background.
        let empty = layout.sensor_point(300.0, 900.0);
        assert_eq!(*image.get_pixel(empty.0 as u32, empty.1 as u32), SENSOR);
        let svg = residual_plot(&report, 0, (1024, 1024), PlotFormat::Svg).unwrap();
        let svg = String::from_utf8(svg).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("camera cam1"));
    }

    #[test]
    fn missing_data_is_said() {
        let report = ResidualReport::from_json(&report_json(), "r.json").unwrap();
        let error = residual_plot(&report, 3, (10, 10), PlotFormat::Png).unwrap_err();
        assert!(matches!(
            error,
            PlotError::Camera {
                camera: 3,
                cameras: 1
            }
        ));
        let old = report_json().replace("\"image_px\":[100.5,200.5],", "");
        let old = ResidualReport::from_json(&old, "r.json").unwrap();
        let error = residual_plot(&old, 0, (10, 10), PlotFormat::Png).unwrap_err();
        assert!(error.to_string().contains("calibrate again"), "{error}");
        let selfcal = r#"{"outcome": "converged", "cameras": []}"#;
        let error = ResidualReport::from_json(selfcal, "s.json").unwrap_err();
        assert!(error.to_string().contains("self-calibration"), "{error}");
        let error = ResidualReport::from_json("{\"cameras\": 3}", "s.json").unwrap_err();
        assert!(error.to_string().starts_with("s.json: "), "{error}");
    }

    #[test]
    fn every_label_fits_and_none_overlap() {
        let report = ResidualReport::from_json(&report_json(), "r.json").unwrap();
        for sensor in [(1024, 1024), (2560, 600), (320, 1200)] {
            let camera = &report.cameras[0];
            let layout = ResidualLayout::new(camera, sensor);
            let boxes = crate::plot::TextBoxes::of((layout.width, layout.height), |d| {
                draw_residuals(d, camera, report.check_points.as_ref(), sensor, &layout)
            });
            boxes.assert_fit();
            // And without check points.
            crate::plot::TextBoxes::of((layout.width, layout.height), |d| {
                draw_residuals(d, camera, None, sensor, &layout)
            })
            .assert_fit();
        }
    }
}
