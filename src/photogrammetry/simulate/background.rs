//! Structured backgrounds for rendered images: what real recordings put
//! behind the particles (issue 13). The design paper's pre-processing
//! (section 6.1) names "reflections and the nonuniform intensity profile of
//! the light sheet" as what the high-pass filter must remove; labs also film
//! through models, windows and tank walls that are brighter than the
//! particles. The parts, each optional and composable:
//!
//! - **glare streaks**: long thin bright bands (a Gaussian profile across),
//!   whose centre line wiggles and whose brightness ripples along their
//!   length, like light reflected by a rippled free surface or a wall: every
//!   ripple is a local maximum, which a detector with a small split depth
//!   cuts into many false targets;
//! - **bright static objects**: soft-edged rectangles and ellipses, brighter
//!   than any particle, added until they cover a given share of the image;
//! - **vignetting**: a radial falloff of the whole scene, `1 - v (r/R)²`
//!   with `R` the centre-to-corner distance;
//! - **hot pixels**: isolated pixels stuck at the largest grey value;
//! - **illumination drift**: a gain `1 + a sin(2π f / T)` on the whole
//!   illuminated scene (background and particles) at frame `f`.
//!
//! Everything static is drawn from the background's own seed, not from the
//! frame's random numbers, so every frame of a sequence has the same
//! structure (identical expected values when the drift is off, and the
//! same hot pixels always): a temporal median or minimum removes it, while
//! the particles move and the sensor noise changes from frame to frame.

use rand::Rng;

use super::rng;

/// What to put behind the particles. [`StructuredBackground::none`] adds
/// nothing; [`StructuredBackground::lab`] is a hard but typical scene.
#[derive(Clone, Debug, PartialEq)]
pub struct StructuredBackground {
    /// Seed of the static structure (streaks, objects, hot pixels).
    pub seed: u64,
    /// Number of glare streaks.
    pub glare_streaks: usize,
    /// Peak brightness of a streak's crest (grey levels above the plane
    /// background); the ripples vary it between 30% and 100% of this.
    pub glare_peak: f64,
    /// Standard deviation of a streak's profile across it (px).
    pub glare_width: f64,
    /// Share of the image (0..1) covered by bright static objects.
    pub bright_share: f64,
    /// Brightness of the objects (grey levels above the plane background).
    pub bright_level: f64,
    /// Vignetting: the scene is darker by this fraction in the corners.
    pub vignetting: f64,
    /// Number of hot pixels.
    pub hot_pixels: usize,
    /// Amplitude `a` of the illumination drift (relative gain).
    pub drift: f64,
    /// Period `T` of the drift (frames); 0 turns it off.
    pub drift_period: f64,
}

impl StructuredBackground {
    /// No structure: [`super::render_scene`] then renders exactly what
    /// [`super::render`] does.
    pub fn none() -> StructuredBackground {
        StructuredBackground {
            seed: 0,
            glare_streaks: 0,
            glare_peak: 0.0,
            glare_width: 0.0,
            bright_share: 0.0,
            bright_level: 0.0,
            vignetting: 0.0,
            hot_pixels: 0,
            drift: 0.0,
            drift_period: 0.0,
        }
    }

    /// A hard 8-bit lab scene for [`super::RenderSpec::eight_bit`]
    /// particles: 8 glare streaks of 90 grey levels and 1.5 px across,
    /// bright objects of 170 grey levels over a quarter of the image
    /// (brighter than any particle's brightest pixel: a 2.5 px spot of the
    /// largest peak, 200, centred on a pixel gives it 163; on an object a
    /// particle's core may saturate, as on a real 8-bit camera), 30%
    /// vignetting, one hot pixel per 10,000 pixels of a 1280x1024 frame
    /// (131) and a 2% drift over 200 frames.
    pub fn lab(seed: u64) -> StructuredBackground {
        StructuredBackground {
            seed,
            glare_streaks: 8,
            glare_peak: 90.0,
            glare_width: 1.5,
            bright_share: 0.25,
            bright_level: 170.0,
            vignetting: 0.3,
            hot_pixels: 131,
            drift: 0.02,
            drift_period: 200.0,
        }
    }

