//! Background images over a recording: the temporal median or minimum of a
//! camera's frames, to subtract before detection (issue 13; the design
//! paper's high-pass filter, section 6.1, removes slow "non-uniformities of
//! the background intensity level", but not static structure brighter than
//! the particles: reflections, windows, models in the flow).
//!
//! A [`BackgroundBuilder`] takes the frames one at a time
//! ([`BackgroundBuilder::add`]) and keeps a bounded amount of state, so
//! that its memory does not depend on how many frames a recording has:
//!
//! - [`BackgroundMode::Min`]: the running per-pixel minimum, one image.
//!   Exact over every frame.
//! - [`BackgroundMode::Median`]: the exact per-pixel median of an evenly
//!   spaced sample of at most `K` frames ([`DEFAULT_MEDIAN_SAMPLE`] = 32,
//!   or [`BackgroundBuilder::with_sample_limit`]). The sample keeps every
//!   `s`-th frame (frames `0, s, 2s, ...` in the order added), starting with
//!   `s = 1`; when `K` frames are kept and another is due, `s` doubles and
//!   the kept frames that are not multiples of the new `s` are dropped, so
//!   between `K/2` and `K` frames spread over the whole recording remain.
//!   Memory: `K` frames (32 x 1.3 MB for 1280x1024 8-bit, 32 x 7.9 MB for
//!   2304x1720 16-bit). The median is the lower median of the sample (its
//!   `floor((n-1)/2)`-th order statistic), always a grey value that some
//!   frame had.
//!
//! Why a sample and not a per-pixel histogram: a histogram is exact over
//! every frame, but costs 256 counters per pixel for 8-bit data (at 16-bit
//! counts, 670 MB for 1280x1024) and 65,536 for 16-bit data, which does
//! not fit; an approximate streaming median (a running estimate nudged
//! towards each new value) has an error that depends on the step and the
//! order of the frames. Tools that compute median backgrounds in practice
//! also take the median of a bounded, evenly spaced subset of a sequence's
//! images (tens to a hundred) rather than of all of them. A particle moves
//! through a pixel in a few frames of a recording, so for every pixel
//! that a particle covers in fewer than half of the sampled frames the
//! sample's median is the static scene's grey value; evenly spaced frames
//! (rather than the first `K`) also follow a slow illumination drift over
//! the whole recording.
//!
//! Deterministic: the same frames in the same order give the same image.

use super::image::{BitDepth, GreyImage, GreyPixels};

/// The default bound `K` on the frames a median keeps (see the module doc).
pub const DEFAULT_MEDIAN_SAMPLE: usize = 32;

/// How a background is computed from frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackgroundMode {
    /// The per-pixel median of an evenly spaced sample of the frames.
    Median,
    /// The per-pixel minimum over every frame.
    Min,
}

/// Why frames do not make a background.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BackgroundError {
    /// A frame's size differs from the background's.
    #[error(
        "frame {frame} is {width}x{height} but the background is {expected_width}x\
         {expected_height}; give frames of one camera only"
    )]
    Size {
        /// The frame (0-based, in the order added).
        frame: usize,
        /// Its width.
        width: u32,
        /// Its height.
        height: u32,
        /// The background's width.
        expected_width: u32,
        /// The background's height.
        expected_height: u32,
    },
    /// A frame's bit depth differs from the background's.
    #[error(
        "frame {frame} has {bits}-bit samples but the background has {expected_bits}; give \
         frames of one camera only"
    )]
    Depth {
        /// The frame (0-based, in the order added).
        frame: usize,
        /// Its bits per sample.
        bits: u32,
        /// The background's.
        expected_bits: u32,
    },
    /// No frame was added.
    #[error("a background needs at least one frame; none was given")]
    NoFrames,
    /// The size is empty or the sample bound too small.
    #[error("{0}")]
    Invalid(String),
}

/// Samples of one frame, in their own width.
#[derive(Clone, Debug)]
enum Samples {
    Eight(Vec<u8>),
    Sixteen(Vec<u16>),
}

