//! Pictures of results, as PNG or SVG: a small drawing interface
//! ([`Draw`]: filled rectangles, lines, discs, rings, arrows, text in
//! DejaVu Sans built into the binary ([`font`]), a grey image) with two backends, a raster
//! [`Canvas`] on `image`'s RGB buffer and an [`Svg`] document, and the
//! plots, each written once against [`Draw`]:
//!
//! - [`residuals`]: a calibration's residual vectors over one camera's
//!   sensor, a histogram of their lengths, the check points' errors
//!   (Maas, Gruen, Papantoniou 1993, section 5: the resection's image
//!   residuals `v`, Eq. 1-2 observed minus computed).
//! - [`disparity`]: the self-calibration's disparity maps (Wieneke 2008).
//! - [`overlay`]: a camera image with its detected targets and the
//!   particles' reprojections (Eq. 1-12), coloured by how many cameras
//!   saw each particle; unmatched targets stand out.
//! - [`health`]: a run's calibration health over its frames: each
//!   camera's mean disparity drift, the threshold, the alarms.
//! - [`views`]: a frame's particles and a sequence's trajectories in three
//!   orthographic views (XY, XZ, YZ), trajectories coloured by speed.
//!
//! Drawn with `image` directly rather than a plotting crate: the pictures
//! are panels of markers, arrows, bars and labels, a few hundred lines of
//! drawing; `image` (with its PNG encoder) is already a dependency, so
//! nothing is added to the build but `ab_glyph` (a small pure-Rust
//! rasteriser of TrueType outlines) for the text; the font is a file of
//! the repository built into the binary, so no font file, system font or
//! download is needed at run time (`plotters` would bring its own text
//! stack and want the system's fonts). In SVG, text is `<text>` in the
//! same font and size, stretched to the PNG's width, so the two layouts
//! agree. Outside the pure core
//! (`src/photogrammetry`), which it only reads; no tokio or axum.
//!
//! Coordinates: a point (`f64`) names a pixel's centre at integer values
//! (the raster's pixel (i, j) is centred on (i, j)); rectangles and text
//! start at a pixel's top-left corner. A camera's pixel position
//! (`x`, `y`), whose top-left pixel is centred on (0.5, 0.5)
//! ([`crate::photogrammetry::camera`]), is the point (`x - 0.5`,
//! `y - 0.5`) of a picture drawn at the sensor's scale.

pub mod disparity;
pub mod font;
pub mod health;
pub mod overlay;
pub mod residuals;
pub mod views;

use std::fmt::Write as _;
use std::path::Path;

use image::{Rgb, RgbImage};

use crate::photogrammetry::image::{GreyImage, GreyPixels};

pub use disparity::{disparity_plot, disparity_png, DisparityMaps, DisparityPictureError};

/// A colour.
pub type Colour = Rgb<u8>;

/// White.
pub const WHITE: Colour = Rgb([255, 255, 255]);
/// Black.
pub const BLACK: Colour = Rgb([0, 0, 0]);
/// Light grey, for frames and empty cells.
pub const GREY: Colour = Rgb([200, 200, 200]);

/// The largest side of a picture (pixels): larger ones are refused rather
/// than allocated.
pub const MAX_SIDE: u32 = 8000;

/// A picture's file format.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum PlotFormat {
    /// PNG (RGB, 8 bits a channel).
    #[default]
    Png,
    /// SVG 1.1, text as `<text>`, a camera image embedded as a PNG.
    Svg,
}

impl PlotFormat {
    /// The format a file name asks for by its extension, `.png` or
    /// `.svg` (any case).
    pub fn from_path(path: &Path) -> Result<PlotFormat, PlotError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("png") => Ok(PlotFormat::Png),
            Some("svg") => Ok(PlotFormat::Svg),
            _ => Err(PlotError::Extension(path.display().to_string())),
        }
    }

    /// The HTTP content type.
    pub fn content_type(self) -> &'static str {
        match self {
            PlotFormat::Png => "image/png",
            PlotFormat::Svg => "image/svg+xml",
        }
    }
}

