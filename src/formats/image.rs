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
//!
//! Whether a file is such an image is decided in one place, from its header
//! alone ([`probe_image`], [`probe_raw`], [`read_header`] for a file):
//! decoding starts there, and the service checks uploads with it before it
//! accepts them, without decoding their pixels.
//!
//! Images larger than any sensor may be ([`MAX_SENSOR_SIDE`] per side,
//! [`MAX_SENSOR_PIXELS`] in all) are refused from their header, before a
//! sample is decoded: a small PNG of zeros can declare 22,000 x 22,000
//! pixels. The decoder's own allocation limit ([`MAX_DECODE_BYTES`])
//! backs this up.

use std::io::{BufRead, BufReader, Cursor, Seek};
use std::path::Path;

use image::{ColorType, DynamicImage, ImageDecoder, ImageFormat, ImageReader, Limits};

use super::FormatError;
use crate::photogrammetry::{BitDepth, GreyImage, GreyPixels, MAX_SENSOR_PIXELS, MAX_SENSOR_SIDE};

/// The most the image decoder may allocate at once: the largest allowed
/// 16-bit image (128 MiB) twice over, for a decoder's buffers beside its
/// output (TIFF strips, PNG rows). A colour image of the largest size
/// would need more, and is refused either way.
pub const MAX_DECODE_BYTES: u64 = 2 * 2 * MAX_SENSOR_PIXELS;

/// Checks an image's declared size against the sensor limits, before
/// anything is decoded or copied.
fn check_image_size(width: u32, height: u32, source: &str) -> Result<(), FormatError> {
    let pixels = u64::from(width) * u64::from(height);
    let problem = if width > MAX_SENSOR_SIDE || height > MAX_SENSOR_SIDE {
        format!("more than the limit of {MAX_SENSOR_SIDE} px per side (MAX_SENSOR_SIDE)")
    } else if pixels > MAX_SENSOR_PIXELS {
        format!("{pixels} pixels, more than the limit of {MAX_SENSOR_PIXELS} (64 Mpx, MAX_SENSOR_PIXELS)")
    } else {
        return Ok(());
    };
    Err(FormatError::invalid(
        source,
        "size",
        format!(
            "the image is {width}x{height} pixels, {problem}; no camera's sensor is that large, \
             so give one camera's frame"
        ),
    ))
}

/// The decoder's limits, from the sensor limits.
fn decoder_limits() -> Limits {
    let mut limits = Limits::default();
    limits.max_image_width = Some(MAX_SENSOR_SIDE);
    limits.max_image_height = Some(MAX_SENSOR_SIDE);
    limits.max_alloc = Some(MAX_DECODE_BYTES);
    limits
}

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

/// What an image's header says: a greyscale image of this size and depth.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageHeader {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Bits per sample.
    pub bit_depth: BitDepth,
}

/// Reads the header of an image file without decoding its pixels: raw
/// samples if `raw` is given (the file's length must fit the layout), else
/// PNG or TIFF; `source` names the file in errors.
pub fn read_header(
    path: &Path,
    raw: Option<&RawLayout>,
    source: &str,
) -> Result<ImageHeader, FormatError> {
    let io = |reason| FormatError::Io {
        path: path.to_owned(),
        reason,
    };
    match raw {
        Some(layout) => probe_raw(std::fs::metadata(path).map_err(io)?.len(), layout, source),
        None => probe_image(
            BufReader::new(std::fs::File::open(path).map_err(io)?),
            source,
        ),
    }
}

/// Reads a PNG or TIFF image's header from its first bytes: its size and
/// depth if it is an 8- or 16-bit greyscale image the detector takes, else
/// why not. The pixels are not decoded (a file cut short after its header
/// passes here and fails in [`decode_image`]).
pub fn probe_image<R: BufRead + Seek>(reader: R, source: &str) -> Result<ImageHeader, FormatError> {
    open_image(reader, source).map(|(header, _, _)| header)
}