impl Samples {
    fn of(image: &GreyImage) -> Samples {
        match image.pixels() {
            GreyPixels::Eight(s) => Samples::Eight(s.clone()),
            GreyPixels::Sixteen(s) => Samples::Sixteen(s.clone()),
        }
    }
}

#[derive(Debug)]
enum State {
    /// The running minimum, once a frame arrived.
    Min(Option<Samples>),
    /// The kept frames (each the `stride`-multiple frame index) and the
    /// stride.
    Median {
        kept: Vec<Samples>,
        stride: usize,
        limit: usize,
    },
}

/// Builds a background from frames streamed one at a time (module doc).
#[derive(Debug)]
pub struct BackgroundBuilder {
    width: u32,
    height: u32,
    depth: BitDepth,
    frames: usize,
    state: State,
}

impl BackgroundBuilder {
    /// A builder for frames of `width` x `height` at `depth`; a median
    /// keeps at most [`DEFAULT_MEDIAN_SAMPLE`] frames.
    pub fn new(mode: BackgroundMode, width: u32, height: u32, depth: BitDepth) -> Self {
        let state = match mode {
            BackgroundMode::Min => State::Min(None),
            BackgroundMode::Median => State::Median {
                kept: Vec::new(),
                stride: 1,
                limit: DEFAULT_MEDIAN_SAMPLE,
            },
        };
        BackgroundBuilder {
            width,
            height,
            depth,
            frames: 0,
            state,
        }
    }

    /// Sets the bound `K` on the frames a median keeps: an even number of
    /// at least 2 (ignored by [`BackgroundMode::Min`]). Call before adding
    /// frames.
    pub fn with_sample_limit(mut self, k: usize) -> Result<Self, BackgroundError> {
        if k < 2 || k % 2 != 0 {
            return Err(BackgroundError::Invalid(format!(
                "the median's sample bound is {k}; give an even number of at least 2"
            )));
        }
        if let State::Median { limit, .. } = &mut self.state {
            *limit = k;
        }
        Ok(self)
    }

    /// The mode.
    pub fn mode(&self) -> BackgroundMode {
        match self.state {
            State::Min(_) => BackgroundMode::Min,
            State::Median { .. } => BackgroundMode::Median,
        }
    }

    /// Adds the next frame; a frame of another size or depth is refused
    /// and leaves the builder as it was.
    pub fn add(&mut self, frame: &GreyImage) -> Result<(), BackgroundError> {
        let index = self.frames;
        if frame.width() != self.width || frame.height() != self.height {
            return Err(BackgroundError::Size {
                frame: index,
                width: frame.width(),
                height: frame.height(),
                expected_width: self.width,
                expected_height: self.height,
            });
        }
        if frame.bit_depth() != self.depth {
            return Err(BackgroundError::Depth {
                frame: index,
                bits: frame.bit_depth().bits(),
                expected_bits: self.depth.bits(),
            });
        }
        match &mut self.state {
            State::Min(None) => self.state = State::Min(Some(Samples::of(frame))),
            State::Min(Some(min)) => match (min, frame.pixels()) {
                (Samples::Eight(m), GreyPixels::Eight(f)) => {
                    m.iter_mut().zip(f).for_each(|(m, &f)| *m = (*m).min(f))
                }
                (Samples::Sixteen(m), GreyPixels::Sixteen(f)) => {
                    m.iter_mut().zip(f).for_each(|(m, &f)| *m = (*m).min(f))
                }
                // The depth was checked above.
                _ => unreachable!("the depth was checked"),
            },
            State::Median {
                kept,
                stride,
                limit,
            } => {
                if index % *stride == 0 {
                    if kept.len() == *limit {
                        // Thin the sample: keep the multiples of 2s. The
                        // kept frames are 0, s, ..., (K-1)s, so every
                        // other one stays, and index = Ks is one (K even).
                        *stride *= 2;
                        let mut i = 0;
                        kept.retain(|_| {
                            let keep = i % 2 == 0;
                            i += 1;
                            keep
                        });
                    }
                    if index % *stride == 0 {
                        kept.push(Samples::of(frame));
                    }
                }
            }
        }
        self.frames += 1;
        Ok(())
    }