/// Why there is no picture.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// An output file name whose extension names no format.
    #[error("{0}: the picture's format comes from the file name's extension: .png or .svg")]
    Extension(String),
    /// A camera the calibration or report does not have.
    #[error("camera {camera} does not exist; cameras are 0 to {}", cameras.saturating_sub(1))]
    Camera {
        /// The camera asked for.
        camera: usize,
        /// Cameras there are.
        cameras: usize,
    },
    /// The data the picture needs is not in the input.
    #[error("{0}")]
    Missing(String),
    /// An input (report, table) that does not read.
    #[error("{input}: {reason}")]
    Input {
        /// Which input.
        input: String,
        /// What is wrong.
        reason: String,
    },
    /// The picture would be too large.
    #[error("the picture would be {width}x{height} pixels, more than {MAX_SIDE} on a side")]
    TooLarge {
        /// Width.
        width: u64,
        /// Height.
        height: u64,
    },
    /// The disparity maps cannot be drawn.
    #[error(transparent)]
    Disparity(#[from] DisparityPictureError),
    /// The PNG encoder failed.
    #[error("the picture could not be encoded as PNG: {0}")]
    Encode(String),
}

/// A number that may be `null` in a report's JSON (the writers turn
/// non-finite numbers into `null`): NaN then.
pub fn lenient_f64<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    Ok(<Option<f64> as serde::Deserialize>::deserialize(deserializer)?.unwrap_or(f64::NAN))
}

/// Checks a picture's size against [`MAX_SIDE`].
pub fn check_size(width: u64, height: u64) -> Result<(u32, u32), PlotError> {
    if width == 0 || height == 0 || width > MAX_SIDE as u64 || height > MAX_SIDE as u64 {
        Err(PlotError::TooLarge { width, height })
    } else {
        Ok((width as u32, height as u32))
    }
}

/// Draws a picture of `width` x `height` with `draw` in `format`: the
/// file's bytes.
pub fn render(
    format: PlotFormat,
    (width, height): (u32, u32),
    draw: impl FnOnce(&mut dyn Draw),
) -> Result<Vec<u8>, PlotError> {
    match format {
        PlotFormat::Png => {
            let mut canvas = Canvas::new(width, height);
            draw(&mut canvas);
            to_png(&canvas.into_image()).map_err(|e| PlotError::Encode(e.to_string()))
        }
        PlotFormat::Svg => {
            let mut svg = Svg::new(width, height);
            draw(&mut svg);
            Ok(svg.finish().into_bytes())
        }
    }
}

/// What the plots draw with: a raster [`Canvas`] or an [`Svg`] document.
pub trait Draw {
    /// The picture's size (pixels).
    fn size(&self) -> (u32, u32);
    /// Fills the rectangle from (`x`, `y`) of `w` x `h` pixels.
    fn fill_rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour);
    /// The outline of a rectangle, one pixel wide, inside it.
    fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour);
    /// A line from `a` to `b`, `width` pixels wide, round ends.
    fn line(&mut self, a: (f64, f64), b: (f64, f64), width: f64, colour: Colour);
    /// A filled disc of radius `r` around (`cx`, `cy`).
    fn disc(&mut self, cx: f64, cy: f64, r: f64, colour: Colour);
    /// A ring: the circle of radius `r` around (`cx`, `cy`), `width`
    /// pixels wide.
    fn ring(&mut self, cx: f64, cy: f64, r: f64, width: f64, colour: Colour);
    /// Writes `text` with its line's top-left corner at (`x`, `y`), in
    /// size class `scale` (1 labels, 2 titles: [`font::px`]); it takes
    /// [`text_width`] x [`text_height`] pixels.
    fn text(&mut self, x: i64, y: i64, text: &str, scale: u32, colour: Colour);
    /// A grey image with its top-left corner at (`x`, `y`), one pixel a
    /// sample, 16-bit samples shown by their top 8 bits of the image's
    /// depth.
    fn grey_image(&mut self, x: i64, y: i64, image: &GreyImage);

    /// An arrow from `from` to `to` with a head of `head` pixels; an arrow
    /// shorter than a pixel is drawn as a dot.
    fn arrow(&mut self, from: (f64, f64), to: (f64, f64), width: f64, head: f64, colour: Colour) {
        let (dx, dy) = (to.0 - from.0, to.1 - from.1);
        let length = dx.hypot(dy);
        if length.is_nan() || length < 1.0 {
            self.disc(from.0, from.1, width.max(1.5), colour);
            return;
        }
        self.line(from, to, width, colour);
        let head = head.min(length * 0.6);
        let (ux, uy) = (dx / length, dy / length);
        for side in [-1.0, 1.0] {
            // 25 degrees either side of the shaft, backwards.
            let (c, s) = (0.906, 0.423 * side);
            let (bx, by) = (-(ux * c - uy * s), -(uy * c + ux * s));
            self.line(to, (to.0 + head * bx, to.1 + head * by), width, colour);
        }
    }

    /// A "+" around (`cx`, `cy`) whose arms reach from `gap` to `arm`
    /// pixels from it (a hollow centre with `gap` > 0).
    fn cross(&mut self, cx: f64, cy: f64, (gap, arm): (f64, f64), width: f64, colour: Colour) {
        for (dx, dy) in [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)] {
            self.line(
                (cx + gap * dx, cy + gap * dy),
                (cx + arm * dx, cy + arm * dy),
                width,
                colour,
            );
        }
    }
}

