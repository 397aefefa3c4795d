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
//!
//! PNG's ancillary chunks that hold compressed data (`iCCP`, `zTXt`,
//! `iTXt`, and `tEXt` with them) are skipped unread, never inflated: a 1 MB
//! `iCCP` chunk can inflate to 1 GiB, and a colour profile or text says
//! nothing the detector uses. PNG is therefore decoded with the `png` crate
//! directly (the `image` crate cannot be told to skip them), with
//! [`PNG_METADATA_BYTES`] for whatever else it buffers (other ancillary
//! chunks, a row); TIFF with `image`'s decoder. Every route decodes here:
//! frames, masks, backgrounds and calibration images in the service, and
//! the command line.
//!
//! Errors: a file that is not an image this program can use (empty, not
//! PNG or TIFF, BigTIFF, colour, grey with alpha, floating point, truncated
//! or corrupt) is [`FormatError::UnsupportedImage`] (the service's 415),
//! whichever step finds it; a readable greyscale image of the wrong size is
//! [`FormatError::Invalid`] (422).

use std::io::{BufRead, BufReader, Cursor, Seek};
use std::path::Path;

use image::codecs::tiff::TiffDecoder;
use image::{ColorType, DynamicImage, ImageDecoder, ImageFormat, Limits};

use super::FormatError;
use crate::photogrammetry::{BitDepth, GreyImage, GreyPixels, MAX_SENSOR_PIXELS, MAX_SENSOR_SIDE};

/// The most the image decoder may allocate at once: the largest allowed
/// 16-bit image (128 MiB) twice over, for a decoder's buffers beside its
/// output (TIFF strips, PNG rows). A colour image of the largest size
/// would need more, and is refused either way.
pub const MAX_DECODE_BYTES: u64 = 2 * 2 * MAX_SENSOR_PIXELS;

/// What the PNG decoder may allocate besides the image itself: the
/// ancillary chunks it reads (`eXIf` and the small fixed-size ones; the
/// compressed ones are skipped unread) and its row buffers (a row of the
/// widest sensor is at most 128 KiB). 16 MiB, far more than a camera's PNG
/// carries.
pub const PNG_METADATA_BYTES: usize = 16 << 20;

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

/// A PNG or TIFF image whose header has been read, ready for its pixels.
enum Opened<R: BufRead + Seek> {
    /// PNG, with the `png` crate (ancillary chunks that inflate skipped).
    Png(Box<png::Reader<R>>),
    /// TIFF, with `image`'s decoder.
    Tiff(Box<TiffDecoder<R>>),
}

/// Opens a PNG or TIFF image and reads its header: the header, the
/// container's name for messages, and the decoder, ready for the pixels.
fn open_image<R: BufRead + Seek>(
    mut reader: R,
    source: &str,
) -> Result<(ImageHeader, &'static str, Opened<R>), FormatError> {
    let head = reader.fill_buf().map_err(|reason| FormatError::Io {
        path: source.into(),
        reason,
    })?;
    if head.is_empty() {
        return Err(unsupported(
            source,
            "file",
            "the file is empty; expected a greyscale PNG or TIFF image".to_owned(),
        ));
    }
    if is_bigtiff(head) {
        return Err(unsupported(
            source,
            "TIFF",
            "BigTIFF is not supported: save the frame as a classic TIFF or PNG".to_owned(),
        ));
    }
    match sniff(head) {
        Some(ImageFormat::Png) => open_png(reader, source),
        Some(_) => open_tiff(reader, source),
        None => {
            let head: Vec<String> = head.iter().take(4).map(|b| format!("{b:02x}")).collect();
            Err(unsupported(
                source,
                "format",
                format!(
                    "neither a PNG nor a TIFF image (it starts with bytes {}); for raw pixel \
                     data give its width, height and bit depth",
                    head.join(" ")
                ),
            ))
        }
    }
}

/// A file this program cannot use as an image (the service's 415).
fn unsupported(source: &str, location: &str, reason: String) -> FormatError {
    FormatError::UnsupportedImage {
        input: source.to_owned(),
        location: location.to_owned(),
        reason,
    }
}

