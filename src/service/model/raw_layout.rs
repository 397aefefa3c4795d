//! The raw image layout as stored with a sequence's frames.

use serde::Deserialize;

use crate::formats::image::RawLayout;
use crate::photogrammetry::BitDepth;

/// The raw layout as stored with a frame.
#[derive(Debug, Deserialize, serde::Serialize)]
pub struct StoredRawLayout {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// 8 or 16.
    pub bits: u32,
}

impl StoredRawLayout {
    /// The layout for the decoder.
    pub fn layout(&self) -> Option<RawLayout> {
        Some(RawLayout {
            width: self.width,
            height: self.height,
            bit_depth: BitDepth::from_bits(self.bits)?,
        })
    }
}
