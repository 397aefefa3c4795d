//! Pictures of results as PNG: a small raster canvas (filled rectangles,
//! lines, arrows, text in a built-in 5x7 bitmap font, a colour map) on
//! `image`'s RGB buffer, and the plots drawn with it ([`disparity`]: the
//! self-calibration's disparity maps).
//!
//! Drawn with `image` directly rather than a plotting crate: the pictures
//! are panels of cells, arrows and labels, a few hundred lines of drawing;
//! `image` (with its PNG encoder) is already a dependency, so nothing is
//! added to the build, and the built-in font needs no font file, system
//! font or download. Outside the pure core (`src/photogrammetry`), which it
//! only reads.

pub mod disparity;
mod font;

use image::{Rgb, RgbImage};

pub use disparity::{disparity_picture, disparity_png, DisparityPictureError};

/// A colour.
pub type Colour = Rgb<u8>;

/// White.
pub const WHITE: Colour = Rgb([255, 255, 255]);
/// Black.
pub const BLACK: Colour = Rgb([0, 0, 0]);
/// Light grey, for frames and empty cells.
pub const GREY: Colour = Rgb([200, 200, 200]);

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

    /// Fills the rectangle from (`x`, `y`) of `w` x `h` pixels.
    pub fn fill_rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour) {
        for yy in y..y + h {
            for xx in x..x + w {
                self.put(xx, yy, colour);
            }
        }
    }

    /// The outline of a rectangle, one pixel wide.
    pub fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, colour: Colour) {
        self.fill_rect(x, y, w, 1, colour);
        self.fill_rect(x, y + h - 1, w, 1, colour);
        self.fill_rect(x, y, 1, h, colour);
        self.fill_rect(x + w - 1, y, 1, h, colour);
    }

    /// A line from `a` to `b` (pixel centres), `width` pixels wide.
    pub fn line(&mut self, a: (f64, f64), b: (f64, f64), width: f64, colour: Colour) {
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let length = dx.hypot(dy);
        if !length.is_finite() {
            return;
        }
        let steps = (length * 2.0).ceil().max(1.0) as usize;
        let r = (width / 2.0).max(0.5);
        for s in 0..=steps {
            let t = s as f64 / steps as f64;
            let (cx, cy) = (a.0 + t * dx, a.1 + t * dy);
            self.disc(cx, cy, r, colour);
        }
    }

    /// A filled disc of radius `r` around (`cx`, `cy`).
    pub fn disc(&mut self, cx: f64, cy: f64, r: f64, colour: Colour) {
        let reach = r.ceil() as i64;
        let (x0, y0) = (cx.round() as i64, cy.round() as i64);
        for yy in y0 - reach..=y0 + reach {
            for xx in x0 - reach..=x0 + reach {
                if (xx as f64 - cx).hypot(yy as f64 - cy) <= r {
                    self.put(xx, yy, colour);
                }
            }
        }
    }

    /// An arrow from `from` to `to` with a head of `head` pixels; an arrow
    /// shorter than a pixel is drawn as a dot.
    pub fn arrow(
        &mut self,
        from: (f64, f64),
        to: (f64, f64),
        width: f64,
        head: f64,
        colour: Colour,
    ) {
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

    /// Writes `text` with its top-left corner at (`x`, `y`), each font
    /// pixel `scale` pixels.
    pub fn text(&mut self, x: i64, y: i64, text: &str, scale: u32, colour: Colour) {
        let scale = scale.max(1) as i64;
        for (i, c) in text.chars().enumerate() {
            let rows = font::glyph(c);
            let left = x + i as i64 * text_advance(scale as u32) as i64;
            for (row, bits) in rows.iter().enumerate() {
                for column in 0..font::GLYPH.0 as i64 {
                    if bits & (1 << (4 - column)) != 0 {
                        self.fill_rect(
                            left + column * scale,
                            y + row as i64 * scale,
                            scale,
                            scale,
                            colour,
                        );
                    }
                }
            }
        }
    }
}

/// The horizontal advance of one character at `scale`.
pub fn text_advance(scale: u32) -> u32 {
    (font::GLYPH.0 + 1) * scale.max(1)
}

/// The width of `text` at `scale` (pixels).
pub fn text_width(text: &str, scale: u32) -> u32 {
    text.chars().count() as u32 * text_advance(scale)
}

/// The height of a line of text at `scale` (pixels).
pub fn text_height(scale: u32) -> u32 {
    font::GLYPH.1 * scale.max(1)
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
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    let mix = |k: usize| (STOPS[i][k] + f * (STOPS[i + 1][k] - STOPS[i][k])).round() as u8;
    Rgb([mix(0), mix(1), mix(2)])
}

/// Encodes a picture as PNG.
pub fn to_png(image: &RgbImage) -> Result<Vec<u8>, image::ImageError> {
    let mut bytes = Vec::new();
    image.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )?;
    Ok(bytes)
}