/// The refusal of an image that is not 8- or 16-bit greyscale: `kind` says
/// what it is, `color` as the decoder names it.
fn not_grey(source: &str, name: &str, kind: &str, color: impl std::fmt::Debug) -> FormatError {
    unsupported(
        source,
        name,
        format!(
            "the image is {kind} ({color:?}); the detector needs 8- or 16-bit greyscale, so \
             convert the frame to greyscale without alpha"
        ),
    )
}

/// Opens a PNG: its header (IHDR) first, whose size is checked before any
/// other chunk is read, then the chunks up to the image data, with those
/// that inflate (`iCCP`, `zTXt`, `iTXt`) and `tEXt` skipped unread.
/// Samples of fewer than 8 bits are expanded to 8, as `image` did.
fn open_png<R: BufRead + Seek>(
    reader: R,
    source: &str,
) -> Result<(ImageHeader, &'static str, Opened<R>), FormatError> {
    let mut decoder = png::Decoder::new_with_limits(
        reader,
        png::Limits {
            bytes: PNG_METADATA_BYTES,
        },
    );
    decoder.set_ignore_iccp_chunk(true);
    decoder.set_ignore_text_chunk(true);
    decoder.set_transformations(png::Transformations::EXPAND);
    let (width, height) = decoder
        .read_header_info()
        .map_err(|error| unsupported(source, "PNG", png_problem(error)))?
        .size();
    check_image_size(width, height, source)?;
    let reader = decoder
        .read_info()
        .map_err(|error| unsupported(source, "PNG", png_problem(error)))?;
    let bit_depth = match reader.output_color_type() {
        (png::ColorType::Grayscale, png::BitDepth::Eight) => BitDepth::Eight,
        (png::ColorType::Grayscale, png::BitDepth::Sixteen) => BitDepth::Sixteen,
        (color, bits) => {
            // Named as `image` names colour types: `Rgb8`, `La16`, ...
            let (kind, name) = match color {
                png::ColorType::GrayscaleAlpha => ("grey with an alpha channel", "La"),
                png::ColorType::Rgb => ("colour", "Rgb"),
                png::ColorType::Rgba => ("colour", "Rgba"),
                png::ColorType::Indexed => ("colour", "Indexed"),
                png::ColorType::Grayscale => ("grey", "L"),
            };
            let name = format!("{name}{}", bits as u8);
            return Err(not_grey(source, "PNG", kind, format_args!("{name}")));
        }
    };
    let header = ImageHeader {
        width,
        height,
        bit_depth,
    };
    Ok((header, "PNG", Opened::Png(Box::new(reader))))
}

/// Opens a TIFF with `image`'s decoder (the `tiff` crate's default limits
/// while it reads the header, [`decoder_limits`] for the pixels).
fn open_tiff<R: BufRead + Seek>(
    reader: R,
    source: &str,
) -> Result<(ImageHeader, &'static str, Opened<R>), FormatError> {
    let name = "TIFF";
    let mut decoder = TiffDecoder::new(reader)
        .map_err(|error| unsupported(source, name, decoding_problem(error, name)))?;
    let color = decoder.color_type();
    let bit_depth = match color {
        ColorType::L8 => BitDepth::Eight,
        ColorType::L16 => BitDepth::Sixteen,
        ColorType::La8 | ColorType::La16 => {
            return Err(not_grey(source, name, "grey with an alpha channel", color))
        }
        ColorType::Rgb32F | ColorType::Rgba32F => {
            return Err(not_grey(source, name, "floating-point colour", color))
        }
        other => return Err(not_grey(source, name, "colour", other)),
    };
    let (width, height) = decoder.dimensions();
    check_image_size(width, height, source)?;
    decoder
        .set_limits(decoder_limits())
        .map_err(|error| unsupported(source, name, decoding_problem(error, name)))?;
    let header = ImageHeader {
        width,
        height,
        bit_depth,
    };
    Ok((header, name, Opened::Tiff(Box::new(decoder))))
}

