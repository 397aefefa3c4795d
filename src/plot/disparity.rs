//! The self-calibration's disparity maps as a picture (issue 14's report;
//! Wieneke 2008, *Volume self-calibration for 3D particle image
//! velocimetry*, section 3 and its figures: the mean disparity vector of
//! the particles in each sub-volume, per camera).
//!
//! One row per camera; per z layer of sub-volumes two panels, the maps
//! before and after the self-calibration. A panel is the layer's x-y grid
//! of cells (x to the right, y up); each cell with particles is coloured by
//! the length of its mean disparity vector and holds that vector as an
//! arrow from the cell's centre, in the camera's image axes (x right, y
//! down), on one scale for the whole picture (the scale bar at the top).
//! Cells without particles are light grey, without an arrow.
//!
//! Drawn from [`DisparityMaps`], the part of the report's JSON the picture
//! needs, read from a stored or written report (`ptv plot disparity`, the
//! service's `disparity.png`) or taken from a report in memory (`ptv
//! selfcalibrate --disparity-png`) through the same JSON.

use image::Rgb;
use serde::Deserialize;

use super::{
    format_value, heat, lenient_f64, nice, render, text_height, text_width, Draw, PlotError,
    PlotFormat, BLACK, GREY,
};
use crate::photogrammetry::selfcal::SelfCalibrationReport;
use crate::photogrammetry::volume::Volume;

/// The disparity maps of a self-calibration report: the fields of its
/// JSON ([`SelfCalibrationReport`]) the picture draws.
#[derive(Clone, Debug, Deserialize)]
pub struct DisparityMaps {
    /// The observation volume.
    pub volume: Volume,
    /// Sub-volumes per axis.
    pub grid: [usize; 3],
    /// Per camera.
    pub cameras: Vec<CameraMaps>,
}

/// One camera's maps.
#[derive(Clone, Debug, Deserialize)]
pub struct CameraMaps {
    /// The camera's name.
    pub name: String,
    /// Disparities before.
    pub before: Rms,
    /// Disparities after.
    pub after: Rms,
    /// The map before.
    pub map_before: Map,
    /// The map after.
    pub map_after: Map,
}

/// An RMS disparity (px; NaN where the report has none).
#[derive(Clone, Debug, Deserialize)]
pub struct Rms {
    /// RMS length (px).
    #[serde(deserialize_with = "lenient_f64")]
    pub rms_px: f64,
}

/// A map's cells with particles.
#[derive(Clone, Debug, Deserialize)]
pub struct Map {
    /// The cells.
    pub cells: Vec<Cell>,
}

/// One cell: its index and mean disparity vector (px).
#[derive(Clone, Debug, Deserialize)]
pub struct Cell {
    /// Index along x, y, z.
    pub index: [usize; 3],
    /// Mean disparity, x (px).
    #[serde(deserialize_with = "lenient_f64")]
    pub mean_dx_px: f64,
    /// Mean disparity, y (px).
    #[serde(deserialize_with = "lenient_f64")]
    pub mean_dy_px: f64,
}

impl DisparityMaps {
    /// The maps of a report in memory (through its JSON, as a stored one
    /// is read).
    pub fn from_report(report: &SelfCalibrationReport) -> Result<DisparityMaps, PlotError> {
        let value = serde_json::to_value(report).map_err(|e| PlotError::Input {
            input: "the self-calibration report".to_owned(),
            reason: e.to_string(),
        })?;
        DisparityMaps::from_value(value, "the self-calibration report")
    }

    /// The maps of a report's JSON text; a calibration's (resection)
    /// report has none, which the error says.
    pub fn from_json(text: &str, source: &str) -> Result<DisparityMaps, PlotError> {
        let value: serde_json::Value =
            serde_json::from_str(text).map_err(|e| PlotError::Input {
                input: source.to_owned(),
                reason: format!("not JSON: {e}"),
            })?;
        DisparityMaps::from_value(value, source)
    }

    fn from_value(value: serde_json::Value, source: &str) -> Result<DisparityMaps, PlotError> {
        if value.get("outcome").is_none() {
            return Err(PlotError::Missing(format!(
                "{source} is not a self-calibration's report (`ptv selfcalibrate`, or a \
                 calibration refined by POST /sequences/{{id}}/self-calibration): only those \
                 have disparity maps"
            )));
        }
        serde_path_to_error::deserialize(value).map_err(|e| PlotError::Input {
            input: source.to_owned(),
            reason: e.to_string(),
        })
    }
}