/// The header of a raw buffer of `len` bytes with `layout`: a size of at
/// least one pixel, and exactly the bytes it needs.
pub fn probe_raw(len: u64, layout: &RawLayout, source: &str) -> Result<ImageHeader, FormatError> {
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
    check_image_size(width, height, source)?;
    let bytes_per_sample: u64 = match bit_depth {
        BitDepth::Eight => 1,
        BitDepth::Sixteen => 2,
    };
    let expected = u64::from(width) * u64::from(height) * bytes_per_sample;
    if len != expected {
        return Err(FormatError::invalid(
            source,
            "size",
            format!(
                "a raw {width}x{height} image of {} bits needs {expected} bytes, but the file has \
                 {len}; check the width, height and bit depth{}",
                bit_depth.bits(),
                if len < expected {
                    ", or whether the file is truncated"
                } else {
                    ""
                }
            ),
        ));
    }
    Ok(ImageHeader {
        width,
        height,
        bit_depth,
    })
}

/// Opens a PNG or TIFF image and reads its header: the header, the
/// container's name for messages, and the decoder, ready for the pixels.
fn open_image<'a, R: BufRead + Seek + 'a>(
    mut reader: R,
    source: &str,
) -> Result<(ImageHeader, &'static str, impl ImageDecoder + 'a), FormatError> {
    let unsupported = |location: &str, reason: String| FormatError::UnsupportedImage {
        input: source.to_owned(),
        location: location.to_owned(),
        reason,
    };
    let head = reader.fill_buf().map_err(|reason| FormatError::Io {
        path: source.into(),
        reason,
    })?;
    if head.is_empty() {
        return Err(unsupported(
            "file",
            "the file is empty; expected a greyscale PNG or TIFF image".to_owned(),
        ));
    }
    let Some(format) = sniff(head) else {
        let head: Vec<String> = head.iter().take(4).map(|b| format!("{b:02x}")).collect();
        return Err(unsupported(
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
    let mut reader = ImageReader::with_format(reader, format);
    // Our own size check first, so that a refusal names the sensor limits;
    // the decoder's limits then bound what it allocates.
    reader.no_limits();
    let mut decoder = reader
        .into_decoder()
        .map_err(|error| unsupported(name, decoding_problem(error, name)))?;
    let color = decoder.color_type();
    let bit_depth = match color {
        ColorType::L8 => BitDepth::Eight,
        ColorType::L16 => BitDepth::Sixteen,
        other => {
            let kind = match other {
                ColorType::La8 | ColorType::La16 => "grey with an alpha channel",
                ColorType::Rgb32F | ColorType::Rgba32F => "floating-point colour",
                _ => "colour",
            };
            return Err(FormatError::invalid(
                source,
                name,
                format!(
                    "the image is {kind} ({other:?}); the detector needs 8- or 16-bit greyscale, \
                     so convert the frame to greyscale without alpha"
                ),
            ));
        }
    };
    let (width, height) = decoder.dimensions();
    check_image_size(width, height, source)?;
    decoder
        .set_limits(decoder_limits())
        .map_err(|error| FormatError::invalid(source, name, decoding_problem(error, name)))?;
    let header = ImageHeader {
        width,
        height,
        bit_depth,
    };
    Ok((header, name, decoder))
}

/// What went wrong decoding a PNG or TIFF (`name`), and what to do.
fn decoding_problem(error: image::ImageError, name: &str) -> String {
    match error {
        image::ImageError::Unsupported(e) => format!(
            "this kind of {name} is not supported ({e}); save the frame as 8- or 16-bit greyscale"
        ),
        image::ImageError::Limits(e) => format!(
            "the image needs more memory to decode than the limit of {MAX_DECODE_BYTES} bytes \
             (MAX_DECODE_BYTES) ({e}); give an 8- or 16-bit greyscale frame of at most \
             {MAX_SENSOR_PIXELS} pixels"
        ),
        e => format!("cannot be decoded, the file is truncated or corrupt ({e})"),
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
    let (ImageHeader { width, height, .. }, name, decoder) =
        open_image(Cursor::new(bytes), source)?;
    let decoded = DynamicImage::from_decoder(decoder)
        .map_err(|error| FormatError::invalid(source, name, decoding_problem(error, name)))?;
    let image = match decoded {
        DynamicImage::ImageLuma8(buffer) => GreyImage::from_u8(width, height, buffer.into_raw()),
        DynamicImage::ImageLuma16(buffer) => GreyImage::from_u16(width, height, buffer.into_raw()),
        other => {
            return Err(FormatError::invalid(
                source,
                name,
                format!(
                    "decoded as {:?}, not the greyscale its header says",
                    other.color()
                ),
            ))
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
    let ImageHeader {
        width,
        height,
        bit_depth,
    } = probe_raw(bytes.len() as u64, layout, source)?;
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

/// A grey image as a PNG of its own bit depth; `source` names it in the
/// error (which the encoder gives only for sizes a `GreyImage` cannot have).
pub fn encode_png(image: &GreyImage, source: &str) -> Result<Vec<u8>, FormatError> {
    use ::image::ImageEncoder;
    let mut bytes = Vec::new();
    let encoder = ::image::codecs::png::PngEncoder::new(&mut bytes);
    let (width, height) = (image.width(), image.height());
    match image.pixels() {
        GreyPixels::Eight(samples) => {
            encoder.write_image(samples, width, height, ::image::ExtendedColorType::L8)
        }
        GreyPixels::Sixteen(samples) => {
            let native: Vec<u8> = samples.iter().flat_map(|v| v.to_ne_bytes()).collect();
            encoder.write_image(&native, width, height, ::image::ExtendedColorType::L16)
        }
    }
    .map_err(|e| FormatError::invalid(source, "image", format!("cannot encode as PNG: {e}")))?;
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1x1 8-bit PNG whose header then declares `width` x `height`
    /// (its one row of data left as it is).
    fn png_declaring(width: u32, height: u32) -> Vec<u8> {
        use ::image::ImageEncoder;
        let mut bytes = Vec::new();
        ::image::codecs::png::PngEncoder::new(&mut bytes)
            .write_image(&[0], 1, 1, ::image::ExtendedColorType::L8)
            .unwrap();
        // Signature (8), IHDR length (4) and type (4), then width, height.
        bytes[16..20].copy_from_slice(&width.to_be_bytes());
        bytes[20..24].copy_from_slice(&height.to_be_bytes());
        let mut crc = flate2::Crc::new();
        crc.update(&bytes[12..29]);
        bytes[29..33].copy_from_slice(&crc.sum().to_be_bytes());
        bytes
    }

    #[test]
    fn images_larger_than_a_sensor_are_refused_from_their_header() {
        // The 22,000 x 22,000 PNG of the issue, in 70 bytes.
        let message = decode_image(&png_declaring(22_000, 22_000), "huge.png")
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("huge.png: size: the image is 22000x22000 pixels")
                && message.contains("MAX_SENSOR_SIDE"),
            "{message}"
        );
        let message = decode_image(&png_declaring(8193, 8192), "many.png")
            .unwrap_err()
            .to_string();
        assert!(message.contains("MAX_SENSOR_PIXELS"), "{message}");
        // At the limits the size passes, and this file fails as truncated.
        for (width, height) in [(8192, 8192), (MAX_SENSOR_SIDE, 4096)] {
            let message = decode_image(&png_declaring(width, height), "at.png")
                .unwrap_err()
                .to_string();
            assert!(message.contains("truncated or corrupt"), "{message}");
        }
        // A real image one past the side limit, and one at it.
        let encode = |width: u32| {
            use ::image::ImageEncoder;
            let mut bytes = Vec::new();
            ::image::codecs::tiff::TiffEncoder::new(std::io::Cursor::new(&mut bytes))
                .write_image(
                    &vec![0; width as usize],
                    width,
                    1,
                    ::image::ExtendedColorType::L8,
                )
                .unwrap();
            bytes
        };
        let wide = decode_image(&encode(MAX_SENSOR_SIDE + 1), "wide.tif").unwrap_err();
        assert!(wide.to_string().contains("16385x1"), "{wide}");
        assert_eq!(
            decode_image(&encode(MAX_SENSOR_SIDE), "ok.tif")
                .unwrap()
                .width(),
            MAX_SENSOR_SIDE
        );
    }

    #[test]
    fn raw_layouts_larger_than_a_sensor_are_refused_before_the_length() {
        let layout = |width, height| RawLayout {
            width,
            height,
            bit_depth: BitDepth::Sixteen,
        };
        let message = decode_raw(&[], &layout(22_000, 22_000), "huge.raw")
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("22000x22000") && message.contains("MAX_SENSOR_SIDE"),
            "{message}"
        );
        let message = decode_raw(&[], &layout(8192, 8193), "many.raw")
            .unwrap_err()
            .to_string();
        assert!(message.contains("MAX_SENSOR_PIXELS"), "{message}");
        let at = vec![0; 2 * MAX_SENSOR_SIDE as usize];
        assert!(decode_raw(&at, &layout(MAX_SENSOR_SIDE, 1), "at.raw").is_ok());
    }

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

    /// A `width` x `height` image of `color` encoded as `format`.
    fn encoded(
        format: ImageFormat,
        color: image::ExtendedColorType,
        width: u32,
        height: u32,
    ) -> Vec<u8> {
        use image::ImageEncoder;
        let bytes_per_pixel = usize::from(color.bits_per_pixel() / 8);
        let samples = vec![7u8; width as usize * height as usize * bytes_per_pixel];
        let mut out = Cursor::new(Vec::new());
        match format {
            ImageFormat::Png => image::codecs::png::PngEncoder::new(&mut out)
                .write_image(&samples, width, height, color)
                .unwrap(),
            _ => image::codecs::tiff::TiffEncoder::new(&mut out)
                .write_image(&samples, width, height, color)
                .unwrap(),
        }
        out.into_inner()
    }

    #[test]
    fn the_header_says_size_and_depth_without_decoding_the_pixels() {
        use image::ExtendedColorType::{Rgb8, L16, L8};
        let probe = |bytes: &[u8]| probe_image(Cursor::new(bytes), "cam0");
        let header = |width, height, bit_depth| ImageHeader {
            width,
            height,
            bit_depth,
        };
        let png8 = encoded(ImageFormat::Png, L8, 5, 3);
        assert_eq!(probe(&png8).unwrap(), header(5, 3, BitDepth::Eight));
        let png16 = encoded(ImageFormat::Png, L16, 4, 2);
        assert_eq!(probe(&png16).unwrap(), header(4, 2, BitDepth::Sixteen));
        let tiff16 = encoded(ImageFormat::Tiff, L16, 6, 4);
        assert_eq!(probe(&tiff16).unwrap(), header(6, 4, BitDepth::Sixteen));
        // The header alone decides: a PNG cut after its header passes here
        // and fails when decoded.
        let cut = &png8[..png8.len() - 20];
        assert_eq!(probe(cut).unwrap(), header(5, 3, BitDepth::Eight));
        assert!(decode_image(cut, "cam0")
            .unwrap_err()
            .to_string()
            .contains("truncated or corrupt"));

        // Colour is refused as a value (the service's 422), anything that
        // is not an image this program opens as unsupported (415).
        let colour = probe(&encoded(ImageFormat::Png, Rgb8, 2, 2)).unwrap_err();
        assert!(matches!(colour, FormatError::Invalid { .. }), "{colour}");
        assert!(
            colour
                .to_string()
                .starts_with("cam0: PNG: the image is colour (Rgb8)"),
            "{colour}"
        );
        for (bytes, message) in [
            (
                &b"this is not an image"[..],
                "cam0: format: neither a PNG nor a TIFF image (it starts with bytes 74 68 69 73)",
            ),
            (&b""[..], "cam0: file: the file is empty"),
            (
                &b"\x89PNG\r\n\x1a\n\xa5\xa5\xa5\xa5"[..],
                "cam0: PNG: cannot be decoded",
            ),
        ] {
            let error = probe(bytes).unwrap_err();
            assert!(
                matches!(error, FormatError::UnsupportedImage { .. })
                    && error.to_string().starts_with(message),
                "{error}"
            );
        }
    }

    #[test]
    fn raw_headers_and_files_are_read_by_their_length() {
        let layout = RawLayout {
            width: 3,
            height: 2,
            bit_depth: BitDepth::Sixteen,
        };
        let header = probe_raw(12, &layout, "cam1").unwrap();
        assert_eq!((header.width, header.height), (3, 2));
        let error = probe_raw(13, &layout, "cam1").unwrap_err();
        assert!(
            error.to_string().starts_with(
                "cam1: size: a raw 3x2 image of 16 bits needs 12 bytes, but the file has 13"
            ),
            "{error}"
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("upload");
        std::fs::write(&path, [0u8; 12]).unwrap();
        assert_eq!(read_header(&path, Some(&layout), "cam1").unwrap(), header);
        std::fs::write(
            &path,
            encoded(ImageFormat::Png, image::ExtendedColorType::L8, 3, 2),
        )
        .unwrap();
        assert_eq!(
            read_header(&path, None, "cam1").unwrap(),
            ImageHeader {
                width: 3,
                height: 2,
                bit_depth: BitDepth::Eight
            }
        );
        let missing = read_header(&dir.path().join("gone"), None, "cam1").unwrap_err();
        assert!(matches!(missing, FormatError::Io { .. }), "{missing}");
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