/// A raster canvas.
pub struct Canvas {
    image: RgbImage,
}

impl Canvas {
    /// A white canvas of `width` x `height` pixels.
    pub fn new(width: u32, height: u32) -> Canvas {
        Canvas {
            image: RgbImage::from_pixel(width, height, WHITE),
        }
    }

    /// The picture.
    pub fn into_image(self) -> RgbImage {
        self.image
    }

    /// Sets a pixel; coordinates off the canvas are ignored.
    pub fn put(&mut self, x: i64, y: i64, colour: Colour) {
        if x >= 0 && y >= 0 && (x as u64) < self.image.width() as u64 {
            if let Some(p) = self.image.get_pixel_mut_checked(x as u32, y as u32) {
                *p = colour;
            }
        }
    }

    /// Mixes `colour` into a pixel by `coverage` (0 leaves it, 1
    /// replaces it): anti-aliased text; off the canvas is ignored.
    fn blend(&mut self, x: i64, y: i64, colour: Colour, coverage: f32) {
        let coverage = coverage.clamp(0.0, 1.0);
        if x >= 0 && y >= 0 && (x as u64) < self.image.width() as u64 {
            if let Some(p) = self.image.get_pixel_mut_checked(x as u32, y as u32) {
                for (old, new) in p.0.iter_mut().zip(colour.0) {
                    *old = (*old as f32 + (new as f32 - *old as f32) * coverage).round() as u8;
                }
            }
        }
    }

    /// The pixels within `reach` of (`cx`, `cy`) for which `inside` holds
    /// of their distance from it, set to `colour`.
    fn around(
        &mut self,
        cx: f64,
        cy: f64,
        reach: f64,
        colour: Colour,
        inside: impl Fn(f64) -> bool,
    ) {
        if !(cx.is_finite() && cy.is_finite() && reach.is_finite()) {
            return;
        }
        let (w, h) = (self.image.width() as f64, self.image.height() as f64);
        if cx + reach < -1.0 || cy + reach < -1.0 || cx - reach > w || cy - reach > h {
            return;
        }
        let reach = reach.ceil() as i64;
        let (x0, y0) = (cx.round() as i64, cy.round() as i64);
        for yy in y0 - reach..=y0 + reach {
            for xx in x0 - reach..=x0 + reach {
                let (dx, dy) = (xx as f64 - cx, yy as f64 - cy);
                if inside((dx * dx + dy * dy).sqrt()) {
                    self.put(xx, yy, colour);
                }
            }
        }
    }
}

impl Draw for Canvas {
    fn size(&self) -> (u32, u32) {
        self.image.dimensions()
    }