/// The colour of empty cells.
pub const EMPTY: Rgb<u8> = Rgb([235, 235, 235]);

/// The arrows' colour (nothing else inside a panel is black).
pub const ARROW: Rgb<u8> = BLACK;

/// The largest picture side (pixels): finer grids than fit are refused.
pub const MAX_SIDE: u32 = super::MAX_SIDE;

const MARGIN: u32 = 20;
const PANEL_GAP: u32 = 8;
const LAYER_GAP: u32 = 24;
const ROW_GAP: u32 = 28;
/// The narrowest picture: its explanation's lines fit.
const MIN_WIDTH: u64 = 760;

/// Why there is no picture.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DisparityPictureError {
    /// The report has no cameras.
    #[error("the report has no cameras: there are no disparity maps to draw")]
    NoCameras,
    /// The grid has an axis without cells.
    #[error("the report's sub-volume grid {0:?} has an axis without cells")]
    EmptyGrid([usize; 3]),
    /// The picture would be too large.
    #[error("a picture of the {grid:?} sub-volume grid for {cameras} cameras would be {width}x{height} pixels, more than {MAX_SIDE} on a side; use a coarser grid")]
    TooLarge {
        /// The grid.
        grid: [usize; 3],
        /// Cameras.
        cameras: usize,
        /// The picture's width.
        width: u32,
        /// The picture's height.
        height: u32,
    },
}

/// Where things are in the picture.
#[derive(Clone, Debug, PartialEq)]
pub struct DisparityLayout {
    /// The picture's size (pixels).
    pub width: u32,
    /// The picture's height.
    pub height: u32,
    /// A cell's side (pixels).
    pub cell_px: u32,
    /// Drawing pixels per pixel of disparity.
    pub arrow_scale: f64,
    /// The longest mean disparity vector drawn (px), the colour scale's top.
    pub max_disparity_px: f64,
    grid: [usize; 3],
    top: u32,
    left: u32,
    row_height: u32,
}

impl DisparityLayout {
    /// The layout of a report's picture.
    pub fn of(report: &DisparityMaps) -> Result<DisparityLayout, DisparityPictureError> {
        let names: Vec<&str> = report.cameras.iter().map(|c| c.name.as_str()).collect();
        let max = report
            .cameras
            .iter()
            .flat_map(|c| c.map_before.cells.iter().chain(&c.map_after.cells))
            .map(mean_length)
            .fold(0.0, f64::max);
        DisparityLayout::new(report.grid, &names, max)
    }

    /// The layout of the picture of a report with this sub-volume grid,
    /// these cameras, and `max_disparity_px` the longest mean disparity
    /// vector of its maps (before and after).
    pub fn new(
        grid: [usize; 3],
        names: &[&str],
        max_disparity_px: f64,
    ) -> Result<DisparityLayout, DisparityPictureError> {
        if names.is_empty() {
            return Err(DisparityPictureError::NoCameras);
        }
        if grid.contains(&0) {
            return Err(DisparityPictureError::EmptyGrid(grid));
        }
        let cell_px = (160 / grid[0].max(grid[1]) as u32).clamp(6, 48);
        let left = MARGIN
            + names
                .iter()
                .map(|name| text_width(name, 2))
                .max()
                .unwrap_or(0)
                .max(text_width("Camera", 1))
            + 12;
        // Title, three lines, the scale row, the z layers' headers.
        let top = MARGIN + text_height(2) + 5 * text_height(1) + 60;
        let panel_w = grid[0] as u64 * cell_px as u64;
        let panel_h = grid[1] as u64 * cell_px as u64;
        let width = left as u64
            + grid[2] as u64 * (2 * panel_w + PANEL_GAP as u64 + LAYER_GAP as u64)
            + MARGIN as u64;
        let row_height = panel_h + text_height(1) as u64 + 6 + ROW_GAP as u64;
        let height = top as u64 + names.len() as u64 * row_height + MARGIN as u64;
        // The line of the cameras' RMS before and after fits (the digits
        // are all one width in the font).
        let stats: u64 = names
            .iter()
            .map(|n| text_width(&format!("{n}: RMS 00.00 → 00.00 px   "), 1) as u64)
            .sum();
        let width = width.max(MIN_WIDTH).max(2 * MARGIN as u64 + stats);
        if width > MAX_SIDE as u64 || height > MAX_SIDE as u64 {
            return Err(DisparityPictureError::TooLarge {
                grid,
                cameras: names.len(),
                width: width.min(u32::MAX as u64) as u32,
                height: height.min(u32::MAX as u64) as u32,
            });
        }
        let max_disparity_px = if max_disparity_px.is_finite() && max_disparity_px > 0.0 {
            max_disparity_px
        } else {
            1.0
        };
        Ok(DisparityLayout {
            width: width as u32,
            height: height as u32,
            cell_px,
            arrow_scale: 0.45 * cell_px as f64 / max_disparity_px,
            max_disparity_px,
            grid,
            top,
            left,
            row_height: row_height as u32,
        })
    }

