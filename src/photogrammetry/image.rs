//! Grey images: one camera's frame as the detector sees it.
//!
//! The design paper's cameras deliver 8-bit grey images (section 3); today's
//! cameras also write 10..16-bit data in 16-bit words. A [`GreyImage`] keeps
//! the samples in the width they came in, so the detector works on `u8`
//! data directly and never widens a frame it does not have to.
//!
//! Rows run top to bottom and columns left to right; pixel (column `i`, row
//! `j`) has its centre at (`i + 0.5`, `j + 0.5`) in the pixel coordinates of
//! [`super::camera`]. Decoding files into a `GreyImage` is
//! `crate::formats::image`'s job; this module only checks that the samples
//! fill the stated size and that a frame fits its camera's sensor.

use super::camera::Sensor;

/// How many bits a sample has.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum BitDepth {
    /// 8 bits: grey values 0..=255.
    Eight,
    /// 16 bits: grey values 0..=65535 (also 10-, 12- and 14-bit data in
    /// 16-bit words).
    Sixteen,
}

impl BitDepth {
    /// The bit depth of `bits`, if it is 8 or 16.
    pub fn from_bits(bits: u32) -> Option<BitDepth> {
        match bits {
            8 => Some(BitDepth::Eight),
            16 => Some(BitDepth::Sixteen),
            _ => None,
        }
    }

    /// Bits per sample.
    pub fn bits(self) -> u32 {
        match self {
            BitDepth::Eight => 8,
            BitDepth::Sixteen => 16,
        }
    }

    /// The brightest grey value.
    pub fn max_value(self) -> u16 {
        match self {
            BitDepth::Eight => u16::from(u8::MAX),
            BitDepth::Sixteen => u16::MAX,
        }
    }
}

/// The samples of a grey image, row by row, in their own width.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum GreyPixels {
    /// 8-bit samples.
    Eight(Vec<u8>),
    /// 16-bit samples.
    Sixteen(Vec<u16>),
}

/// A grey image whose samples fill its width and height exactly.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GreyImage {
    width: u32,
    height: u32,
    pixels: GreyPixels,
}

/// Why samples do not make an image.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    /// The width or height is zero.
    #[error("the image is {width}x{height} pixels; both sides must be at least 1 pixel")]
    Empty {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// There are more or fewer samples than the size needs.
    #[error(
        "a {width}x{height} image needs {expected} samples, but {actual} were given; \
         check the width, height and bit depth"
    )]
    WrongLength {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// `width * height`.
        expected: u64,
        /// Samples given.
        actual: u64,
    },
    /// More pixels than detection can index (2^32); camera images are far
    /// smaller (see `camera::MAX_SENSOR_PIXELS`).
    #[error(
        "the image is {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS} an image may have; \
         split it or use a smaller region of interest"
    )]
    TooLarge {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
}

/// The most pixels a [`GreyImage`] may have: detection packs a pixel's index
/// in 32 bits.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 32;

/// An image that does not fit the sensor it is said to come from.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "the image is {width}x{height} pixels but the camera's sensor is \
     {sensor_width}x{sensor_height}; use this camera's images, or a calibration made for them"
)]
pub struct SensorMismatch {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Sensor width.
    pub sensor_width: u32,
    /// Sensor height.
    pub sensor_height: u32,
}

impl SensorMismatch {
    /// Checks that an image of `width` x `height` pixels can come from a
    /// camera with `sensor` (also for an image known only by its header).
    pub fn check(width: u32, height: u32, sensor: &Sensor) -> Result<(), SensorMismatch> {
        if width == sensor.width && height == sensor.height {
            Ok(())
        } else {
            Err(SensorMismatch {
                width,
                height,
                sensor_width: sensor.width,
                sensor_height: sensor.height,
            })
        }
    }
}

fn check_size(width: u32, height: u32, actual: usize) -> Result<(), ImageError> {
    if width == 0 || height == 0 {
        return Err(ImageError::Empty { width, height });
    }
    let expected = u64::from(width) * u64::from(height);
    if expected > MAX_IMAGE_PIXELS {
        return Err(ImageError::TooLarge { width, height });
    }
    // A length that does not fit in u64 cannot equal `expected` either.
    let actual = u64::try_from(actual).unwrap_or(u64::MAX);
    if actual != expected {
        return Err(ImageError::WrongLength {
            width,
            height,
            expected,
            actual,
        });
    }
    Ok(())
}

impl GreyImage {
    /// An 8-bit image from its samples, row by row.
    pub fn from_u8(width: u32, height: u32, pixels: Vec<u8>) -> Result<GreyImage, ImageError> {
        check_size(width, height, pixels.len())?;
        Ok(GreyImage {
            width,
            height,
            pixels: GreyPixels::Eight(pixels),
        })
    }

    /// A 16-bit image from its samples, row by row.
    pub fn from_u16(width: u32, height: u32, pixels: Vec<u16>) -> Result<GreyImage, ImageError> {
        check_size(width, height, pixels.len())?;
        Ok(GreyImage {
            width,
            height,
            pixels: GreyPixels::Sixteen(pixels),
        })
    }

    /// Width in pixels (at least 1).
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels (at least 1).
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The samples.
    pub fn pixels(&self) -> &GreyPixels {
        &self.pixels
    }

