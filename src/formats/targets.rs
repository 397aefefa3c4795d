//! Targets files read as their bytes arrive ([`TargetsReader`]): the
//! service's `targetsC` upload parts, parsed while they stream in, with a
//! limit on the targets applied row by row.
//!
//! The text is cut into slices at record ends and each slice parsed with
//! the whole-file parsers' own code ([`super::parse_targets`]'s formats:
//! a CSV table's slices each behind its header line, OpenPTV `_targets`
//! line by line), with lines numbered as in the whole file. What is held
//! is bounded whatever the file: the slice being gathered
//! ([`SLICE_BYTES`], or one record of at most [`MAX_RECORD_BYTES`]) and
//! the targets so far, at most `limit` (40 bytes each, twice that while
//! their vector grows).
//!
//! The result is the whole-file parser's, with two differences a real file
//! never shows: a record longer than [`MAX_RECORD_BYTES`] is refused, and
//! in a CSV file whose lines end in a lone `\r` the header is its first
//! record (the whole-file parser takes its optional columns from the text
//! before the first `\n`).

use super::{csv, openptv, FormatError};
use crate::photogrammetry::Target;

/// The slice of text parsed at once: once this much is gathered, the
/// complete records in it are parsed.
pub const SLICE_BYTES: usize = 64 << 10;

/// The longest record (line) taken: 1 MiB, for a row of a few numbers.
pub const MAX_RECORD_BYTES: usize = 1 << 20;

/// Which format the file is, once its first non-blank line is known.
enum Kind {
    /// Not known yet.
    Unknown,
    /// A CSV table: its header line (for every later slice) and columns.
    Csv {
        header: String,
        rows: csv::TargetRows,
    },
    /// OpenPTV `_targets`, once its first line (the count) has been read.
    OpenPtv { count: Option<usize> },
}

/// The first non-blank line of `text` (by `\n`, as `str::lines`), once it
/// is complete, or the file has ended (`end`: `""` if it has none), or it
/// is too long to be a count; `None` while it may still change.
fn first_line(text: &str, end: bool) -> Option<&str> {
    for line in text.split_inclusive('\n') {
        if !line.ends_with('\n') && !end {
            // Incomplete: a line too long for a count is CSV's header.
            return (line.trim().len() > 64).then_some(line);
        }
        if !line.trim().is_empty() {
            return Some(line.trim_end_matches('\n'));
        }
    }
    end.then_some("")
}

/// Where the scan of a CSV record is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Field {
    /// At a field's start.
    Start,
    /// In an unquoted field (a quote there is a character).
    Unquoted,
    /// In a quoted field (line breaks and commas are characters).
    Quoted,
    /// Just after a quote in a quoted field: its end, or the first of `""`.
    QuoteInQuoted,
}

/// A targets file read as its bytes arrive: [`TargetsReader::push`] each
/// chunk, then [`TargetsReader::finish`].
pub struct TargetsReader {
    source: String,
    limit: usize,
    /// What the limit is, for its message ("camera 1's sensor, ...").
    limit_reason: String,
    kind: Kind,
    /// Bytes received and not parsed yet.
    pending: Vec<u8>,
    /// How far `pending` has been scanned for record ends, where in a
    /// CSV field that is, and the end of the last complete record.
    scanned: usize,
    field: Field,
    record_end: usize,
    /// The file's line (from 1) where `pending` starts.
    line: u64,
    /// Whether a CSV table's first slice (with its header) has been read.
    started: bool,
    targets: Vec<Target>,
    /// Until the format is decided: where the first line that is not
    /// blank may start (every complete line before it is blank), how far
    /// `pending` has been looked at for line ends, and the length of that
    /// line when it was last looked at whole ([`TargetsReader::ready`]).
    line_start: usize,
    looked: usize,
    looked_whole: usize,
    /// Bytes examined to decide the format: at most a few times the bytes
    /// received, however they are cut ([`TargetsReader::ready`]).
    examined: u64,
}

impl TargetsReader {
    /// A reader for the file `source` that refuses more than `limit`
    /// targets; `limit_reason` says whose limit it is.
    pub fn new(source: &str, limit: usize, limit_reason: &str) -> TargetsReader {
        TargetsReader {
            source: source.to_owned(),
            limit,
            limit_reason: limit_reason.to_owned(),
            kind: Kind::Unknown,
            pending: Vec::new(),
            scanned: 0,
            field: Field::Start,
            record_end: 0,
            line: 1,
            started: false,
            targets: Vec::new(),
            line_start: 0,
            looked: 0,
            looked_whole: 0,
            examined: 0,
        }
    }