    /// The illumination gain at `frame`.
    pub fn gain(&self, frame: u64) -> f64 {
        if self.drift_period > 0.0 && self.drift.is_finite() {
            1.0 + self.drift * (2.0 * std::f64::consts::PI * frame as f64 / self.drift_period).sin()
        } else {
            1.0
        }
    }

    /// The static structure on a `width` x `height` image (sides at least
    /// 1), computed once and shared by every frame.
    pub fn field(&self, width: u32, height: u32) -> BackgroundField {
        let (width, height) = (width.max(1), height.max(1));
        let (w, h) = (width as usize, height as usize);
        let mut rng = rng(self.seed);
        let mut additive = vec![0.0; w * h];
        let finite = |v: f64| if v.is_finite() { v.max(0.0) } else { 0.0 };
        let (glare_peak, glare_width) = (finite(self.glare_peak), finite(self.glare_width));
        if glare_peak > 0.0 && glare_width > 0.0 {
            for _ in 0..self.glare_streaks {
                add_streak(&mut additive, w, h, glare_peak, glare_width, &mut rng);
            }
        }
        let share = finite(self.bright_share).min(1.0);
        let level = finite(self.bright_level);
        let mut bright = vec![0.0f64; w * h];
        let mut covered = 0usize;
        // Enough objects to cover any share; each covers at least ~0.5% of
        // the image, and the loop stops once the share is reached.
        for _ in 0..1000 {
            if covered as f64 >= share * (w * h) as f64 || level <= 0.0 || share <= 0.0 {
                break;
            }
            covered = add_object(&mut bright, w, h, covered, &mut rng);
        }
        for (a, b) in additive.iter_mut().zip(&bright) {
            *a += level * b;
        }
        let vignetting = finite(self.vignetting).min(1.0);
        let gain_map = if vignetting > 0.0 {
            let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
            let corner2 = cx * cx + cy * cy;
            (0..w * h)
                .map(|i| {
                    let dx = (i % w) as f64 + 0.5 - cx;
                    let dy = (i / w) as f64 + 0.5 - cy;
                    1.0 - vignetting * (dx * dx + dy * dy) / corner2
                })
                .collect()
        } else {
            Vec::new()
        };
        let hot = (0..self.hot_pixels.min(w * h))
            .map(|_| rng.random_range(0..w * h))
            .collect();
        BackgroundField {
            width,
            height,
            additive,
            vignette: gain_map,
            hot,
            bright_pixels: covered,
            spec: self.clone(),
        }
    }
}

/// A [`StructuredBackground`] laid out on an image of a given size.
#[derive(Clone, Debug, PartialEq)]
pub struct BackgroundField {
    width: u32,
    height: u32,
    /// Per pixel, grey levels added to the plane background.
    additive: Vec<f64>,
    /// Per pixel, the vignetting factor; empty for none.
    vignette: Vec<f64>,
    /// Row-major indices of the hot pixels.
    hot: Vec<usize>,
    /// Pixels at least half covered by a bright object.
    bright_pixels: usize,
    spec: StructuredBackground,
}

impl BackgroundField {
    /// Image width (px).
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height (px).
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Per pixel (row-major), grey levels the streaks and objects add to
    /// the plane background, before vignetting and drift.
    pub fn additive(&self) -> &[f64] {
        &self.additive
    }

    /// The vignetting factor of pixel `index` (row-major).
    pub fn vignette(&self, index: usize) -> f64 {
        self.vignette.get(index).copied().unwrap_or(1.0)
    }

    /// Row-major indices of the hot pixels.
    pub fn hot_pixels(&self) -> &[usize] {
        &self.hot
    }

    /// The share of the image at least half covered by bright objects.
    pub fn bright_share(&self) -> f64 {
        self.bright_pixels as f64 / self.additive.len() as f64
    }

    /// The background this field was made from.
    pub fn spec(&self) -> &StructuredBackground {
        &self.spec
    }
}