    fn fill_rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour) {
        let (width, height) = (self.image.width() as i64, self.image.height() as i64);
        let (x0, x1) = (x.max(0), x.saturating_add(w).min(width));
        let (y0, y1) = (y.max(0), y.saturating_add(h).min(height));
        for yy in y0..y1 {
            for xx in x0..x1 {
                self.image.put_pixel(xx as u32, yy as u32, colour);
            }
        }
    }

    fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour) {
        self.fill_rect(x, y, w, 1, colour);
        self.fill_rect(x, y + h - 1, w, 1, colour);
        self.fill_rect(x, y, 1, h, colour);
        self.fill_rect(x + w - 1, y, 1, h, colour);
    }

    fn line(&mut self, a: (f64, f64), b: (f64, f64), width: f64, colour: Colour) {
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let length = dx.hypot(dy);
        if !length.is_finite() || length > 4.0 * MAX_SIDE as f64 {
            return;
        }
        let steps = (length * 2.0).ceil().max(1.0) as usize;
        let r = (width / 2.0).max(0.5);
        for s in 0..=steps {
            let t = s as f64 / steps as f64;
            self.disc(a.0 + t * dx, a.1 + t * dy, r, colour);
        }
    }

    fn disc(&mut self, cx: f64, cy: f64, r: f64, colour: Colour) {
        if r < 0.75 {
            // Thinner than a pixel's diagonal: the nearest pixel, so that a
            // thin line's points (half a pixel apart) join up.
            if cx.is_finite() && cy.is_finite() {
                self.put(cx.round() as i64, cy.round() as i64, colour);
            }
            return;
        }
        self.around(cx, cy, r, colour, |d| d <= r);
    }

    fn ring(&mut self, cx: f64, cy: f64, r: f64, width: f64, colour: Colour) {
        let half = width / 2.0;
        self.around(cx, cy, r + half, colour, |d| (d - r).abs() <= half);
    }

    fn text(&mut self, x: i64, y: i64, text: &str, scale: u32, colour: Colour) {
        if x.unsigned_abs() > 4 * MAX_SIDE as u64 || y.unsigned_abs() > 4 * MAX_SIDE as u64 {
            return;
        }
        for glyph in font::outlines(text, x as f32, y as f32, scale) {
            let bounds = glyph.px_bounds();
            let (left, top) = (bounds.min.x as i64, bounds.min.y as i64);
            glyph.draw(|gx, gy, coverage| {
                self.blend(left + gx as i64, top + gy as i64, colour, coverage);
            });
        }
    }

    fn grey_image(&mut self, x: i64, y: i64, image: &GreyImage) {
        let shift = image.bit_depth().bits().saturating_sub(8);
        let (width, height) = (self.image.width() as i64, self.image.height() as i64);
        let w = image.width() as usize;
        for row in 0..image.height() as i64 {
            let yy = y + row;
            if yy < 0 || yy >= height {
                continue;
            }
            let start = row as usize * w;
            let out_row = &mut self.image.as_mut()
                [(yy * width * 3) as usize..((yy + 1) * width * 3) as usize];
            let mut put = |column: usize, v: u8| {
                let xx = x + column as i64;
                if xx >= 0 && xx < width {
                    let k = xx as usize * 3;
                    out_row[k..k + 3].copy_from_slice(&[v, v, v]);
                }
            };
            match image.pixels() {
                GreyPixels::Eight(p) => {
                    for (column, &v) in p[start..start + w].iter().enumerate() {
                        put(column, v);
                    }
                }
                GreyPixels::Sixteen(p) => {
                    for (column, &v) in p[start..start + w].iter().enumerate() {
                        put(column, (v >> shift).min(255) as u8);
                    }
                }
            }
        }
    }
}

/// An SVG document being written.
pub struct Svg {
    size: (u32, u32),
    body: String,
}

/// A colour as `#rrggbb`.
fn hex(colour: Colour) -> String {
    let [r, g, b] = colour.0;
    format!("#{r:02x}{g:02x}{b:02x}")
}

/// A coordinate for SVG: finite, a few decimals.
fn num(v: f64) -> String {
    let v = if v.is_finite() { v } else { 0.0 };
    let text = format!("{v:.2}");
    let text = text.trim_end_matches('0').trim_end_matches('.');
    if text.is_empty() || text == "-" || text == "-0" {
        "0".to_owned()
    } else {
        text.to_owned()
    }
}