    /// Bits per sample.
    pub fn bit_depth(&self) -> BitDepth {
        match self.pixels {
            GreyPixels::Eight(_) => BitDepth::Eight,
            GreyPixels::Sixteen(_) => BitDepth::Sixteen,
        }
    }

    /// The grey value of pixel (column `x`, row `y`), `None` outside the image.
    pub fn get(&self, x: u32, y: u32) -> Option<u16> {
        if x >= self.width || y >= self.height {
            return None;
        }
        // Both are below their side, so the index is below width * height,
        // which is the samples' length.
        let index = y as usize * self.width as usize + x as usize;
        match &self.pixels {
            GreyPixels::Eight(p) => p.get(index).map(|&v| u16::from(v)),
            GreyPixels::Sixteen(p) => p.get(index).copied(),
        }
    }

    /// Checks that this image can come from a camera with `sensor`: the same
    /// width and height. The frame pipeline calls this before detection, so
    /// that targets are never measured in the wrong pixel grid.
    pub fn check_sensor(&self, sensor: &Sensor) -> Result<(), SensorMismatch> {
        SensorMismatch::check(self.width, self.height, sensor)
    }
}

/// Which pixels of a camera's frames detection may use: a fixed mask of
/// parts of the view that never hold particles (walls, windows' edges,
/// reflections that do not move). One bit a pixel.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mask {
    width: u32,
    height: u32,
    /// Bit `i % 64` of word `i / 64` is pixel `i`'s (row by row): 1 = use it.
    bits: Vec<u64>,
}

impl Mask {
    /// The mask of an image: a non-zero pixel is used, a zero one is not (a
    /// black-and-white image painted black where nothing is to be found).
    pub fn from_image(image: &GreyImage) -> Mask {
        let pixels = image.width as usize * image.height as usize;
        let mut bits = vec![0u64; pixels.div_ceil(64)];
        let mut set = |i: usize| bits[i / 64] |= 1 << (i % 64);
        match &image.pixels {
            GreyPixels::Eight(p) => p
                .iter()
                .enumerate()
                .filter(|(_, &v)| v != 0)
                .for_each(|(i, _)| set(i)),
            GreyPixels::Sixteen(p) => p
                .iter()
                .enumerate()
                .filter(|(_, &v)| v != 0)
                .for_each(|(i, _)| set(i)),
        }
        Mask {
            width: image.width,
            height: image.height,
            bits,
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Whether pixel `index` (row by row) is used; false beyond the mask.
    #[inline(always)]
    pub fn uses(&self, index: usize) -> bool {
        self.bits
            .get(index / 64)
            .is_some_and(|word| word >> (index % 64) & 1 == 1)
    }

    /// How many pixels are used.
    pub fn used(&self) -> u64 {
        self.bits.iter().map(|w| u64::from(w.count_ones())).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mask_uses_the_non_zero_pixels() {
        let image =
            GreyImage::from_u16(70, 2, (0..140).map(|i| (i % 3) as u16 * 300).collect()).unwrap();
        let mask = Mask::from_image(&image);
        assert_eq!((mask.width(), mask.height()), (70, 2));
        for i in 0..140 {
            assert_eq!(mask.uses(i), i % 3 != 0, "pixel {i}");
        }
        assert!(!mask.uses(140));
        assert_eq!(mask.used(), 93);
    }

    #[test]
    fn samples_must_fill_the_size() {
        assert!(GreyImage::from_u8(3, 2, vec![0; 6]).is_ok());
        let short = GreyImage::from_u8(3, 2, vec![0; 5]).unwrap_err();
        assert!(short.to_string().contains("needs 6 samples"), "{short}");
        let empty = GreyImage::from_u16(0, 2, vec![]).unwrap_err();
        assert_eq!(
            empty,
            ImageError::Empty {
                width: 0,
                height: 2
            }
        );
    }

    #[test]
    fn images_beyond_two_to_the_32_pixels_are_refused() {
        // Checked before the samples, so no 4 GB vector is needed.
        let error = GreyImage::from_u8(65536, 65537, Vec::new()).unwrap_err();
        assert_eq!(
            error,
            ImageError::TooLarge {
                width: 65536,
                height: 65537
            }
        );
        assert!(error.to_string().contains("65536x65537"), "{error}");
        assert!(matches!(
            GreyImage::from_u8(65536, 65536, Vec::new()),
            Err(ImageError::WrongLength { .. })
        ));
    }

    #[test]
    fn get_reads_row_by_row() {
        let image = GreyImage::from_u16(2, 2, vec![1, 2, 3, 65535]).unwrap();
        assert_eq!(image.get(1, 0), Some(2));
        assert_eq!(image.get(1, 1), Some(65535));
        assert_eq!(image.get(2, 0), None);
        assert_eq!(image.bit_depth(), BitDepth::Sixteen);
    }

    #[test]
    fn sensor_check_names_both_sizes() {
        let sensor = Sensor {
            width: 4,
            height: 3,
            pixel_size_x: 0.01,
            pixel_size_y: 0.01,
        };
        let image = GreyImage::from_u8(4, 3, vec![0; 12]).unwrap();
        assert!(image.check_sensor(&sensor).is_ok());
        let other = GreyImage::from_u8(3, 4, vec![0; 12]).unwrap();
        let message = other.check_sensor(&sensor).unwrap_err().to_string();
        assert!(
            message.contains("3x4") && message.contains("4x3"),
            "{message}"
        );
    }
}