/// What went wrong decoding a PNG, and what to do.
fn png_problem(error: png::DecodingError) -> String {
    match error {
        png::DecodingError::LimitsExceeded => format!(
            "its chunks need more memory to decode than the limit of {PNG_METADATA_BYTES} bytes \
             (PNG_METADATA_BYTES); save the frame as an 8- or 16-bit greyscale PNG without \
             large metadata"
        ),
        e => format!("cannot be decoded, the file is truncated or corrupt ({e})"),
    }
}

/// What went wrong decoding a TIFF (`name`), and what to do.
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

/// Whether a file's first bytes announce a BigTIFF (64-bit offsets), which
/// is refused by name rather than read.
fn is_bigtiff(bytes: &[u8]) -> bool {
    bytes.starts_with(b"II+\0") || bytes.starts_with(b"MM\0+")
}

/// The container a file's first bytes announce.
fn sniff(bytes: &[u8]) -> Option<ImageFormat> {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Some(ImageFormat::Png)
    } else if [b"II*\0", b"MM\0*"]
        .iter()
        .any(|magic| bytes.starts_with(*magic))
    {
        Some(ImageFormat::Tiff)
    } else {
        None
    }
}

/// A classic greyscale TIFF of strips, uncompressed or LZW without a
/// predictor (what cameras and OpenPTV's recordings write; test_cavity's
/// frames are 171 LZW strips of 6 rows): its size, sample layout and each
/// strip's bytes, sliced from the file. The `tiff` crate reads the tags.
struct PlainStrips<'a> {
    width: usize,
    height: usize,
    /// 1 or 2.
    sample_bytes: usize,
    lzw: bool,
    big_endian: bool,
    /// The rows of every strip but perhaps the last, in bytes.
    strip_bytes: usize,
    inputs: Vec<&'a [u8]>,
}

impl<'a> PlainStrips<'a> {
    /// `None` for any other TIFF, which the general decoder decodes or
    /// reports.
    fn of(bytes: &'a [u8]) -> Option<Self> {
        use tiff::decoder::{ChunkType, Decoder};
        use tiff::tags::{ByteOrder, Tag};

        let mut decoder = Decoder::new(Cursor::new(bytes)).ok()?;
        let (width, height) = decoder.dimensions().ok()?;
        check_image_size(width, height, "").ok()?;
        let unsigned = |decoder: &mut Decoder<_>, tag, default: u64| {
            decoder
                .find_tag_unsigned::<u64>(tag)
                .ok()
                .map(|v| v.unwrap_or(default))
        };
        let bits = unsigned(&mut decoder, Tag::BitsPerSample, 1)?;
        let compression = unsigned(&mut decoder, Tag::Compression, 1)?;
        let plain = unsigned(&mut decoder, Tag::SamplesPerPixel, 1)? == 1
            && unsigned(&mut decoder, Tag::PhotometricInterpretation, 2)? == 1
            && unsigned(&mut decoder, Tag::Predictor, 1)? == 1
            && unsigned(&mut decoder, Tag::FillOrder, 1)? == 1
            && unsigned(&mut decoder, Tag::SampleFormat, 1)? == 1
            && matches!(decoder.get_chunk_type(), ChunkType::Strip)
            && matches!(bits, 8 | 16)
            && matches!(compression, 1 | 5);
        if !plain {
            return None;
        }
        let rows_per_strip = unsigned(&mut decoder, Tag::RowsPerStrip, u64::from(height))?
            .clamp(1, u64::from(height)) as usize;
        let offsets = decoder.get_tag_u64_vec(Tag::StripOffsets).ok()?;
        let counts = decoder.get_tag_u64_vec(Tag::StripByteCounts).ok()?;
        let (width, height) = (width as usize, height as usize);
        let strips = height.div_ceil(rows_per_strip);
        if offsets.len() != strips || counts.len() != strips {
            return None;
        }
        let mut inputs = Vec::with_capacity(strips);
        for (&offset, &count) in offsets.iter().zip(&counts) {
            let start = usize::try_from(offset).ok()?;
            let end = start.checked_add(usize::try_from(count).ok()?)?;
            inputs.push(bytes.get(start..end)?);
        }
        let sample_bytes = (bits / 8) as usize;
        Some(PlainStrips {
            width,
            height,
            sample_bytes,
            lzw: compression == 5,
            big_endian: decoder.byte_order() == ByteOrder::BigEndian,
            strip_bytes: rows_per_strip * width * sample_bytes,
            inputs,
        })
    }