    /// Takes the next bytes of the file, parsing the complete records once
    /// a slice's worth has arrived.
    pub fn push(&mut self, bytes: &[u8]) -> Result<(), FormatError> {
        self.pending.extend_from_slice(bytes);
        self.scan();
        // A first line longer than a record may be is decided as it is.
        if matches!(self.kind, Kind::Unknown) {
            let end = self.pending.len() > MAX_RECORD_BYTES;
            if !(end || self.ready()) || !self.decide(end)? {
                return Ok(());
            }
        }
        if self.record_end >= SLICE_BYTES {
            self.parse_slice()?;
        }
        if self.pending.len() - self.record_end > MAX_RECORD_BYTES {
            return Err(self.invalid(
                self.line + self.breaks(&self.pending[..self.record_end]),
                format!(
                    "a line longer than {MAX_RECORD_BYTES} bytes (MAX_RECORD_BYTES); a target is \
                     a line of a few numbers{}",
                    if matches!(self.kind, Kind::Csv { .. }) {
                        " (is a quote left open?)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        Ok(())
    }

    /// The end of the file: the last records, and the targets.
    pub fn finish(mut self) -> Result<Vec<Target>, FormatError> {
        if matches!(self.kind, Kind::Unknown) {
            self.decide(true)?;
        }
        self.record_end = self.pending.len();
        self.parse_slice()?;
        if let Kind::OpenPtv { count } = self.kind {
            match count {
                Some(count) => {
                    openptv::check_target_count(count, self.targets.len(), &self.source)?
                }
                None => {
                    return Err(FormatError::invalid(
                        &self.source,
                        "line 1",
                        "the file is empty; expected the number of targets",
                    ))
                }
            }
        }
        Ok(self.targets)
    }

    fn invalid(&self, line: u64, reason: String) -> FormatError {
        FormatError::invalid(&self.source, format!("line {line}"), reason)
    }

    /// Finds the record ends in the bytes not scanned yet: for OpenPTV a
    /// `\n`; for CSV a line break outside a quoted field, as the CSV
    /// reader parses them (a quote opens a quoted field only at a field's
    /// start, `""` inside one is a quote; a `\r` ends a record only once
    /// the byte after it is known, so that `\r\n` is one break).
    fn scan(&mut self) {
        let csv = !matches!(self.kind, Kind::OpenPtv { .. });
        let bytes = &self.pending;
        let mut i = self.scanned;
        while i < bytes.len() {
            let byte = bytes[i];
            if !csv {
                if byte == b'\n' {
                    self.record_end = i + 1;
                }
                i += 1;
                continue;
            }
            let quoted = self.field == Field::Quoted;
            if byte == b'\r' && !quoted {
                match bytes.get(i + 1) {
                    None => break,
                    Some(b'\n') => {}
                    Some(_) => self.record_end = i + 1,
                }
                self.field = Field::Start;
            } else if byte == b'\n' && !quoted {
                self.record_end = i + 1;
                self.field = Field::Start;
            } else if byte == b',' && !quoted {
                self.field = Field::Start;
            } else {
                self.field = match (self.field, byte) {
                    (Field::Start, b'"') => Field::Quoted,
                    (Field::Quoted, b'"') => Field::QuoteInQuoted,
                    (Field::Quoted, _) => Field::Quoted,
                    (Field::QuoteInQuoted, b'"') => Field::Quoted,
                    _ => Field::Unquoted,
                };
            }
            i += 1;
        }
        self.scanned = i;
    }

    /// Whether [`TargetsReader::decide`] may decide now: a complete line
    /// that is not blank has arrived, or the line after the blank ones is
    /// already longer than a count may be. Looks at each byte received
    /// once for line ends, at each complete blank line once more, and at
    /// the incomplete line whole only when it has doubled since the last
    /// look, so deciding costs at most a few times the bytes received,
    /// however they are cut (`decide` itself reads `pending` whole, once).
    fn ready(&mut self) -> bool {
        while let Some(at) = self.pending[self.looked..].iter().position(|&b| b == b'\n') {
            let end = self.looked + at;
            self.examined += (at + 1) as u64;
            self.looked = end + 1;
            let line = &self.pending[self.line_start..end];
            self.examined += line.len() as u64;
            if !String::from_utf8_lossy(line).trim().is_empty() {
                return true;
            }
            self.line_start = end + 1;
            self.looked_whole = 0;
        }
        self.examined += (self.pending.len() - self.looked) as u64;
        self.looked = self.pending.len();
        let line = &self.pending[self.line_start..];
        if line.len() <= 64 || line.len() < 2 * self.looked_whole {
            return false;
        }
        self.looked_whole = line.len();
        self.examined += line.len() as u64;
        String::from_utf8_lossy(line).trim().len() > 64
    }

    /// Decides the format from the first non-blank line (by `\n`, as
    /// [`super::parse_targets`]), once it is complete or the file has
    /// ended (`end`); returns whether it is decided.
    fn decide(&mut self, end: bool) -> Result<bool, FormatError> {
        self.examined += self.pending.len() as u64;
        let text = String::from_utf8_lossy(&self.pending);
        let Some(first) = first_line(&text, end) else {
            return Ok(false);
        };
        self.kind = if first.trim().parse::<u64>().is_ok() {
            Kind::OpenPtv { count: None }
        } else {
            // The header is the first non-blank line after a byte order
            // mark (as `csv`'s header_names), up to a line break of any
            // kind.
            let Some(header) = first_line(text.trim_start_matches('\u{feff}'), end) else {
                return Ok(false);
            };
            let header = header.split(['\r', '\n']).next().unwrap_or("").to_owned();
            Kind::Csv {
                rows: csv::TargetRows::new(&header),
                header,
            }
        };
        // The record ends again, by the format's rule.
        self.scanned = 0;
        self.field = Field::Start;
        self.record_end = 0;
        self.scan();
        Ok(true)
    }

    /// The line breaks in `bytes`, as the format counts them: `\n`,
    /// `\r\n` and a lone `\r` in CSV (as the CSV reader and [`csv`]'s line
    /// numbers count them), `\n` in OpenPTV (as `str::lines`).
    fn breaks(&self, bytes: &[u8]) -> u64 {
        let csv = !matches!(self.kind, Kind::OpenPtv { .. });
        let mut count = 0;
        for (i, &b) in bytes.iter().enumerate() {
            if b == b'\n' || (csv && b == b'\r' && bytes.get(i + 1) != Some(&b'\n')) {
                count += 1;
            }
        }
        count
    }

    /// Parses `pending` up to the last record end.
    fn parse_slice(&mut self) -> Result<(), FormatError> {
        let end = self.record_end;
        let first_csv = matches!(self.kind, Kind::Csv { .. }) && !self.started;
        if end == 0 && !first_csv {
            return Ok(());
        }
        if first_csv && end < self.pending.len() && self.pending[..end].trim_ascii().is_empty() {
            // Blank lines before the header: only their count matters.
            self.line += self.breaks(&self.pending[..end]);
            self.pending.drain(..end);
            self.scanned = self.scanned.saturating_sub(end);
            self.record_end = 0;
            return Ok(());
        }
        let slice = match std::str::from_utf8(&self.pending[..end]) {
            Ok(slice) => slice,
            Err(error) => {
                let line = self.line + self.breaks(&self.pending[..error.valid_up_to()]);
                return Err(self.invalid(
                    line,
                    "is not UTF-8 text; send the targets as UTF-8 (or ASCII) text".to_owned(),
                ));
            }
        };
        let (limit, targets) = (self.limit, &mut self.targets);
        let source = self.source.as_str();
        let too_many = |line: u64| {
            FormatError::invalid(
                source,
                format!("line {line}"),
                format!(
                    "more than {limit} targets, the limit for {}; send one frame's targets of \
                     this camera, or detect them with a higher threshold",
                    self.limit_reason
                ),
            )
        };
        match &mut self.kind {
            Kind::Csv { header, rows } => {
                let mut push = |target, line| {
                    if targets.len() >= limit {
                        return Err(too_many(line));
                    }
                    targets.push(target);
                    Ok(())
                };
                if !self.started {
                    self.started = true;
                    // The header as the first slice holds it whole: the
                    // format may have been decided on its first 64 bytes,
                    // before its line ended.
                    let whole = first_line(slice.trim_start_matches('\u{feff}'), true)
                        .and_then(|h| h.split(['\r', '\n']).next())
                        .unwrap_or("");
                    if whole != header.as_str() {
                        *header = whole.to_owned();
                        *rows = csv::TargetRows::new(header);
                    }
                    rows.read(slice, source, self.line, &mut push)?;
                } else if !slice.is_empty() {
                    // The header again, as the line before the slice's.
                    let text = format!("{header}\n{slice}");
                    rows.read(&text, source, self.line - 1, &mut push)?;
                }
            }
            Kind::OpenPtv { count } => {
                for (number, text) in (self.line..).zip(slice.split_inclusive('\n')) {
                    let text = text.strip_suffix('\n').unwrap_or(text);
                    let text = text.strip_suffix('\r').unwrap_or(text);
                    if text.trim().is_empty() {
                        continue;
                    }
                    let number = usize::try_from(number).unwrap_or(usize::MAX);
                    match count {
                        None => {
                            let announced = openptv::parse_target_count(text, number, source)?;
                            if announced > limit {
                                return Err(FormatError::invalid(
                                    source,
                                    format!("line {number}"),
                                    format!(
                                        "announces {announced} targets, more than {limit}, the \
                                         limit for {}; send one frame's targets of this camera, \
                                         or detect them with a higher threshold",
                                        self.limit_reason
                                    ),
                                ));
                            }
                            *count = Some(announced);
                        }
                        Some(_) => {
                            if targets.len() >= limit {
                                return Err(too_many(number as u64));
                            }
                            let target =
                                openptv::parse_target_line(text, number, targets.len(), source)?;
                            targets.push(target);
                        }
                    }
                }
            }
            Kind::Unknown => unreachable!("decided before a slice is parsed"),
        }
        self.line += self.breaks(&self.pending[..end]);
        self.pending.drain(..end);
        self.scanned = self.scanned.saturating_sub(end);
        self.record_end = 0;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `text` pushed in chunks of `size` bytes.
    fn streamed(text: &str, size: usize, limit: usize) -> Result<Vec<Target>, FormatError> {
        let mut reader = TargetsReader::new("targets1", limit, "camera 1's sensor");
        for chunk in text.as_bytes().chunks(size.max(1)) {
            reader.push(chunk)?;
        }
        reader.finish()
    }

    fn csv_rows(rows: usize) -> String {
        let mut text = "x,y,n\n".to_owned();
        for i in 0..rows {
            text.push_str(&format!("{}.5,{},{}\n", i, i * 2, i % 7));
        }
        text
    }

    fn openptv_rows(rows: usize) -> String {
        let mut text = format!("{rows}\n");
        for i in 0..rows {
            text.push_str(&format!("{i:4} {i}.25 {}.5 4 2 2 100 -1\n", i + 1));
        }
        text
    }

    #[test]
    fn streamed_targets_are_the_whole_files() {
        let big_csv = csv_rows(20_000);
        let big_openptv = openptv_rows(20_000);
        for text in [
            big_csv.as_str(),
            big_openptv.as_str(),
            "x,y\n1,2\n3,4",
            "\u{feff}\n\nx , y,sumg\r\n1,2,3\r\n\r\n4,5,6\r\n",
            "x,y,note\n1,2,\"a\nb\"\n3,4,c\n",
            "x,y,note\n1,2,a\"b\n3,4,\"c\"\"\nd\"\n5,6,e\n",
            "x,y\r1,2\r3,4\r",
            "\n 2 \n0 1 2 3 4 5 6 -1\n\n1 1 2 3 4 5 6 -1",
            "0\n",
            "x,y\n",
        ] {
            let whole = crate::formats::parse_targets(text, "targets1").unwrap();
            for size in [1, 2, 7, 1000, 1 << 20] {
                assert_eq!(
                    streamed(text, size, usize::MAX).unwrap(),
                    whole,
                    "{size}: {:?}",
                    &text[..text.len().min(40)]
                );
            }
        }
    }

    #[test]
    fn streamed_errors_are_the_whole_files() {
        let mut late = csv_rows(30_000);
        late.push_str("1,zz,3\n");
        let mut late_openptv = openptv_rows(30_000).replacen("30000\n", "30001\n", 1);
        late_openptv.push_str("30000 1 2 3 4 5 6 -1 9\n");
        for text in [
            late.as_str(),
            late_openptv.as_str(),
            "x,y\n1,2\n3\n",
            "x,z\n1,2\n",
            "",
            "  \n",
            "2\n0 1 2 3 4 5 6 -1\n",
            "x,y\n1,\"2\n\n\",3\n4,a\n",
        ] {
            let whole = crate::formats::parse_targets(text, "targets1")
                .unwrap_err()
                .to_string();
            for size in [1, 5, 4096, 1 << 20] {
                let error = streamed(text, size, usize::MAX).unwrap_err().to_string();
                assert_eq!(error, whole, "{size}");
            }
        }
    }

    #[test]
    fn the_limit_stops_the_file_at_its_row() {
        let error = streamed(&csv_rows(100_000), 4096, 1000)
            .unwrap_err()
            .to_string();
        assert!(
            error.starts_with(
                "targets1: line 1002: more than 1000 targets, the limit for camera 1's sensor"
            ),
            "{error}"
        );
        assert_eq!(streamed(&csv_rows(1000), 4096, 1000).unwrap().len(), 1000);
        let error = streamed(&openptv_rows(1001), 4096, 1000)
            .unwrap_err()
            .to_string();
        assert!(
            error.starts_with("targets1: line 1: announces 1001 targets, more than 1000"),
            "{error}"
        );
        let lying = openptv_rows(2000).replacen("2000\n", "10\n", 1);
        let error = streamed(&lying, 4096, 1000).unwrap_err().to_string();
        assert!(
            error.contains("line 1002: more than 1000 targets"),
            "{error}"
        );
    }

    /// Deciding the format looks at each byte a bounded number of times,
    /// however the bytes are cut: 512 KiB of blank lines, or of spaces
    /// with no line end, or a long header, a byte at a time, cost a few
    /// times their bytes (rescanning everything pending at each byte, as
    /// before, cost about n²/2: 1.4·10^11 here). Counted, not timed.
    #[test]
    fn deciding_the_format_is_linear_in_the_bytes() {
        let long_header = format!("x,y,{}\n1,2,3\n", "n".repeat(300_000));
        for (case, text) in [
            (
                "blank lines",
                format!("{}x,y\n1,2\n", "\n".repeat(512 << 10)),
            ),
            ("spaces", format!("{}\nx,y\n1,2\n", " ".repeat(512 << 10))),
            (
                "blank lines of spaces",
                format!("{}x,y\n1,2\n", " \r\n".repeat(170 << 10)),
            ),
            ("a long header", long_header),
        ] {
            let mut reader = TargetsReader::new("targets1", usize::MAX, "camera 1's sensor");
            for byte in text.as_bytes().chunks(1) {
                reader.push(byte).unwrap();
            }
            let examined = reader.examined;
            let bytes = text.len() as u64;
            assert!(
                examined <= 6 * bytes,
                "{case}: {examined} bytes examined for {bytes} received"
            );
            assert!(examined > 0, "{case}: the count counts");
            let whole = crate::formats::parse_targets(&text, "targets1");
            assert_eq!(
                reader.finish().map_err(|e| e.to_string()),
                whole.map_err(|e| e.to_string()),
                "{case}"
            );
        }
    }

    /// A CSV header longer than 64 bytes that arrives in pieces is still
    /// the whole header for every slice (the format is decided on its
    /// first 64 bytes; the slices after the first are read behind it).
    #[test]
    fn a_long_header_arriving_in_pieces_is_read_whole() {
        // The optional columns after the first 64 bytes.
        let mut text =
            "x,y,a_column_that_makes_the_header_longer_than_a_count_could_be,n,nx,ny,sumg\n"
                .to_owned();
        for i in 0..20_000 {
            text.push_str(&format!("{i}.5,{},7,3,2,2,100\n", i * 2));
        }
        let whole = crate::formats::parse_targets(&text, "targets1").unwrap();
        for size in [1, 7, 100] {
            assert_eq!(streamed(&text, size, usize::MAX).unwrap(), whole, "{size}");
        }
    }

    #[test]
    fn long_lines_and_bad_text_are_refused() {
        let long = format!("x,y\n1,{}\n", "2".repeat(2 * MAX_RECORD_BYTES));
        let error = streamed(&long, 65536, usize::MAX).unwrap_err().to_string();
        assert!(
            error.starts_with("targets1: line 2: a line longer than"),
            "{error}"
        );
        let mut reader = TargetsReader::new("targets1", 10, "camera 1's sensor");
        reader.push(b"x,y\n1,2\n\xff,3\n").unwrap();
        let error = reader.finish().unwrap_err().to_string();
        assert!(
            error.starts_with("targets1: line 3: is not UTF-8"),
            "{error}"
        );
    }
}
