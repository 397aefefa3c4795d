//! Frame numbers in file names and on the command line: [`FramePattern`],
//! a file name with one printf-style frame number (`img/cam1.%d`,
//! `c%05d.tif`), and [`FrameRange`], `FIRST..LAST`.

use std::path::PathBuf;

/// What a pattern without a frame number (no `%d`) means.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WithoutNumber {
    /// An error: the frame number must be placed.
    Refuse,
    /// The frame is appended after a dot, OpenPTV's `base.frame` naming
    /// (`img/cam1` is `img/cam1.10001`).
    AppendAfterDot,
}

/// A file name pattern with one printf-style frame number: `%d`, `%0Nd`
/// (zero padded to N digits), `%Nd` (space padded); `%%` is a percent sign.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FramePattern {
    text: String,
    prefix: String,
    /// Minimum digits and whether padded with zeros (else spaces); `None`:
    /// no `%d`, the frame is appended after a dot.
    number: Option<(usize, bool)>,
    suffix: String,
}

impl FramePattern {
    /// Parses `text`; `without` says what a pattern without `%d` means.
    /// Any other `%` sequence, or two frame numbers, is an error.
    pub fn parse(text: &str, without: WithoutNumber) -> Result<FramePattern, String> {
        let mut prefix: Option<String> = None;
        let mut current = String::new();
        let mut number: Option<(usize, bool)> = None;
        let mut chars = text.chars().peekable();
        while let Some(c) = chars.next() {
            if c != '%' {
                current.push(c);
                continue;
            }
            if chars.peek() == Some(&'%') {
                chars.next();
                current.push('%');
                continue;
            }
            let mut digits = String::new();
            while let Some(&d) = chars.peek().filter(|d| d.is_ascii_digit()) {
                digits.push(d);
                chars.next();
            }
            if chars.next() != Some('d') {
                return Err(format!(
                    "`{text}`: only %d, %0Nd or %Nd (the frame number) and %% may follow a %"
                ));
            }
            if number.is_some() {
                return Err(format!(
                    "`{text}` has two frame numbers; give one %d per pattern"
                ));
            }
            let zeros = digits.starts_with('0');
            let width = digits.parse::<usize>().unwrap_or(0);
            if width > 20 {
                return Err(format!("`{text}`: a frame number of {width} digits"));
            }
            number = Some((width, zeros));
            prefix = Some(std::mem::take(&mut current));
        }
        if number.is_none() && without == WithoutNumber::Refuse {
            return Err(format!(
                "`{text}` has no frame number; put %d (or %05d) where the frame goes, \
                 e.g. img/cam1.%d"
            ));
        }
        Ok(FramePattern {
            text: text.to_owned(),
            prefix: prefix.unwrap_or(current.clone()),
            number,
            suffix: if number.is_some() {
                current
            } else {
                String::new()
            },
        })
    }

    /// The pattern as given.
    pub fn as_str(&self) -> &str {
        &self.text
    }

    /// The name of `frame`.
    pub fn format(&self, frame: u64) -> String {
        let number = match self.number {
            Some((width, true)) => format!("{frame:0width$}"),
            Some((width, false)) => format!("{frame:width$}"),
            None => format!(".{frame}"),
        };
        format!("{}{number}{}", self.prefix, self.suffix)
    }

    /// The file of `frame`.
    pub fn path(&self, frame: u64) -> PathBuf {
        PathBuf::from(self.format(frame))
    }
}

/// Frames `first..=last`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameRange {
    /// The first frame.
    pub first: u64,
    /// The last frame (included).
    pub last: u64,
}

/// The most frames one range holds (a typo guard: `1..100000000`).
pub const MAX_FRAMES: u64 = 10_000_000;

impl FrameRange {
    /// Parses `FIRST..LAST` (both included; `FIRST..=LAST` too) or one
    /// frame `N`; at most [`MAX_FRAMES`] frames. Usable as a clap value
    /// parser.
    pub fn parse(text: &str) -> Result<FrameRange, String> {
        let number = |s: &str| {
            s.trim().parse::<u64>().map_err(|_| {
                format!(
                    "`{s}` is not a frame number in `{text}`; give FIRST..LAST, e.g. 10001..10004"
                )
            })
        };
        let (first, last) = match text.split_once("..") {
            Some((first, last)) => (number(first)?, number(last.trim_start_matches('='))?),
            None => {
                let frame = number(text)?;
                (frame, frame)
            }
        };
        if last < first {
            return Err(format!(
                "the last frame {last} comes before the first {first}"
            ));
        }
        if last - first >= MAX_FRAMES {
            return Err(format!(
                "{} frames; give at most {MAX_FRAMES} at once",
                last - first + 1
            ));
        }
        Ok(FrameRange { first, last })
    }

    /// Whether it lies within `within`, else why not.
    pub fn check_within(&self, within: FrameRange) -> Result<(), String> {
        if self.first < within.first || self.last > within.last {
            return Err(format!(
                "{}..{} is outside the experiment's frames {}..{}",
                self.first, self.last, within.first, within.last
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_put_the_frame_number_in_place() {
        let name = |p: &str, f| {
            FramePattern::parse(p, WithoutNumber::Refuse)
                .unwrap()
                .format(f)
        };
        assert_eq!(name("img/cam1.%d", 10001), "img/cam1.10001");
        assert_eq!(name("c%05d.tif", 42), "c00042.tif");
        assert_eq!(name("c%3d", 7), "c  7");
        assert_eq!(name("100%%_%d.png", 3), "100%_3.png");
        assert_eq!(name("%d", 123456), "123456");
        for bad in ["img/cam1", "a%d%d", "a%s", "a%05x", "a%"] {
            assert!(
                FramePattern::parse(bad, WithoutNumber::Refuse).is_err(),
                "{bad}"
            );
        }
        let openptv = FramePattern::parse("img/cam1", WithoutNumber::AppendAfterDot).unwrap();
        assert_eq!(openptv.format(10001), "img/cam1.10001");
        assert_eq!(openptv.as_str(), "img/cam1");
        let openptv = FramePattern::parse("img/c%05d.tif", WithoutNumber::AppendAfterDot).unwrap();
        assert_eq!(openptv.format(42), "img/c00042.tif");
    }

    #[test]
    fn frame_ranges_include_both_ends() {
        let range = |first, last| FrameRange { first, last };
        assert_eq!(FrameRange::parse("10001..10004"), Ok(range(10001, 10004)));
        assert_eq!(FrameRange::parse("1..=3"), Ok(range(1, 3)));
        assert_eq!(FrameRange::parse("7"), Ok(range(7, 7)));
        assert!(FrameRange::parse("5..3")
            .unwrap_err()
            .contains("comes before"));
        assert!(FrameRange::parse("a..3").is_err());
        assert!(FrameRange::parse("0..99999999").is_err());
        assert!(range(1, 5).check_within(range(1, 10)).is_ok());
        assert!(range(1, 11)
            .check_within(range(1, 10))
            .unwrap_err()
            .contains("outside"));
    }
}