impl Svg {
    /// An empty white document of `width` x `height` pixels.
    pub fn new(width: u32, height: u32) -> Svg {
        let mut body = String::new();
        let _ = write!(
            body,
            "<svg xmlns=\"http://www.w3.org/2000/svg\" version=\"1.1\" width=\"{width}\" height=\"{height}\" viewBox=\"0 0 {width} {height}\">\n<rect x=\"0\" y=\"0\" width=\"{width}\" height=\"{height}\" fill=\"#ffffff\"/>\n"
        );
        Svg {
            size: (width, height),
            body,
        }
    }

    /// The document.
    pub fn finish(mut self) -> String {
        self.body.push_str("</svg>\n");
        self.body
    }
}

/// Points are pixel centres: (i, j) is the middle of SVG's square from
/// (i, j) to (i + 1, j + 1).
fn centre(v: f64) -> String {
    num(v + 0.5)
}

impl Draw for Svg {
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn fill_rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour) {
        if w > 0 && h > 0 {
            let _ = writeln!(
                self.body,
                "<rect x=\"{x}\" y=\"{y}\" width=\"{w}\" height=\"{h}\" fill=\"{}\"/>",
                hex(colour)
            );
        }
    }

    fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour) {
        if w > 0 && h > 0 {
            let _ = writeln!(
                self.body,
                "<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"{}\" stroke-width=\"1\"/>",
                x as f64 + 0.5,
                y as f64 + 0.5,
                (w - 1).max(0),
                (h - 1).max(0),
                hex(colour)
            );
        }
    }

    fn line(&mut self, a: (f64, f64), b: (f64, f64), width: f64, colour: Colour) {
        let _ = writeln!(
            self.body,
            "<line x1=\"{}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"{}\" stroke-width=\"{}\" stroke-linecap=\"round\"/>",
            centre(a.0),
            centre(a.1),
            centre(b.0),
            centre(b.1),
            hex(colour),
            num(width.max(1.0))
        );
    }

    fn disc(&mut self, cx: f64, cy: f64, r: f64, colour: Colour) {
        let _ = writeln!(
            self.body,
            "<circle cx=\"{}\" cy=\"{}\" r=\"{}\" fill=\"{}\"/>",
            centre(cx),
            centre(cy),
            num(r.max(0.5)),
            hex(colour)
        );
    }

    fn ring(&mut self, cx: f64, cy: f64, r: f64, width: f64, colour: Colour) {
        let _ = writeln!(
            self.body,
            "<circle cx=\"{}\" cy=\"{}\" r=\"{}\" fill=\"none\" stroke=\"{}\" stroke-width=\"{}\"/>",
            centre(cx),
            centre(cy),
            num(r),
            hex(colour),
            num(width)
        );
    }

    fn text(&mut self, x: i64, y: i64, text: &str, scale: u32, colour: Colour) {
        if text.is_empty() {
            return;
        }
        let mut escaped = String::with_capacity(text.len());
        for c in text.chars() {
            match c {
                '&' => escaped.push_str("&amp;"),
                '<' => escaped.push_str("&lt;"),
                '>' => escaped.push_str("&gt;"),
                '"' => escaped.push_str("&quot;"),
                c if c.is_control() => escaped.push(' '),
                c => escaped.push(c),
            }
        }
        // At the baseline, in the PNG's font and size; stretched to the
        // PNG's advance so that the layout holds in another font.
        let _ = writeln!(
            self.body,
            "<text x=\"{x}\" y=\"{}\" font-family=\"{}\" font-size=\"{}\" textLength=\"{}\" lengthAdjust=\"spacingAndGlyphs\" fill=\"{}\">{escaped}</text>",
            num(y as f64 + font::ascent(scale) as f64),
            font::SVG_FAMILY,
            font::px(scale),
            text_width(text, scale),
            hex(colour)
        );
    }

    fn grey_image(&mut self, x: i64, y: i64, image: &GreyImage) {
        use base64::Engine as _;
        let shift = image.bit_depth().bits().saturating_sub(8);
        let samples: Vec<u8> = match image.pixels() {
            GreyPixels::Eight(p) => p.clone(),
            GreyPixels::Sixteen(p) => p.iter().map(|&v| (v >> shift).min(255) as u8).collect(),
        };
        let Some(grey) = image::GrayImage::from_raw(image.width(), image.height(), samples) else {
            return;
        };
        let mut png = Vec::new();
        let encoder = image::codecs::png::PngEncoder::new_with_quality(
            &mut png,
            image::codecs::png::CompressionType::Fast,
            image::codecs::png::FilterType::Adaptive,
        );
        if image::ImageEncoder::write_image(
            encoder,
            grey.as_raw(),
            grey.width(),
            grey.height(),
            image::ExtendedColorType::L8,
        )
        .is_err()
        {
            return;
        }
        let _ = writeln!(
            self.body,
            "<image x=\"{x}\" y=\"{y}\" width=\"{}\" height=\"{}\" style=\"image-rendering:pixelated\" href=\"data:image/png;base64,{}\"/>",
            image.width(),
            image.height(),
            base64::engine::general_purpose::STANDARD.encode(&png)
        );
    }
}

