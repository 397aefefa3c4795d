//! Camera images: the files a frame grabber writes, decoded into a
//! [`GreyImage`] for the detector (design paper, section 6.1).
//!
//! - PNG and TIFF, recognised by their first bytes (not their name): 8- or
//!   16-bit greyscale, TIFF uncompressed, LZW- or Deflate-compressed.
//! - Raw buffers: samples row by row with no header, 8-bit or 16-bit
//!   little-endian, of a width and height the caller states
//!   ([`RawLayout`]).
//!
//! Anything else is refused with a message that names the file and the
//! problem: colour or grey-with-alpha images, floating-point samples,
//! truncated or corrupt files, zero sizes, raw buffers whose length does not
//! match the stated size. Whether an image fits a camera's sensor is
//! [`GreyImage::check_sensor`]'s question.

use std::io::Cursor;
use std::path::Path;

use image::{DynamicImage, ImageFormat, ImageReader};

use super::FormatError;
use crate::photogrammetry::{BitDepth, GreyImage};

/// The layout of a raw image buffer, which has no header to say it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RawLayout {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Bits per sample; 16-bit samples are little-endian.
    pub bit_depth: BitDepth,
}

/// Reads an image file: raw samples if `raw` is given, else PNG or TIFF.
pub fn read_image(path: &Path, raw: Option<&RawLayout>) -> Result<GreyImage, FormatError> {
    let bytes = std::fs::read(path).map_err(|reason| FormatError::Io {
        path: path.to_owned(),
        reason,
    })?;
    let source = path.display().to_string();
    match raw {
        Some(layout) => decode_raw(&bytes, layout, &source),
        None => decode_image(&bytes, &source),
    }
}

/// The container a file's first bytes announce.
fn sniff(bytes: &[u8]) -> Option<ImageFormat> {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Some(ImageFormat::Png)
    } else if [b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"]
        .iter()
        .any(|magic| bytes.starts_with(*magic))
    {
        Some(ImageFormat::Tiff)
    } else {
        None
    }
}

/// Decodes a greyscale PNG or TIFF file's bytes.
pub fn decode_image(bytes: &[u8], source: &str) -> Result<GreyImage, FormatError> {
    if bytes.is_empty() {
        return Err(FormatError::invalid(
            source,
            "file",
            "the file is empty; expected a greyscale PNG or TIFF image",
        ));
    }
    let Some(format) = sniff(bytes) else {
        let head: Vec<String> = bytes.iter().take(4).map(|b| format!("{b:02x}")).collect();
        return Err(FormatError::invalid(
            source,
            "format",
            format!(
                "neither a PNG nor a TIFF image (it starts with bytes {}); for raw pixel data \
                 give its width, height and bit depth",
                head.join(" ")
            ),
        ));
    };
    let name = match format {
        ImageFormat::Png => "PNG",
        _ => "TIFF",
    };
    let decoded = ImageReader::with_format(Cursor::new(bytes), format)
        .decode()
        .map_err(|error| {
            let reason = match error {
                image::ImageError::Unsupported(e) => format!(
                    "this kind of {name} is not supported ({e}); save the frame as 8- or 16-bit \
                     greyscale"
                ),
                image::ImageError::Limits(e) => format!("the image is too large to decode ({e})"),
                e => format!("cannot be decoded, the file is truncated or corrupt ({e})"),
            };
            FormatError::invalid(source, name, reason)
        })?;
    let (width, height) = (decoded.width(), decoded.height());
    let image = match decoded {
        DynamicImage::ImageLuma8(buffer) => GreyImage::from_u8(width, height, buffer.into_raw()),
        DynamicImage::ImageLuma16(buffer) => GreyImage::from_u16(width, height, buffer.into_raw()),
        other => {
            let kind = match other {
                DynamicImage::ImageLumaA8(_) | DynamicImage::ImageLumaA16(_) => {
                    "grey with an alpha channel"
                }
                DynamicImage::ImageRgb32F(_) | DynamicImage::ImageRgba32F(_) => {
                    "floating-point colour"
                }
                _ => "colour",
            };
            return Err(FormatError::invalid(
                source,
                name,
                format!(
                    "the image is {kind} ({:?}); the detector needs 8- or 16-bit greyscale, \
                     so convert the frame to greyscale without alpha",
                    other.color()
                ),
            ));
        }
    };
    image.map_err(|e| FormatError::invalid(source, name, e.to_string()))
}

/// Decodes raw samples: `width * height` of them, row by row, 16-bit ones
/// little-endian.
pub fn decode_raw(
    bytes: &[u8],
    layout: &RawLayout,
    source: &str,
) -> Result<GreyImage, FormatError> {
    let RawLayout {
        width,
        height,
        bit_depth,
    } = *layout;
    if width == 0 || height == 0 {
        return Err(FormatError::invalid(
            source,
            "size",
            format!("a raw image of {width}x{height} pixels is empty; give a width and height of at least 1"),
        ));
    }
    let bytes_per_sample: u64 = match bit_depth {
        BitDepth::Eight => 1,
        BitDepth::Sixteen => 2,
    };
    let expected = u64::from(width) * u64::from(height) * bytes_per_sample;
    let actual = bytes.len() as u64;
    if actual != expected {
        return Err(FormatError::invalid(
            source,
            "size",
            format!(
                "a raw {width}x{height} image of {} bits needs {expected} bytes, but the file has \
                 {actual}; check the width, height and bit depth{}",
                bit_depth.bits(),
                if actual < expected {
                    ", or whether the file is truncated"
                } else {
                    ""
                }
            ),
        ));
    }
    let image = match bit_depth {
        BitDepth::Eight => GreyImage::from_u8(width, height, bytes.to_vec()),
        BitDepth::Sixteen => GreyImage::from_u16(
            width,
            height,
            bytes
                .chunks_exact(2)
                .map(|pair| u16::from_le_bytes([pair[0], pair[1]]))
                .collect(),
        ),
    };
    image.map_err(|e| FormatError::invalid(source, "size", e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raw_buffers_need_exactly_their_size() {
        let layout = RawLayout {
            width: 3,
            height: 2,
            bit_depth: BitDepth::Sixteen,
        };
        let bytes = [1, 0, 2, 0, 3, 0, 4, 0, 5, 0, 0, 1];
        let image = decode_raw(&bytes, &layout, "frame.raw").unwrap();
        assert_eq!(image.get(2, 1), Some(256));
        let message = decode_raw(&bytes[..11], &layout, "frame.raw")
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("frame.raw: size: a raw 3x2 image of 16 bits needs 12 bytes")
                && message.contains("truncated"),
            "{message}"
        );
        let empty = RawLayout { width: 0, ..layout };
        assert!(decode_raw(&[], &empty, "x").is_err());
    }

    #[test]
    fn unknown_and_empty_files_are_named() {
        let message = decode_image(b"P5\n3 2\n255\n", "frame.pgm")
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("frame.pgm: format: neither a PNG nor a TIFF"),
            "{message}"
        );
        assert!(decode_image(b"", "e.png")
            .unwrap_err()
            .to_string()
            .contains("empty"));
    }
}