    /// The frames added so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The frames a median keeps now (at most its bound); 1 for a minimum
    /// once a frame was added.
    pub fn frames_kept(&self) -> usize {
        match &self.state {
            State::Min(min) => usize::from(min.is_some()),
            State::Median { kept, .. } => kept.len(),
        }
    }

    /// The background.
    pub fn finish(self) -> Result<GreyImage, BackgroundError> {
        let (width, height) = (self.width, self.height);
        let samples = match self.state {
            State::Min(Some(min)) => min,
            State::Min(None) => return Err(BackgroundError::NoFrames),
            State::Median { kept, .. } if kept.is_empty() => return Err(BackgroundError::NoFrames),
            State::Median { kept, .. } => median(&kept),
        };
        let image = match samples {
            Samples::Eight(s) => GreyImage::from_u8(width, height, s),
            Samples::Sixteen(s) => GreyImage::from_u16(width, height, s),
        };
        image.map_err(|e| BackgroundError::Invalid(e.to_string()))
    }
}

/// Pixels per block of the median: the block's samples of every kept
/// frame are copied side by side (at most 32 frames x 4096 x 2 bytes =
/// 256 KiB, in the L2 cache) before each pixel's values are gathered.
const BLOCK: usize = 4096;

/// The per-pixel lower median of the kept frames (not empty, all of one
/// depth and size).
fn median(kept: &[Samples]) -> Samples {
    match &kept[0] {
        Samples::Eight(_) => {
            let frames: Vec<&[u8]> = kept
                .iter()
                .map(|s| match s {
                    Samples::Eight(v) => v.as_slice(),
                    Samples::Sixteen(_) => unreachable!("one depth"),
                })
                .collect();
            Samples::Eight(median_of(&frames))
        }
        Samples::Sixteen(_) => {
            let frames: Vec<&[u16]> = kept
                .iter()
                .map(|s| match s {
                    Samples::Sixteen(v) => v.as_slice(),
                    Samples::Eight(_) => unreachable!("one depth"),
                })
                .collect();
            Samples::Sixteen(median_of(&frames))
        }
    }
}