/// The width of `text` at `scale` (pixels): its advance in the plots'
/// font ([`font`]), rounded up.
pub fn text_width(text: &str, scale: u32) -> u32 {
    font::width(text, scale)
}

/// The height of a line of text at `scale` (pixels): every glyph's ink
/// lies within it, from the line's top.
pub fn text_height(scale: u32) -> u32 {
    font::line_height(scale)
}

/// A light sequential colour map for `t` in [0, 1] (clamped): pale yellow
/// through orange to red, light enough that black arrows and text stay
/// readable on every colour, and never black or grey.
pub fn heat(t: f64) -> Colour {
    const STOPS: [[f64; 3]; 4] = [
        [255.0, 255.0, 204.0],
        [254.0, 217.0, 118.0],
        [253.0, 141.0, 60.0],
        [227.0, 26.0, 28.0],
    ];
    ramp(&STOPS, t)
}

/// Encodes a picture as PNG, with the encoder's fast compression and its
/// "Sub" filter: a 1280x1024 overlay in a few milliseconds rather than
/// tens (the default's adaptive filter and stronger compression), for
/// files about a third larger.
pub fn to_png(image: &RgbImage) -> Result<Vec<u8>, image::ImageError> {
    let mut bytes = Vec::with_capacity(image.as_raw().len() / 4);
    let encoder = image::codecs::png::PngEncoder::new_with_quality(
        &mut bytes,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Sub,
    );
    image::ImageEncoder::write_image(
        encoder,
        image.as_raw(),
        image.width(),
        image.height(),
        image::ExtendedColorType::Rgb8,
    )?;
    Ok(bytes)
}

/// A grey image as an 8-bit grey PNG, a 12 or 16-bit image by the top 8
/// bits of its depth (as [`Draw::grey_image`] shows it).
pub fn grey_png(image: &GreyImage) -> Result<Vec<u8>, image::ImageError> {
    let shift = image.bit_depth().bits().saturating_sub(8);
    let samples: Vec<u8> = match image.pixels() {
        GreyPixels::Eight(p) => p.clone(),
        GreyPixels::Sixteen(p) => p.iter().map(|&v| (v >> shift).min(255) as u8).collect(),
    };
    let mut bytes = Vec::with_capacity(samples.len() / 2);
    let encoder = image::codecs::png::PngEncoder::new_with_quality(
        &mut bytes,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Sub,
    );
    image::ImageEncoder::write_image(
        encoder,
        &samples,
        image.width(),
        image.height(),
        image::ExtendedColorType::L8,
    )?;
    Ok(bytes)
}

/// A round value for a scale bar: 1, 2 or 5 times a power of ten, at
/// most `max` (1 for a `max` that is not positive and finite).
pub fn nice(max: f64) -> f64 {
    if !(max.is_finite() && max > 0.0) {
        return 1.0;
    }
    let power = 10f64.powf(max.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * power)
        .find(|v| *v <= max)
        .unwrap_or(power)
}

/// A value for a label: short, without trailing zeros.
pub fn format_value(v: f64) -> String {
    if !v.is_finite() {
        return "-".to_owned();
    }
    let text = if v.abs() >= 1000.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.3}")
    };
    let text = if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.')
    } else {
        &text
    };
    text.to_owned()
}

