//! Targets: the particle images found in one camera's frame.

use serde::{Deserialize, Serialize};

/// One particle image in a camera frame (OpenPTV's `target`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Target {
    /// Centroid x (pixels, the camera model's convention).
    pub x: f64,
    /// Centroid y (pixels).
    pub y: f64,
    /// Number of pixels (0 when unknown).
    pub n: u32,
    /// Extent in x (pixels; 0 when unknown).
    pub nx: u32,
    /// Extent in y (pixels; 0 when unknown).
    pub ny: u32,
    /// Sum of grey values (0 when unknown).
    pub sumg: u64,
}