fn median_of<T: Copy + Ord + Default>(frames: &[&[T]]) -> Vec<T> {
    let n = frames.len();
    let len = frames[0].len();
    let rank = (n - 1) / 2;
    let mut out = vec![T::default(); len];
    let mut block = vec![T::default(); n * BLOCK];
    let mut values = vec![T::default(); n];
    let mut start = 0;
    while start < len {
        let size = BLOCK.min(len - start);
        for (k, frame) in frames.iter().enumerate() {
            block[k * BLOCK..k * BLOCK + size].copy_from_slice(&frame[start..start + size]);
        }
        for (i, out) in out[start..start + size].iter_mut().enumerate() {
            for (k, v) in values.iter_mut().enumerate() {
                *v = block[k * BLOCK + i];
            }
            *out = *values.select_nth_unstable(rank).1;
        }
        start += size;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A static scene (a gradient with a bright "window"), and frames that
    /// add moving bright particles on it.
    fn scene(width: u32, height: u32) -> Vec<u8> {
        (0..height)
            .flat_map(|y| {
                (0..width).map(move |x| {
                    let window = (10..20).contains(&x) && (5..15).contains(&y);
                    if window {
                        230
                    } else {
                        (20 + x + 2 * y) as u8
                    }
                })
            })
            .collect()
    }

    /// Frame `t`: the scene with a 3x3 particle at a position moving with
    /// `t`, a different place in every frame of the first 40.
    fn frame(width: u32, height: u32, t: usize) -> GreyImage {
        let mut pixels = scene(width, height);
        for particle in 0..3 {
            let cx = (t * 3 + particle * 11) as u32 % (width - 3);
            let cy = (t * 2 + particle * 7) as u32 % (height - 3);
            for y in cy..cy + 3 {
                for x in cx..cx + 3 {
                    pixels[(y * width + x) as usize] = 255;
                }
            }
        }
        GreyImage::from_u8(width, height, pixels).unwrap()
    }

    #[test]
    fn the_median_of_a_static_scene_with_moving_particles_is_the_scene() {
        let (w, h) = (40, 30);
        for frames in [5, 31, 32, 33, 100] {
            let mut builder = BackgroundBuilder::new(BackgroundMode::Median, w, h, BitDepth::Eight);
            for t in 0..frames {
                builder.add(&frame(w, h, t)).unwrap();
            }
            assert_eq!(builder.frames(), frames);
            assert!(builder.frames_kept() <= DEFAULT_MEDIAN_SAMPLE);
            let background = builder.finish().unwrap();
            assert_eq!(
                background.pixels(),
                &GreyPixels::Eight(scene(w, h)),
                "{frames} frames"
            );
        }
    }

    #[test]
    fn the_sample_is_evenly_spaced_and_bounded() {
        // Frame t is a flat image of grey t: the kept frames' greys are
        // their indices, so the median tells which were kept.
        let mut builder = BackgroundBuilder::new(BackgroundMode::Median, 2, 2, BitDepth::Sixteen)
            .with_sample_limit(4)
            .unwrap();
        for t in 0..9u16 {
            builder
                .add(&GreyImage::from_u16(2, 2, vec![t; 4]).unwrap())
                .unwrap();
            assert!(builder.frames_kept() <= 4);
        }
        // 0..=8 with K = 4: 0,1,2,3 -> (at 4) 0,2,4 -> 0,2,4,6 -> (at 8) 0,4,8.
        assert_eq!(builder.frames_kept(), 3);
        let background = builder.finish().unwrap();
        assert_eq!(background.pixels(), &GreyPixels::Sixteen(vec![4; 4]));
    }

    #[test]
    fn the_minimum_is_the_per_pixel_minimum_of_every_frame() {
        let frames = [
            vec![5u16, 900, 7, 65535],
            vec![6, 3, 70, 1],
            vec![4, 800, 9, 2],
        ];
        let mut builder = BackgroundBuilder::new(BackgroundMode::Min, 2, 2, BitDepth::Sixteen);
        for f in &frames {
            builder
                .add(&GreyImage::from_u16(2, 2, f.clone()).unwrap())
                .unwrap();
        }
        assert_eq!(builder.frames(), 3);
        let background = builder.finish().unwrap();
        assert_eq!(background.pixels(), &GreyPixels::Sixteen(vec![4, 3, 7, 1]));
    }

    #[test]
    fn a_frame_of_another_size_or_depth_is_refused_and_changes_nothing() {
        let mut builder = BackgroundBuilder::new(BackgroundMode::Median, 4, 3, BitDepth::Eight);
        builder
            .add(&GreyImage::from_u8(4, 3, vec![9; 12]).unwrap())
            .unwrap();
        let error = builder
            .add(&GreyImage::from_u8(3, 4, vec![1; 12]).unwrap())
            .unwrap_err();
        assert!(
            error
                .to_string()
                .contains("frame 1 is 3x4 but the background is 4x3"),
            "{error}"
        );
        let error = builder
            .add(&GreyImage::from_u16(4, 3, vec![1; 12]).unwrap())
            .unwrap_err();
        assert!(
            error.to_string().contains("frame 1 has 16-bit samples"),
            "{error}"
        );
        assert_eq!(builder.frames(), 1);
        let background = builder.finish().unwrap();
        assert_eq!(background.pixels(), &GreyPixels::Eight(vec![9; 12]));
    }

    #[test]
    fn no_frames_is_an_error() {
        for mode in [BackgroundMode::Median, BackgroundMode::Min] {
            let builder = BackgroundBuilder::new(mode, 4, 3, BitDepth::Eight);
            assert_eq!(builder.finish().unwrap_err(), BackgroundError::NoFrames);
        }
        assert!(
            BackgroundBuilder::new(BackgroundMode::Median, 1, 1, BitDepth::Eight)
                .with_sample_limit(3)
                .is_err()
        );
    }

    #[test]
    fn the_mode_reads_and_writes_in_lowercase() {
        assert_eq!(
            serde_json::to_string(&BackgroundMode::Median).unwrap(),
            "\"median\""
        );
        let min: BackgroundMode = serde_json::from_str("\"min\"").unwrap();
        assert_eq!(min, BackgroundMode::Min);
    }
}