/// A dark-to-bright sequential colour map for `t` in [0, 1] (clamped),
/// blue through green to orange and red, readable on white: speeds.
pub fn speed_colour(t: f64) -> Colour {
    const STOPS: [[f64; 3]; 5] = [
        [49.0, 54.0, 149.0],
        [69.0, 117.0, 180.0],
        [26.0, 152.0, 80.0],
        [244.0, 109.0, 67.0],
        [215.0, 25.0, 28.0],
    ];
    ramp(&STOPS, t)
}

fn ramp<const N: usize>(stops: &[[f64; 3]; N], t: f64) -> Colour {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (N - 1) as f64;
    let i = (x.floor() as usize).min(N - 2);
    let f = x - i as f64;
    let mix = |k: usize| (stops[i][k] + f * (stops[i + 1][k] - stops[i][k])).round() as u8;
    Rgb([mix(0), mix(1), mix(2)])
}

/// The colour of a particle seen by `cameras` cameras: 2 orange, 3
/// yellow, 4 green, more cyan (saturated, to stand out on a camera image
/// and on white); fewer than 2 (unknown) grey.
pub fn cameras_colour(cameras: usize) -> Colour {
    match cameras {
        0 | 1 => Rgb([150, 150, 150]),
        2 => Rgb([255, 140, 0]),
        3 => Rgb([225, 190, 0]),
        4 => Rgb([0, 200, 0]),
        _ => Rgb([0, 190, 230]),
    }
}

/// A [`Draw`] that keeps only where text is inked: the plots' tests check
/// with it that every label lies inside its picture and that no two
/// labels overlap.
#[cfg(test)]
pub(crate) struct TextBoxes {
    size: (u32, u32),
    /// Each text and its ink box (left, top, right, bottom; right and
    /// bottom exclusive).
    pub texts: Vec<(String, (f32, f32, f32, f32))>,
}

#[cfg(test)]
impl TextBoxes {
    /// Draws with `draw` on a picture of `size`; the texts written.
    pub fn of(size: (u32, u32), draw: impl FnOnce(&mut dyn Draw)) -> TextBoxes {
        let mut boxes = TextBoxes {
            size,
            texts: Vec::new(),
        };
        draw(&mut boxes);
        boxes
    }

    /// Panics unless every text's ink lies within the picture and no two
    /// texts' boxes overlap.
    pub fn assert_fit(&self) {
        let (w, h) = (self.size.0 as f32, self.size.1 as f32);
        assert!(!self.texts.is_empty(), "no text");
        for (text, (l, t, r, b)) in &self.texts {
            assert!(
                *l >= 0.0 && *t >= 0.0 && *r <= w && *b <= h,
                "{text:?} at ({l}, {t})..({r}, {b}) is clipped by the {w}x{h} picture"
            );
        }
        for (i, (a, p)) in self.texts.iter().enumerate() {
            for (b, q) in &self.texts[i + 1..] {
                let apart = p.2 <= q.0 || q.2 <= p.0 || p.3 <= q.1 || q.3 <= p.1;
                assert!(apart, "{a:?} {p:?} overlaps {b:?} {q:?}");
            }
        }
    }

    /// Whether some text is exactly `text`.
    pub fn has(&self, text: &str) -> bool {
        self.texts.iter().any(|(t, _)| t == text)
    }
}

#[cfg(test)]
impl Draw for TextBoxes {
    fn size(&self) -> (u32, u32) {
        self.size
    }
    fn fill_rect(&mut self, _: i64, _: i64, _: i64, _: i64, _: Colour) {}
    fn rect(&mut self, _: i64, _: i64, _: i64, _: i64, _: Colour) {}
    fn line(&mut self, _: (f64, f64), _: (f64, f64), _: f64, _: Colour) {}
    fn disc(&mut self, _: f64, _: f64, _: f64, _: Colour) {}
    fn ring(&mut self, _: f64, _: f64, _: f64, _: f64, _: Colour) {}
    fn text(&mut self, x: i64, y: i64, text: &str, scale: u32, _: Colour) {
        if let Some(ink) = font::ink_bounds(text, x as f32, y as f32, scale) {
            self.texts.push((text.to_owned(), ink));
        }
    }
    fn grey_image(&mut self, _: i64, _: i64, _: &GreyImage) {}
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_come_from_extensions() {
        assert_eq!(
            PlotFormat::from_path(Path::new("a/b.PNG")).unwrap(),
            PlotFormat::Png
        );
        assert_eq!(
            PlotFormat::from_path(Path::new("b.svg")).unwrap(),
            PlotFormat::Svg
        );
        for bad in ["b.jpg", "b", "b.png.txt"] {
            let error = PlotFormat::from_path(Path::new(bad)).unwrap_err();
            assert!(error.to_string().contains(".png or .svg"), "{error}");
            assert!(error.to_string().starts_with(bad), "{error}");
        }
    }