    /// Each strip decoded straight into its rows of the image's samples
    /// (by [`super::lzw`], or copied), in parallel where rayon has idle
    /// threads: no copy beside the output, where the general decoder
    /// reads each strip into its own row buffer first. `None` if a strip
    /// does not decode to exactly its rows; the general path then decodes
    /// or reports it, to the same samples (the unit test
    /// `tiff_strips_decode_as_the_general_decoder_does`).
    fn decode(&self) -> Option<GreyImage> {
        use rayon::prelude::*;
        let inflate = |out: &mut [u8]| -> bool {
            out.par_chunks_mut(self.strip_bytes)
                .zip(&self.inputs)
                .try_for_each_init(super::lzw::Table::new, |table, (rows, input)| {
                    if self.lzw {
                        return super::lzw::decode_strip(input, rows, table).map_err(|_| ());
                    }
                    rows.copy_from_slice(input.get(..rows.len()).ok_or(())?);
                    Ok(())
                })
                .is_ok()
        };
        let (w, h) = (self.width as u32, self.height as u32);
        let pixels = self.width * self.height;
        if self.sample_bytes == 1 {
            let mut samples = vec![0u8; pixels];
            inflate(&mut samples).then_some(())?;
            GreyImage::from_u8(w, h, samples).ok()
        } else {
            let mut samples = vec![0u16; pixels];
            inflate(bytemuck::cast_slice_mut(&mut samples)).then_some(())?;
            for sample in &mut samples {
                *sample = if self.big_endian {
                    u16::from_be(*sample)
                } else {
                    u16::from_le(*sample)
                };
            }
            GreyImage::from_u16(w, h, samples).ok()
        }
    }

    /// Whether [`PlainStrips::decode`] succeeds, without decoding: the
    /// strips' lengths, and each LZW strip's codes by
    /// [`super::lzw::check_strip`].
    fn decodes(&self) -> bool {
        let mut left = self.width * self.height * self.sample_bytes;
        let mut table = super::lzw::Table::new();
        self.inputs.iter().all(|input| {
            let rows = self.strip_bytes.min(left);
            left -= rows;
            if self.lzw {
                super::lzw::check_strip(input, rows, &mut table).is_ok()
            } else {
                input.len() >= rows
            }
        })
    }
}

/// Decodes a greyscale PNG or TIFF file's bytes.
pub fn decode_image(bytes: &[u8], source: &str) -> Result<GreyImage, FormatError> {
    if let Some(image) = plain_strips(bytes).and_then(|strips| strips.decode()) {
        return Ok(image);
    }
    decode_image_general(bytes, source)
}

/// Whether [`decode_image`] succeeds on a file's bytes, with the same
/// error if not; a TIFF of plain strips is checked without being decoded
/// ([`super::lzw::check_strip`]: no memory for its samples, which is up to
/// 128 MiB), anything else is decoded and dropped. What the
/// service checks each upload with before it accepts it.
pub fn check_image(bytes: &[u8], source: &str) -> Result<(), FormatError> {
    if plain_strips(bytes).is_some_and(|strips| strips.decodes()) {
        return Ok(());
    }
    decode_image_general(bytes, source).map(drop)
}

/// The file's strips if it is a classic TIFF of plain strips.
fn plain_strips(bytes: &[u8]) -> Option<PlainStrips<'_>> {
    let tiff = sniff(bytes).is_some_and(|format| format == ImageFormat::Tiff);
    (tiff && !is_bigtiff(bytes))
        .then(|| PlainStrips::of(bytes))
        .flatten()
}

