//! The plots' text: DejaVu Sans (`assets/fonts/DejaVuSans.ttf`, the
//! Bitstream Vera licence with DejaVu's changes in the public domain, in
//! `assets/fonts/LICENSE-DejaVu.txt`), built into the binary with
//! `include_bytes!` and rasterised by `ab_glyph` (anti-aliased outlines,
//! the font's kerning). Nothing is loaded at build or run time: no font
//! file beside the binary, no system font, no download.
//!
//! Sizes: a text's `scale` is a size class, 1 for labels (14 px, about
//! 10 px capitals, the size of a browser's small print), 2 for titles
//! (22 px) and so on by 8 px. A line of text is [`line_height`] tall from
//! its top: the font's ascent above the baseline and its descent below,
//! so that every glyph's ink (accents and descenders too) lies within
//! the line's box.

use std::sync::OnceLock;

use ab_glyph::{point, Font, FontRef, GlyphId, OutlinedGlyph, PxScale, ScaleFont};

/// The font file.
static DEJAVU_SANS: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// The parsed font (parsed once: a table lookup, no copy).
fn font() -> &'static FontRef<'static> {
    static FONT: OnceLock<FontRef<'static>> = OnceLock::new();
    FONT.get_or_init(|| {
        // The file is part of the binary and checked by the tests below:
        // it cannot fail at run time unless the build embedded another.
        FontRef::try_from_slice(DEJAVU_SANS).expect("the embedded DejaVu Sans parses")
    })
}

/// The font size (pixels per em) of size class `scale`.
pub fn px(scale: u32) -> f32 {
    6.0 + 8.0 * scale.max(1) as f32
}

/// The height of a line of text at `scale` (pixels): ascent plus descent,
/// rounded up.
pub fn line_height(scale: u32) -> u32 {
    let scaled = font().as_scaled(PxScale::from(px(scale)));
    (scaled.ascent() - scaled.descent() + 2.0 * headroom(scale)).ceil() as u32
}

/// Room above the font's ascent (and below its descent) in a line: a
/// capital's ring or accent (Å, É) reaches a little above the ascent.
fn headroom(scale: u32) -> f32 {
    (0.06 * px(scale)).ceil()
}

/// The glyphs of `text` and where each starts along the line (pixels
/// from the text's left edge), with the advance of the whole text.
fn layout(text: &str, scale: u32) -> (Vec<(GlyphId, f32)>, f32) {
    let scaled = font().as_scaled(PxScale::from(px(scale)));
    let mut caret = 0.0f32;
    let mut previous: Option<GlyphId> = None;
    let mut glyphs = Vec::with_capacity(text.len());
    for c in text.chars() {
        let c = if c.is_control() { ' ' } else { c };
        let id = scaled.glyph_id(c);
        if let Some(previous) = previous {
            caret += scaled.kern(previous, id);
        }
        glyphs.push((id, caret));
        caret += scaled.h_advance(id);
        previous = Some(id);
    }
    (glyphs, caret)
}

/// The width of `text` at `scale` (pixels, its advance rounded up).
pub fn width(text: &str, scale: u32) -> u32 {
    layout(text, scale).1.ceil() as u32
}

/// The outlines of `text` drawn with its line's top-left corner at
/// (`x`, `y`): glyphs without ink (spaces) are left out.
pub fn outlines(text: &str, x: f32, y: f32, scale: u32) -> Vec<OutlinedGlyph> {
    let size = PxScale::from(px(scale));
    let baseline = y + ascent(scale);
    layout(text, scale)
        .0
        .into_iter()
        .filter_map(|(id, dx)| {
            font().outline_glyph(id.with_scale_and_position(size, point(x + dx, baseline)))
        })
        .collect()
}

/// The box of the pixels that `text` at (`x`, `y`) inks: (left, top,
/// right, bottom), right and bottom exclusive; `None` for text without
/// ink.
pub fn ink_bounds(text: &str, x: f32, y: f32, scale: u32) -> Option<(f32, f32, f32, f32)> {
    outlines(text, x, y, scale)
        .iter()
        .map(OutlinedGlyph::px_bounds)
        .map(|b| (b.min.x, b.min.y, b.max.x, b.max.y))
        .reduce(|a, b| (a.0.min(b.0), a.1.min(b.1), a.2.max(b.2), a.3.max(b.3)))
}

/// The SVG font stack: DejaVu Sans where the viewer has it (the widths
/// then agree with the PNG's), else a near one; `textLength` keeps the
/// layout whichever is used.
pub const SVG_FAMILY: &str = "'DejaVu Sans', Verdana, sans-serif";

/// The baseline at `scale`: pixels from a line's top.
pub fn ascent(scale: u32) -> f32 {
    font().as_scaled(PxScale::from(px(scale))).ascent() + headroom(scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_font_parses_and_has_the_plots_characters() {
        // Every character the plots write (labels, units, sigma, minus,
        // times) has its own glyph, not the font's "missing" box.
        for c in "AZaz09 .,:;()[]%+-−/×σ₀µ·…≤≥'\"_=".chars() {
            assert_ne!(font().glyph_id(c), GlyphId(0), "{c:?} has no glyph");
        }
        assert_eq!(px(1), 14.0);
        assert_eq!(px(2), 22.0);
    }

    #[test]
    fn ink_lies_within_the_line_and_the_width() {
        for scale in [1, 2, 3] {
            for text in ["Sequence 12, frame 3", "Ågjpqy|(ÉÇ)", "σ₀ 0.05 px", "W"] {
                let (l, t, r, b) = ink_bounds(text, 10.0, 20.0, scale).unwrap();
                assert!(l >= 9.0 && t >= 20.0, "{text} at {scale}: {l} {t}");
                let w = width(text, scale) as f32;
                assert!(r <= 10.0 + w + 1.0, "{text} at {scale}: {r} > {}", 10.0 + w);
                let h = line_height(scale) as f32;
                assert!(b <= 20.0 + h, "{text} at {scale}: {b} > {}", 20.0 + h);
            }
        }
        assert!(ink_bounds("   ", 0.0, 0.0, 1).is_none());
        // Kerning and proportional widths: "ii" is narrower than "WW".
        assert!(width("ii", 1) * 2 < width("WW", 1));
    }
}