    #[test]
    fn both_backends_draw_the_same_marks() {
        let draw = |d: &mut dyn Draw| {
            d.ring(20.0, 20.0, 6.0, 2.0, cameras_colour(2));
            d.disc(50.0, 10.0, 3.0, BLACK);
            d.text(2, 30, "A<&>", 1, BLACK);
        };
        let png = render(PlotFormat::Png, (64, 40), draw).unwrap();
        let image = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (64, 40));
        assert_eq!(*image.get_pixel(26, 20), cameras_colour(2));
        assert_eq!(*image.get_pixel(20, 20), WHITE);
        assert_eq!(*image.get_pixel(50, 10), BLACK);
        let svg = String::from_utf8(render(PlotFormat::Svg, (64, 40), draw).unwrap()).unwrap();
        assert!(svg.starts_with("<svg"), "{svg}");
        assert!(svg.trim_end().ends_with("</svg>"));
        assert!(
            svg.contains(
                "<circle cx=\"20.5\" cy=\"20.5\" r=\"6\" fill=\"none\" stroke=\"#ff8c00\""
            ),
            "{svg}"
        );
        assert!(svg.contains(">A&lt;&amp;&gt;</text>"), "{svg}");
        assert!(svg.contains("font-family=\"'DejaVu Sans'"), "{svg}");
    }

    #[test]
    fn text_is_inked_where_its_box_says() {
        let text = "Sequence 3, frame 12: 1,204 particles";
        let (w, h) = (text_width(text, 1), text_height(1));
        let png = render(PlotFormat::Png, (w + 20, h + 20), |d| {
            d.text(10, 10, text, 1, BLACK)
        })
        .unwrap();
        let image = image::load_from_memory(&png).unwrap().to_rgb8();
        let inked: Vec<(u32, u32)> = image
            .enumerate_pixels()
            .filter(|(_, _, p)| **p != WHITE)
            .map(|(x, y, _)| (x, y))
            .collect();
        // Ink, anti-aliased (greys between black and white), all within
        // the text's box.
        assert!(inked.len() > 200, "{} inked pixels", inked.len());
        assert!(image.pixels().any(|p| p.0[0] > 40 && p.0[0] < 215));
        assert!(image.pixels().any(|p| p.0[0] < 40));
        for (x, y) in inked {
            assert!(
                x >= 9 && x < 10 + w + 1 && y >= 10 && y < 10 + h,
                "({x}, {y})"
            );
        }
        // A label of 14 px: capitals about 10 px tall, readable at 100%.
        let (_, top, _, bottom) = font::ink_bounds("H", 0.0, 0.0, 1).unwrap();
        assert!((9.0..=11.0).contains(&(bottom - top)), "{}", bottom - top);
    }

    #[test]
    fn sizes_are_bounded() {
        assert!(check_size(100, 100).is_ok());
        assert!(matches!(
            check_size(9000, 10),
            Err(PlotError::TooLarge { .. })
        ));
        assert!(check_size(0, 10).is_err());
    }

    #[test]
    fn scale_values_are_round() {
        assert_eq!(nice(9.4), 5.0);
        assert_eq!(nice(0.27), 0.2);
        assert_eq!(nice(1.0), 1.0);
        assert_eq!(nice(f64::NAN), 1.0);
        assert_eq!(format_value(0.2), "0.2");
        assert_eq!(format_value(5.0), "5");
        assert_eq!(format_value(1500.0), "1500");
    }
}