/// [`decode_image`] by the general decoders: the `png` crate's, `image`'s
/// TIFF decoder.
fn decode_image_general(bytes: &[u8], source: &str) -> Result<GreyImage, FormatError> {
    let (header, name, opened) = open_image(Cursor::new(bytes), source)?;
    let ImageHeader {
        width,
        height,
        bit_depth,
    } = header;
    let corrupt = |reason: String| unsupported(source, name, reason);
    let image = match opened {
        Opened::Png(mut reader) => {
            let size = reader
                .output_buffer_size()
                .ok_or_else(|| corrupt(png_problem(png::DecodingError::LimitsExceeded)))?;
            match bit_depth {
                BitDepth::Eight => {
                    let mut samples = vec![0u8; size];
                    reader
                        .next_frame(&mut samples)
                        .map_err(|e| corrupt(png_problem(e)))?;
                    GreyImage::from_u8(width, height, samples)
                }
                BitDepth::Sixteen => {
                    // Read into the samples' own bytes (big-endian in the
                    // file), then turned around in place: one buffer.
                    let mut samples = vec![0u16; size / 2];
                    reader
                        .next_frame(bytemuck::cast_slice_mut(&mut samples))
                        .map_err(|e| corrupt(png_problem(e)))?;
                    for sample in &mut samples {
                        *sample = u16::from_be(*sample);
                    }
                    GreyImage::from_u16(width, height, samples)
                }
            }
        }
        Opened::Tiff(decoder) => match DynamicImage::from_decoder(*decoder)
            .map_err(|error| corrupt(decoding_problem(error, name)))?
        {
            DynamicImage::ImageLuma8(buffer) => {
                GreyImage::from_u8(width, height, buffer.into_raw())
            }
            DynamicImage::ImageLuma16(buffer) => {
                GreyImage::from_u16(width, height, buffer.into_raw())
            }
            other => {
                return Err(corrupt(format!(
                    "decoded as {:?}, not the greyscale its header says",
                    other.color()
                )))
            }
        },
    };
    image.map_err(|e| corrupt(e.to_string()))
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

    /// A TIFF of `samples` (`width` wide, 8- or 16-bit) with `rows` rows a
    /// strip, by the `tiff` crate's encoder.
    fn tiff_of(
        samples: &GreyPixels,
        width: u32,
        rows: u32,
        compression: tiff::encoder::Compression,
        predictor: tiff::tags::Predictor,
    ) -> Vec<u8> {
        use tiff::encoder::{colortype, TiffEncoder};
        let mut bytes = Cursor::new(Vec::new());
        let mut encoder = TiffEncoder::new(&mut bytes)
            .unwrap()
            .with_compression(compression)
            .with_predictor(predictor);
        match samples {
            GreyPixels::Eight(p) => {
                let height = p.len() as u32 / width;
                let mut image = encoder
                    .new_image::<colortype::Gray8>(width, height)
                    .unwrap();
                image.rows_per_strip(rows).unwrap();
                image.write_data(p).unwrap();
            }
            GreyPixels::Sixteen(p) => {
                let height = p.len() as u32 / width;
                let mut image = encoder
                    .new_image::<colortype::Gray16>(width, height)
                    .unwrap();
                image.rows_per_strip(rows).unwrap();
                image.write_data(p).unwrap();
            }
        }
        bytes.into_inner()
    }

    #[test]
    fn tiff_strips_decode_as_the_general_decoder_does() {
        use rand::{Rng, SeedableRng};
        use tiff::encoder::Compression;
        use tiff::tags::Predictor;
        let mut rng = rand::rngs::StdRng::seed_from_u64(30);
        let (width, height) = (37u32, 29u32);
        let n = (width * height) as usize;
        // Noise with runs, so that LZW codes grow past 9 bits.
        let eight: Vec<u8> = (0..n)
            .map(|i| if i % 7 < 3 { 9 } else { rng.random() })
            .collect();
        let sixteen: Vec<u16> = (0..n).map(|_| rng.random()).collect();
        for samples in [GreyPixels::Eight(eight), GreyPixels::Sixteen(sixteen)] {
            for rows in [1, 6, height, 1000] {
                for (compression, name) in [
                    (Compression::Lzw, "LZW"),
                    (Compression::Uncompressed, "uncompressed"),
                ] {
                    let bytes = tiff_of(&samples, width, rows, compression, Predictor::None);
                    let general = decode_image_general(&bytes, "t.tif").unwrap();
                    assert_eq!(general.pixels(), &samples);
                    let strips = plain_strips(&bytes).and_then(|strips| strips.decode());
                    assert_eq!(strips.as_ref(), Some(&general), "{rows} rows, {name}");
                    assert!(plain_strips(&bytes).unwrap().decodes());
                    assert!(check_image(&bytes, "t.tif").is_ok());
                }
                // With a predictor the general decoder decodes it.
                let bytes = tiff_of(&samples, width, 6, Compression::Lzw, Predictor::Horizontal);
                assert!(plain_strips(&bytes)
                    .and_then(|strips| strips.decode())
                    .is_none());
                assert_eq!(decode_image(&bytes, "t.tif").unwrap().pixels(), &samples);
            }
            // A strip cut short: not decoded here, and the general decoder's
            // error stands.
            let bytes = tiff_of(&samples, width, 6, Compression::Lzw, Predictor::None);
            let cut = &bytes[..bytes.len() / 2];
            assert!(plain_strips(cut)
                .and_then(|strips| strips.decode())
                .is_none());
            let general = decode_image_general(cut, "t.tif").unwrap_err().to_string();
            assert_eq!(decode_image(cut, "t.tif").unwrap_err().to_string(), general);
            assert_eq!(check_image(cut, "t.tif").unwrap_err().to_string(), general);
            // A strip's bytes damaged but not cut: the check finds what
            // decoding finds, every time.
            let strips = plain_strips(&bytes).unwrap();
            let offset = strips.inputs[2].as_ptr() as usize - bytes.as_ptr() as usize;
            for flip in 0..strips.inputs[2].len() * 8 {
                let mut damaged = bytes.clone();
                damaged[offset + flip / 8] ^= 1 << (flip % 8);
                let decoded = plain_strips(&damaged).and_then(|strips| strips.decode());
                assert_eq!(plain_strips(&damaged).unwrap().decodes(), decoded.is_some());
                assert_eq!(
                    check_image(&damaged, "t.tif").is_ok(),
                    decode_image(&damaged, "t.tif").is_ok()
                );
            }
        }
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

        // Colour, as anything that is not an image this program can use,
        // is unsupported (the service's 415).
        let colour = probe(&encoded(ImageFormat::Png, Rgb8, 2, 2)).unwrap_err();
        assert!(
            matches!(colour, FormatError::UnsupportedImage { .. }),
            "{colour}"
        );
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

    /// A zlib stream of `mib` MiB of zeros, built without deflating them
    /// all: one MiB deflated with a full flush (which makes the block
    /// independent of what comes before) repeated, then an empty final
    /// block and the Adler-32 of the zeros.
    fn zlib_zeros(mib: u64) -> Vec<u8> {
        let mut deflate = flate2::Compress::new(flate2::Compression::best(), false);
        let mut block = Vec::with_capacity(8 << 10);
        deflate
            .compress_vec(&vec![0; 1 << 20], &mut block, flate2::FlushCompress::Full)
            .unwrap();
        let mut stream = vec![0x78, 0xda];
        for _ in 0..mib {
            stream.extend_from_slice(&block);
        }
        stream.extend_from_slice(&[0x01, 0x00, 0x00, 0xff, 0xff]);
        // Adler-32 of zeros: a = 1, b = the length mod 65521.
        let b = ((mib << 20) % 65_521) as u32;
        stream.extend_from_slice(&((b << 16) | 1).to_be_bytes());
        stream
    }

    /// `png` with a chunk of `kind` and `data` after its header.
    fn with_chunk(png: &[u8], kind: &[u8; 4], data: &[u8]) -> Vec<u8> {
        let mut chunk = (data.len() as u32).to_be_bytes().to_vec();
        chunk.extend_from_slice(kind);
        chunk.extend_from_slice(data);
        let mut crc = flate2::Crc::new();
        crc.update(&chunk[4..]);
        chunk.extend_from_slice(&crc.sum().to_be_bytes());
        // Signature (8) and IHDR (25).
        [&png[..33], &chunk, &png[33..]].concat()
    }

    #[test]
    fn compressed_ancillary_chunks_are_skipped_not_inflated() {
        use crate::photogrammetry::detect::tests::counting::peak_of;
        let plain = encoded(ImageFormat::Png, image::ExtendedColorType::L16, 64, 32);
        let expected = decode_image(&plain, "plain.png").unwrap();
        // 256 MiB each once inflated, 256 KB in the file.
        let zeros = zlib_zeros(256);
        let bombs = [
            (b"iCCP", [&b"icc\0\0"[..], &zeros].concat()),
            (b"zTXt", [&b"Comment\0\0"[..], &zeros].concat()),
            (b"iTXt", [&b"Comment\0\x01\0\0\0"[..], &zeros].concat()),
            (b"tEXt", [&b"Comment\0"[..], &vec![b'a'; 1 << 20]].concat()),
        ];
        for (kind, data) in bombs {
            let bomb = with_chunk(&plain, kind, &data);
            let (peak, decoded) = peak_of(|| decode_image(&bomb, "bomb.png"));
            let name = String::from_utf8_lossy(kind);
            assert_eq!(decoded.unwrap(), expected, "{name}");
            // The file's bytes are the caller's; the decoder holds its
            // buffers and the image (4 KiB), far below one inflated MiB.
            assert!(peak < 1 << 20, "{name}: {peak} bytes");
            let (peak, header) = peak_of(|| probe_image(Cursor::new(&bomb), "bomb.png"));
            assert_eq!(header.unwrap().width, 64);
            assert!(peak < 1 << 20, "{name}: probing took {peak} bytes");
        }
    }

    #[test]
    fn bigtiff_is_refused_by_name() {
        for head in [&b"II+\0\x08\0\0\0"[..], &b"MM\0+\0\x08\0\0"[..]] {
            let mut bytes = head.to_vec();
            bytes.extend_from_slice(&[0xff; 32]);
            let error = decode_image(&bytes, "cam1").unwrap_err();
            assert!(
                matches!(error, FormatError::UnsupportedImage { .. }),
                "{error}"
            );
            assert_eq!(
                error.to_string(),
                "cam1: TIFF: BigTIFF is not supported: save the frame as a classic TIFF or PNG"
            );
        }
    }

    #[test]
    fn every_file_that_does_not_decode_is_unsupported() {
        let png = encoded(ImageFormat::Png, image::ExtendedColorType::L8, 40, 30);
        let tiff = encoded(ImageFormat::Tiff, image::ExtendedColorType::L8, 40, 30);
        let mut bad_crc = png.clone();
        bad_crc[40] ^= 0xff;
        for (bytes, name) in [
            (png[..png.len() / 2].to_vec(), "cut.png"),
            (png[..40].to_vec(), "header.png"),
            (bad_crc, "crc.png"),
            (tiff[..tiff.len() / 2].to_vec(), "cut.tif"),
            (tiff[..10].to_vec(), "header.tif"),
            (b"II*\0\xff\xff\xff\x7f".to_vec(), "ifd.tif"),
            ((0..200u8).map(|b| b.wrapping_mul(37)).collect(), "random"),
            (
                encoded(ImageFormat::Png, image::ExtendedColorType::Rgb8, 4, 4),
                "rgb.png",
            ),
        ] {
            let error = decode_image(&bytes, name).unwrap_err();
            assert!(
                matches!(error, FormatError::UnsupportedImage { .. }),
                "{name}: {error}"
            );
            let checked = check_image(&bytes, name).unwrap_err();
            assert_eq!(checked.to_string(), error.to_string());
            assert!(error.to_string().starts_with(name), "{error}");
        }
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