    /// The top-left corner of a camera's panel of z layer `layer`, before
    /// or after.
    fn panel(&self, camera: usize, layer: usize, after: bool) -> (u32, u32) {
        let panel_w = self.grid[0] as u32 * self.cell_px;
        let x = self.left
            + layer as u32 * (2 * panel_w + PANEL_GAP + LAYER_GAP)
            + if after { panel_w + PANEL_GAP } else { 0 };
        let y = self.top + camera as u32 * self.row_height + text_height(1) + 6;
        (x, y)
    }

    /// The centre (pixels) of a cell of a camera's map, before or after:
    /// where its arrow starts.
    pub fn cell_centre(&self, camera: usize, after: bool, index: [usize; 3]) -> (f64, f64) {
        let (x, y) = self.panel(camera, index[2], after);
        let c = self.cell_px as f64;
        let row = self.grid[1].saturating_sub(1 + index[1]);
        (
            x as f64 + (index[0] as f64 + 0.5) * c,
            y as f64 + (row as f64 + 0.5) * c,
        )
    }

    /// Where the arrow of a cell whose mean disparity vector is
    /// (`dx`, `dy`) px ends.
    pub fn arrow_tip(
        &self,
        camera: usize,
        after: bool,
        index: [usize; 3],
        (dx, dy): (f64, f64),
    ) -> (f64, f64) {
        let (x, y) = self.cell_centre(camera, after, index);
        (
            x + self.arrow_scale * finite(dx),
            y + self.arrow_scale * finite(dy),
        )
    }
}