/// `smoothstep` from 0 at `edge0` to 1 at `edge1`.
fn smoothstep(edge0: f64, edge1: f64, x: f64) -> f64 {
    let t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Adds one glare streak: a segment of random position, direction and
/// length (25..60% of the larger side), a Gaussian profile of about
/// `width` across, its centre line wiggling by up to 3 px over 60..150 px,
/// its crest rippling between 30% and 100% of `peak` every 8..20 px, and
/// fading in and out over 30 px at its ends.
fn add_streak(field: &mut [f64], w: usize, h: usize, peak: f64, width: f64, rng: &mut impl Rng) {
    use std::f64::consts::TAU;
    let (cx, cy) = (
        rng.random_range(0.0..w as f64),
        rng.random_range(0.0..h as f64),
    );
    let angle = rng.random_range(0.0..std::f64::consts::PI);
    let half_length = 0.5 * rng.random_range(0.25..0.6) * w.max(h) as f64;
    let sigma = width * rng.random_range(0.7..1.4);
    let ripple = rng.random_range(8.0..20.0);
    let ripple_phase = rng.random_range(0.0..TAU);
    let wiggle = rng.random_range(0.0..3.0);
    let wiggle_period = rng.random_range(60.0..150.0);
    let wiggle_phase = rng.random_range(0.0..TAU);
    let (ux, uy) = (angle.cos(), angle.sin());
    let reach = 4.0 * sigma + wiggle + 1.0;
    let extent_x = half_length * ux.abs() + reach;
    let extent_y = half_length * uy.abs() + reach;
    let x0 = (cx - extent_x).floor().max(0.0) as usize;
    let x1 = ((cx + extent_x).ceil().max(0.0) as usize).min(w);
    let y0 = (cy - extent_y).floor().max(0.0) as usize;
    let y1 = ((cy + extent_y).ceil().max(0.0) as usize).min(h);
    let fade = 30.0f64.min(half_length);
    for y in y0..y1 {
        for x in x0..x1 {
            let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
            let along = dx * ux + dy * uy;
            if along.abs() > half_length {
                continue;
            }
            let across =
                -dx * uy + dy * ux - wiggle * (TAU * along / wiggle_period + wiggle_phase).sin();
            if across.abs() > reach {
                continue;
            }
            let crest = 0.65 + 0.35 * (TAU * along / ripple + ripple_phase).sin();
            let ends = smoothstep(half_length, half_length - fade, along.abs());
            field[y * w + x] +=
                peak * crest * ends * (-across * across / (2.0 * sigma * sigma)).exp();
        }
    }
}

/// Adds one bright object (a rectangle or an ellipse, alternately at
/// random, 8..30% of each side, soft edges 3 px wide) to the coverage map
/// `bright` (0..1 per pixel, objects combined by their maximum), and returns
/// the new count of pixels at least half covered (`covered` before).
fn add_object(bright: &mut [f64], w: usize, h: usize, covered: usize, rng: &mut impl Rng) -> usize {
    let half_w = 0.5 * rng.random_range(0.08..0.3) * w as f64;
    let half_h = 0.5 * rng.random_range(0.08..0.3) * h as f64;
    let (cx, cy) = (
        rng.random_range(0.0..w as f64),
        rng.random_range(0.0..h as f64),
    );
    let ellipse = rng.random_bool(0.5);
    let edge = 3.0;
    let x0 = (cx - half_w - edge).floor().max(0.0) as usize;
    let x1 = ((cx + half_w + edge).ceil().max(0.0) as usize).min(w);
    let y0 = (cy - half_h - edge).floor().max(0.0) as usize;
    let y1 = ((cy + half_h + edge).ceil().max(0.0) as usize).min(h);
    let mut covered = covered;
    for y in y0..y1 {
        for x in x0..x1 {
            let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
            // Signed distance (px, approximately for the ellipse) outside
            // the shape's boundary.
            let outside = if ellipse {
                let r = ((dx / half_w).powi(2) + (dy / half_h).powi(2)).sqrt();
                (r - 1.0) * half_w.min(half_h)
            } else {
                (dx.abs() - half_w).max(dy.abs() - half_h)
            };
            let value = smoothstep(edge / 2.0, -edge / 2.0, outside);
            let pixel = &mut bright[y * w + x];
            if *pixel < 0.5 && value >= 0.5 {
                covered += 1;
            }
            *pixel = pixel.max(value);
        }
    }
    covered
}