fn finite(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

fn mean_length(cell: &Cell) -> f64 {
    finite(cell.mean_dx_px).hypot(finite(cell.mean_dy_px))
}

/// Draws the disparity maps of `report` on `canvas`, laid out by
/// `layout` ([`DisparityLayout::of`] the same maps).
pub fn draw_disparity(canvas: &mut dyn Draw, report: &DisparityMaps, layout: &DisparityLayout) {
    let y = draw_header(canvas, report);
    draw_legend(canvas, layout, y);
    draw_layer_headers(canvas, report, layout);
    for (c, camera) in report.cameras.iter().enumerate() {
        let (_, py) = layout.panel(c, 0, false);
        let panel_h = layout.grid[1] as i64 * layout.cell_px as i64;
        canvas.text(
            MARGIN as i64,
            py as i64 + panel_h / 2 - text_height(2) as i64 / 2,
            &camera.name,
            2,
            BLACK,
        );
        for (after, map) in [(false, &camera.map_before), (true, &camera.map_after)] {
            draw_map(canvas, layout, (c, after), map);
        }
    }
}

/// The title, each camera's RMS before and after, and how to read the
/// maps; returns the row below them.
fn draw_header(canvas: &mut dyn Draw, report: &DisparityMaps) -> i64 {
    let (m, mut y) = (MARGIN as i64, MARGIN as i64);
    canvas.text(
        m,
        y,
        "Disparity maps, before and after self-calibration",
        2,
        BLACK,
    );
    y += text_height(2) as i64 + 8;
    let stats: Vec<String> = report
        .cameras
        .iter()
        .map(|c| {
            format!(
                "{}: RMS {:.2} → {:.2} px",
                c.name, c.before.rms_px, c.after.rms_px
            )
        })
        .collect();
    canvas.text(m, y, &stats.join("   "), 1, BLACK);
    y += text_height(1) as i64 + 6;
    canvas.text(
        m,
        y,
        "Per sub-volume: arrow = the mean disparity vector in the image (x right, y down),",
        1,
        BLACK,
    );
    y += text_height(1) as i64 + 6;
    canvas.text(
        m,
        y,
        "colour = its length. Cells: the volume's x right, y up.",
        1,
        BLACK,
    );
    y + text_height(1) as i64 + 14
}

/// The arrows' scale bar and the colours' bar, on row `y`.
fn draw_legend(canvas: &mut dyn Draw, layout: &DisparityLayout, y: i64) {
    let m = MARGIN as i64;
    let bar = nice(layout.max_disparity_px);
    let bar_px = bar * layout.arrow_scale;
    canvas.text(m, y, "Scale:", 1, BLACK);
    let x0 = m as f64 + text_width("Scale: ", 1) as f64;
    let yc = y as f64 + (text_height(1) / 2) as f64;
    canvas.arrow((x0, yc), (x0 + bar_px, yc), 2.0, 6.0, ARROW);
    let label = format!("= {} px", format_value(bar));
    canvas.text((x0 + bar_px + 8.0) as i64, y, &label, 1, BLACK);
    let cx = (x0 + bar_px + 8.0) as i64 + text_width(&label, 1) as i64 + 30;
    canvas.text(cx, y, "Length: 0", 1, BLACK);
    let gx = cx + text_width("Length: 0 ", 1) as i64;
    let gw = 160;
    for i in 0..gw {
        canvas.fill_rect(
            gx + i,
            y + 3,
            1,
            text_height(1) as i64 - 6,
            heat(i as f64 / (gw - 1) as f64),
        );
    }
    canvas.text(
        gx + gw + 6,
        y,
        &format!("{} px", format_value(layout.max_disparity_px)),
        1,
        BLACK,
    );
}

/// The columns' headers: the z layers.
fn draw_layer_headers(canvas: &mut dyn Draw, report: &DisparityMaps, layout: &DisparityLayout) {
    let header_y = layout.top as i64 - text_height(1) as i64 - 16;
    for k in 0..layout.grid[2] {
        let (px, _) = layout.panel(0, k, false);
        let z0 = report.volume.min.z
            + k as f64 * (report.volume.max.z - report.volume.min.z) / layout.grid[2] as f64;
        let z1 = z0 + (report.volume.max.z - report.volume.min.z) / layout.grid[2] as f64;
        canvas.text(
            px as i64,
            header_y,
            &format!("z {:.0} to {:.0} mm", z0, z1),
            1,
            BLACK,
        );
    }
}

/// Camera `c`'s map before or `after` self-calibration, one panel per z
/// layer: the panels, the cells coloured by their mean disparity's length,
/// the grid, then the arrows.
fn draw_map(canvas: &mut dyn Draw, layout: &DisparityLayout, (c, after): (usize, bool), map: &Map) {
    let panel_w = layout.grid[0] as i64 * layout.cell_px as i64;
    let panel_h = layout.grid[1] as i64 * layout.cell_px as i64;
    for k in 0..layout.grid[2] {
        let (px, py) = layout.panel(c, k, after);
        canvas.text(
            px as i64,
            py as i64 - text_height(1) as i64 - 4,
            if after { "After" } else { "Before" },
            1,
            BLACK,
        );
        canvas.fill_rect(px as i64, py as i64, panel_w, panel_h, EMPTY);
    }
    let inside = |cell: &&Cell| cell.index.iter().zip(layout.grid).all(|(i, g)| *i < g);
    let half = layout.cell_px as f64 / 2.0;
    for cell in map.cells.iter().filter(inside) {
        let (x, y) = layout.cell_centre(c, after, cell.index);
        canvas.fill_rect(
            (x - half) as i64,
            (y - half) as i64,
            layout.cell_px as i64,
            layout.cell_px as i64,
            heat(mean_length(cell) / layout.max_disparity_px),
        );
    }
    for k in 0..layout.grid[2] {
        let (px, py) = layout.panel(c, k, after);
        for i in 0..=layout.grid[0] as i64 {
            canvas.fill_rect(
                px as i64 + (i * layout.cell_px as i64).min(panel_w - 1),
                py as i64,
                1,
                panel_h,
                GREY,
            );
        }
        for j in 0..=layout.grid[1] as i64 {
            canvas.fill_rect(
                px as i64,
                py as i64 + (j * layout.cell_px as i64).min(panel_h - 1),
                panel_w,
                1,
                GREY,
            );
        }
    }
    let width = if layout.cell_px >= 20 { 2.0 } else { 1.0 };
    let head = (layout.cell_px as f64 * 0.2).max(3.0);
    for cell in map.cells.iter().filter(inside) {
        let from = layout.cell_centre(c, after, cell.index);
        let tip = layout.arrow_tip(c, after, cell.index, (cell.mean_dx_px, cell.mean_dy_px));
        canvas.arrow(from, tip, width, head, ARROW);
    }
}

/// The disparity maps of `report` as a picture's bytes.
pub fn disparity_plot(report: &DisparityMaps, format: PlotFormat) -> Result<Vec<u8>, PlotError> {
    let layout = DisparityLayout::of(report)?;
    render(format, (layout.width, layout.height), |d| {
        draw_disparity(d, report, &layout)
    })
}

/// The disparity maps of a report in memory as a PNG file's bytes (`ptv
/// selfcalibrate --disparity-png`).
pub fn disparity_png(report: &SelfCalibrationReport) -> Result<Vec<u8>, PlotError> {
    disparity_plot(&DisparityMaps::from_report(report)?, PlotFormat::Png)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_layouts_are_errors_not_panics() {
        assert_eq!(
            DisparityLayout::new([4, 4, 4], &[], 1.0),
            Err(DisparityPictureError::NoCameras)
        );
        assert_eq!(
            DisparityLayout::new([4, 0, 4], &["cam1"], 1.0),
            Err(DisparityPictureError::EmptyGrid([4, 0, 4]))
        );
        let error = DisparityLayout::new([64, 64, 64], &["cam1"], 1.0).unwrap_err();
        assert!(
            error.to_string().contains("more than 8000 on a side"),
            "{error}"
        );
        // No disparity at all, or not a number: a unit scale, not a NaN one.
        for max in [0.0, f64::NAN] {
            let layout = DisparityLayout::new([4, 4, 4], &["cam1", "cam2"], max).unwrap();
            assert_eq!(layout.max_disparity_px, 1.0);
            assert!(layout.arrow_scale.is_finite());
        }
    }

    #[test]
    fn every_label_fits_and_none_overlap() {
        // Four cameras on grids from coarse to the finest the picture
        // allows, with a long camera name and large disparities.
        for grid in [[1, 1, 1], [4, 4, 2], [8, 6, 4]] {
            let cells = |scale: f64| Map {
                cells: (0..grid[0] * grid[1] * grid[2])
                    .map(|i| Cell {
                        index: [
                            i % grid[0],
                            (i / grid[0]) % grid[1],
                            i / (grid[0] * grid[1]),
                        ],
                        mean_dx_px: scale * (i as f64).sin(),
                        mean_dy_px: scale * (i as f64).cos(),
                    })
                    .collect(),
            };
            let maps = DisparityMaps {
                volume: serde_json::from_value(serde_json::json!({
                    "min": [-50.0, -50.0, -120.5], "max": [50.0, 50.0, 20.0]
                }))
                .unwrap(),
                grid,
                cameras: ["cam1", "a long camera name 2", "cam3", "cam4"]
                    .into_iter()
                    .map(|name| CameraMaps {
                        name: name.to_owned(),
                        before: Rms { rms_px: 12.345 },
                        after: Rms { rms_px: 0.067 },
                        map_before: cells(12.3),
                        map_after: cells(0.07),
                    })
                    .collect(),
            };
            let layout = DisparityLayout::of(&maps).unwrap();
            let boxes = super::super::TextBoxes::of((layout.width, layout.height), |d| {
                draw_disparity(d, &maps, &layout)
            });
            boxes.assert_fit();
            assert!(
                boxes.has("After") && boxes.has("Before"),
                "{:?}",
                boxes.texts
            );
        }
    }
}
