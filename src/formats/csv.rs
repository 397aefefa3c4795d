//! Point and observation tables of the command line (CSV with a header).
//!
//! Tables, comma-separated, each starting with a header line that
//! names its columns:
//!
//! - points, read by `ptv project`: columns `x,y,z` (mm) in any order among
//!   others, which are ignored. A point's index is its data row index,
//!   counted from 0.
//! - observations, written by `ptv project` and read by `ptv intersect`:
//!   `point,camera,x,y`, a point id (non-negative integer), the 0-based index
//!   of the camera in the calibration and the image position in pixels (the
//!   convention of [`crate::photogrammetry::camera`]). Each (point, camera)
//!   pair appears at most once.
//! - intersections, written by `ptv intersect`:
//!   `point,x,y,z,sx,sy,sz,rms_px`, the point (mm), its standard deviations
//!   (mm) and the root mean square of its residuals (px).
//! - particles, written by `ptv match` and `ptv process`:
//!   `x,y,z,sx,sy,sz,rms_px,cameras,t0,t1,...`, as intersections, then the
//!   number of cameras that see the particle and, per camera `C`, the index
//!   of its target in that camera's list (`-1` where it has none).
//! - targets, written by `ptv detect` and read by `ptv match`:
//!   `x,y,n,nx,ny,sumg`.
//! - trajectories, written by `ptv track` and read by `ptv plot
//!   trajectories`: `trajectory,frame,x,y,z,u,v,w,...`, the velocity `NaN`
//!   (or empty) where the fit gives none; other columns are ignored.
//!
//! Readers match header names exactly after trimming surrounding
//! whitespace, trim every field, skip a UTF-8 byte order mark and blank
//! lines, require every data line to have as many fields as the header and
//! every number to be finite. Errors name the source, the line (counted from
//! 1 in the text as given) and the column.
//!
//! Writers print numbers in the shortest form that parses back to the same
//! value (Ryū, as `{:?}` for `f64` does but about three times faster; with
//! an exponent for very small or large ones), so a table written and read
//! again is identical bit for bit.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use nalgebra::{Point2, Point3};

use super::FormatError;
use crate::photogrammetry::correspond::Particle;
use crate::photogrammetry::Target;
use crate::photogrammetry::{Intersection, Observation};

/// The columns a points table must have.
pub const POINT_COLUMNS: [&str; 3] = ["x", "y", "z"];
/// The columns of an observations table.
pub const OBSERVATION_COLUMNS: [&str; 4] = ["point", "camera", "x", "y"];
/// The columns of an intersections table.
pub const INTERSECTION_COLUMNS: [&str; 8] = ["point", "x", "y", "z", "sx", "sy", "sz", "rms_px"];

/// A point id and its images: the rows of an observations table that share
/// one `point`.
#[derive(Clone, Debug, PartialEq)]
pub struct ObservedPoint {
    /// The point's id.
    pub point: u64,
    /// Its image positions, at most one per camera.
    pub observations: Vec<Observation>,
}

/// The columns of a targets table; only `x` and `y` are required.
pub const TARGET_COLUMNS: [&str; 6] = ["x", "y", "n", "nx", "ny", "sumg"];

/// Reads a targets table (pixels; `n`, `nx`, `ny`, `sumg` optional, 0 when
/// absent), in file order.
pub fn parse_targets(text: &str, source: &str) -> Result<Vec<Target>, FormatError> {
    let mut rows = TargetRows::new(text);
    let mut targets = Vec::new();
    rows.read(text, source, 1, |target, _| {
        targets.push(target);
        Ok(())
    })?;
    Ok(targets)
}

/// A targets table read in slices: the columns its header names, and the
/// rows of each slice given to a callback.
pub(crate) struct TargetRows {
    /// The optional columns the header has, and `x`, `y`.
    columns: Vec<&'static str>,
}

impl TargetRows {
    /// The columns of a table whose first non-blank line is `text`'s.
    pub(crate) fn new(text: &str) -> TargetRows {
        let header = header_names(text);
        let columns = TARGET_COLUMNS
            .iter()
            .enumerate()
            .filter(|(i, name)| *i < 2 || header.iter().any(|h| h == *name))
            .map(|(_, name)| *name)
            .collect();
        TargetRows { columns }
    }

    /// Reads `text`, a header line and rows, the header being line
    /// `first_line` of the file: `target` gets each row's target and line.
    pub(crate) fn read(
        &mut self,
        text: &str,
        source: &str,
        first_line: u64,
        mut target: impl FnMut(Target, u64) -> Result<(), FormatError>,
    ) -> Result<(), FormatError> {
        let columns = &self.columns;
        read_table_from(text, source, columns, first_line, |row| {
            target(row_target(row, columns)?, row.line)
        })
    }
}

/// The target of a targets table's row, of `columns`.
fn row_target(row: &Row<'_>, columns: &[&str]) -> Result<Target, FormatError> {
    {
        let mut target = Target {
            x: row.number(0)?,
            y: row.number(1)?,
            n: 0,
            nx: 0,
            ny: 0,
            sumg: 0,
        };
        for (i, name) in columns.iter().enumerate().skip(2) {
            let value = row.integer(i)?;
            let small = || {
                u32::try_from(value)
                    .map_err(|_| row.error(i, format!("{value} is too large for a pixel count")))
            };
            match *name {
                "n" => target.n = small()?,
                "nx" => target.nx = small()?,
                "ny" => target.ny = small()?,
                _ => target.sumg = value,
            }
        }
        Ok(target)
    }
}

/// A particle read from a particles table: its position, its standard
/// deviations where the table has them, and its targets per camera where
/// it has `t0,t1,...`.
#[derive(Clone, Debug, PartialEq)]
pub struct ParticleRow {
    /// Position (mm).
    pub position: Point3<f64>,
    /// `sx,sy,sz` (mm), if the table has them.
    pub sigma: Option<nalgebra::Vector3<f64>>,
    /// Per camera `C` of the table's `tC` columns, the target index (`None`
    /// for -1).
    pub targets: Vec<Option<usize>>,
}

/// Reads a particles table as `ptv match` writes it: `x,y,z` required;
/// `sx,sy,sz` and `t0,t1,...` (consecutive from `t0`) where the header has
/// them; other columns ignored.
pub fn parse_particles(text: &str, source: &str) -> Result<Vec<ParticleRow>, FormatError> {
    let header = header_names(text);
    let has = |name: &str| header.iter().any(|h| h == name);
    let sigmas = ["sx", "sy", "sz"].iter().all(|c| has(c));
    let cameras = (0..).take_while(|c| has(&format!("t{c}"))).count();
    let target_columns: Vec<String> = (0..cameras).map(|c| format!("t{c}")).collect();
    let mut columns: Vec<&str> = vec!["x", "y", "z"];
    if sigmas {
        columns.extend(["sx", "sy", "sz"]);
    }
    let first_target = columns.len();
    columns.extend(target_columns.iter().map(String::as_str));
    let mut particles = Vec::new();
    read_table(text, source, &columns, |row| {
        let sigma = if sigmas {
            Some(nalgebra::Vector3::new(
                row.number(3)?,
                row.number(4)?,
                row.number(5)?,
            ))
        } else {
            None
        };
        let targets = (first_target..columns.len())
            .map(|i| match row.field(i)? {
                "-1" => Ok(None),
                _ => usize::try_from(row.integer(i)?)
                    .map(Some)
                    .map_err(|_| row.error(i, "is too large for a target index")),
            })
            .collect::<Result<Vec<_>, FormatError>>()?;
        particles.push(ParticleRow {
            position: Point3::new(row.number(0)?, row.number(1)?, row.number(2)?),
            sigma,
            targets,
        });
        Ok(())
    })?;
    Ok(particles)
}

/// A point of a trajectory read from `ptv track`'s table.
#[derive(Clone, Debug, PartialEq)]
pub struct TrajectoryPointRow {
    /// The trajectory's number.
    pub trajectory: u64,
    /// The frame.
    pub frame: u64,
    /// Position (mm).
    pub position: Point3<f64>,
    /// Velocity (mm per frame), where the fit gives one.
    pub velocity: Option<nalgebra::Vector3<f64>>,
}

/// Reads a trajectories table as `ptv track` writes it:
/// `trajectory,frame,x,y,z` required, `u,v,w` where the header has them
/// (`NaN` or empty for none); other columns ignored. In file order.
pub fn parse_trajectories(
    text: &str,
    source: &str,
) -> Result<Vec<TrajectoryPointRow>, FormatError> {
    let header = header_names(text);
    let velocities = ["u", "v", "w"]
        .iter()
        .all(|c| header.iter().any(|h| h == c));
    let mut columns = vec!["trajectory", "frame", "x", "y", "z"];
    if velocities {
        columns.extend(["u", "v", "w"]);
    }
    let mut points = Vec::new();
    read_table(text, source, &columns, |row| {
        let velocity = if velocities {
            let mut v = [0.0; 3];
            let mut known = true;
            for (k, value) in v.iter_mut().enumerate() {
                match row.field(5 + k)? {
                    "" | "NaN" | "nan" => known = false,
                    _ => *value = row.number(5 + k)?,
                }
            }
            known.then(|| nalgebra::Vector3::from(v))
        } else {
            None
        };
        points.push(TrajectoryPointRow {
            trajectory: row.integer(0)?,
            frame: row.integer(1)?,
            position: Point3::new(row.number(2)?, row.number(3)?, row.number(4)?),
            velocity,
        });
        Ok(())
    })?;
    Ok(points)
}

/// The names in a table's header line (its first line that is not blank),
/// trimmed and unquoted; empty for an empty table.
fn header_names(text: &str) -> Vec<String> {
    text.trim_start_matches('\u{feff}')
        .lines()
        .find(|line| !line.trim().is_empty())
        .unwrap_or("")
        .split(',')
        .map(|name| name.trim().trim_matches('"').to_owned())
        .collect()
}

/// Writes a targets table, `x,y,n,nx,ny,sumg`.
pub fn format_targets(targets: &[Target]) -> String {
    let mut text = header(&TARGET_COLUMNS);
    let mut numbers = Numbers::default();
    for t in targets {
        numbers.float(&mut text, t.x);
        text.push(',');
        numbers.float(&mut text, t.y);
        for n in [u64::from(t.n), u64::from(t.nx), u64::from(t.ny), t.sumg] {
            text.push(',');
            numbers.int(&mut text, n);
        }
        text.push('\n');
    }
    text
}

/// Number formatting for the writers: floats in their shortest
/// round-trip form (`NaN`, `inf` and `-inf` as `{:?}` writes them),
/// integers in decimal.
#[derive(Default)]
struct Numbers {
    floats: ryu::Buffer,
    ints: itoa::Buffer,
}

impl Numbers {
    fn float(&mut self, text: &mut String, value: f64) {
        text.push_str(self.floats.format(value));
    }

    fn int(&mut self, text: &mut String, value: impl itoa::Integer) {
        text.push_str(self.ints.format(value));
    }
}

/// Reads a points table: one 3D point (mm) per data line, in file order.
pub fn parse_points(text: &str, source: &str) -> Result<Vec<Point3<f64>>, FormatError> {
    let mut points = Vec::new();
    read_table(text, source, &POINT_COLUMNS, |row| {
        points.push(Point3::new(row.number(0)?, row.number(1)?, row.number(2)?));
        Ok(())
    })?;
    Ok(points)
}

/// Reads an observations table for a calibration of `cameras` cameras:
/// the points sorted by id, each with its observations in file order.
pub fn parse_observations(
    text: &str,
    source: &str,
    cameras: usize,
) -> Result<Vec<ObservedPoint>, FormatError> {
    // Per point: its observations and the line each came from.
    let mut points: BTreeMap<u64, Vec<(Observation, u64)>> = BTreeMap::new();
    read_table(text, source, &OBSERVATION_COLUMNS, |row| {
        let point = row.integer(0)?;
        let camera = row.integer(1)?;
        let camera = usize::try_from(camera)
            .ok()
            .filter(|&c| c < cameras)
            .ok_or_else(|| {
                row.error(
                    1,
                    format!(
                        "camera {camera} does not exist: the calibration has {cameras} cameras, \
                         numbered from 0 to {}",
                        cameras.saturating_sub(1)
                    ),
                )
            })?;
        let pixel = Point2::new(row.number(2)?, row.number(3)?);
        let seen = points.entry(point).or_default();
        if let Some((_, line)) = seen.iter().find(|(o, _)| o.camera == camera) {
            return Err(row.error(
                1,
                format!(
                    "point {point} already has an observation in camera {camera}, on line {line}"
                ),
            ));
        }
        seen.push((Observation { camera, pixel }, row.line));
        Ok(())
    })?;
    Ok(points
        .into_iter()
        .map(|(point, seen)| ObservedPoint {
            point,
            observations: seen.into_iter().map(|(o, _)| o).collect(),
        })
        .collect())
}

/// Writes a points table, `x,y,z`.
pub fn format_points(points: &[Point3<f64>]) -> String {
    let mut text = header(&POINT_COLUMNS);
    for p in points {
        let _ = writeln!(text, "{:?},{:?},{:?}", p.x, p.y, p.z);
    }
    text
}

/// Writes an observations table, `point,camera,x,y`: one row per
/// observation, in the order given.
pub fn format_observations(points: &[ObservedPoint]) -> String {
    let mut text = header(&OBSERVATION_COLUMNS);
    for point in points {
        for o in &point.observations {
            let _ = writeln!(
                text,
                "{},{},{:?},{:?}",
                point.point, o.camera, o.pixel.x, o.pixel.y
            );
        }
    }
    text
}

/// Writes an intersections table, `point,x,y,z,sx,sy,sz,rms_px`, in the
/// order given.
pub fn format_intersections(points: &[(u64, Intersection)]) -> String {
    let mut text = header(&INTERSECTION_COLUMNS);
    for (id, i) in points {
        let _ = writeln!(
            text,
            "{id},{:?},{:?},{:?},{:?},{:?},{:?},{:?}",
            i.point.x, i.point.y, i.point.z, i.sigma.x, i.sigma.y, i.sigma.z, i.rms_px
        );
    }
    text
}

/// The columns of a trajectories table before the per-camera target
/// columns `t0,t1,...`.
pub const TRAJECTORY_COLUMNS: &str = "trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras";

/// The header line of a trajectories table for `cameras` cameras, as
/// `ptv track` writes it and the service serves it, with its line break.
pub fn trajectory_header(cameras: usize) -> String {
    let mut line = String::from(TRAJECTORY_COLUMNS);
    for c in 0..cameras {
        let _ = write!(line, ",t{c}");
    }
    line.push('\n');
    line
}

/// One point of a trajectories table.
#[derive(Clone, Copy, Debug)]
pub struct TrajectoryPointLine<'a> {
    /// The trajectory's number.
    pub trajectory: i64,
    /// The frame.
    pub frame: i64,
    /// Position (mm).
    pub position: [f64; 3],
    /// Velocity (mm per frame); written as `NaN` where the fit gives none.
    pub velocity: Option<[f64; 3]>,
    /// Acceleration (mm per frame²); empty fields where there is none.
    pub acceleration: Option<[f64; 3]>,
    /// The velocity's standard deviations; `NaN` where there are none.
    pub velocity_sigma: Option<[f64; 3]>,
    /// The particle's target per camera (`-1` where it has none): the
    /// `cameras` count and the `tC` columns; `None` leaves them all empty.
    pub targets: Option<&'a [Option<usize>]>,
}

/// Appends a point of a trajectories table of `cameras` cameras, numbers
/// as `{:?}` writes them (shortest round trip: [`push_debug_f64`]), with
/// its line break.
pub fn write_trajectory_point(out: &mut String, p: &TrajectoryPointLine<'_>, cameras: usize) {
    let mut floats = ryu::Buffer::new();
    let mut ints = itoa::Buffer::new();
    out.push_str(ints.format(p.trajectory));
    out.push(',');
    out.push_str(ints.format(p.frame));
    let mut three = |out: &mut String, values: [f64; 3]| {
        for v in values {
            out.push(',');
            push_debug_f64(out, &mut floats, v);
        }
    };
    three(out, p.position);
    three(out, p.velocity.unwrap_or([f64::NAN; 3]));
    match p.acceleration {
        Some(a) => three(out, a),
        None => out.push_str(",,,"),
    }
    three(out, p.velocity_sigma.unwrap_or([f64::NAN; 3]));
    match p.targets {
        Some(targets) => {
            out.push(',');
            out.push_str(ints.format(targets.iter().flatten().count()));
            for t in targets {
                match t {
                    Some(t) => {
                        out.push(',');
                        out.push_str(ints.format(*t));
                    }
                    None => out.push_str(",-1"),
                }
            }
        }
        None => {
            out.push(',');
            for _ in 0..cameras {
                out.push(',');
            }
        }
    }
    out.push('\n');
}

/// Appends `value` exactly as `{:?}` writes it, by Ryū (about 4x faster
/// than `{:?}`'s Grisu) where the two agree, and by `{:?}` where they may
/// not (`debug_f64_writer_is_debug_byte_for_byte` checks it). Both give
/// the shortest digits that read back to the value, the closest to it
/// where several are as short; they differ in two ways:
/// - `{:?}` writes an exponent for magnitudes below 1e-4 or from 1e16 on,
///   Ryū below 1e-5 or from 1e16 on (`5e-5` against `0.00005`);
/// - where the value lies exactly halfway between the two closest shortest
///   strings, Ryū takes the even last digit, `{:?}` the upper one
///   (1308548795726862.25: `...862.2` against `...862.3`). Such a tie needs
///   a value whose exact decimal expansion has at most 18 significant
///   digits (n + 1 for n <= 17 digits written, ending in 5). A double `m
///   2^-k` (`m` odd, `k > 0`) is `m 5^k / 10^k` exactly, `m 5^k` without a
///   trailing zero: it has 19 digits or more where `m 5^k >= 10^18`, which
///   holds for nearly all measured values (17.54 is `m 2^-48`, `m` of 53
///   bits: ~165 bits). Integers and values of few significant bits are
///   left to `{:?}`.
pub(crate) fn push_debug_f64(out: &mut String, buffer: &mut ryu::Buffer, value: f64) {
    if ryu_may_differ_from_debug(value) {
        let _ = write!(out, "{value:?}");
    } else {
        out.push_str(buffer.format(value));
    }
}

/// Whether Ryū's text of `value` may differ from `{:?}`'s
/// ([`push_debug_f64`]).
fn ryu_may_differ_from_debug(value: f64) -> bool {
    let magnitude = value.abs();
    if !magnitude.is_finite() || magnitude == 0.0 {
        // NaN, inf, -inf, 0.0 and -0.0 are spelt alike.
        return false;
    }
    if (1e-5..1e-4).contains(&magnitude) {
        return true;
    }
    let bits = magnitude.to_bits();
    let biased = (bits >> 52) as i64;
    let fraction = bits & ((1 << 52) - 1);
    let (mantissa, exponent) = if biased == 0 {
        (fraction, -1074)
    } else {
        (fraction | 1 << 52, biased - 1075)
    };
    let zeros = mantissa.trailing_zeros();
    let (odd, exponent) = (mantissa >> zeros, exponent + i64::from(zeros));
    if exponent >= 0 {
        return true;
    }
    // log2(m 5^k) = log2(m) + k log2(5), log2(m) >= its bit length - 1;
    // 10^18 is 2^59.79.
    let k = (-exponent) as f64;
    let log2 = f64::from(63 - odd.leading_zeros()) + k * (std::f64::consts::LOG2_10 - 1.0);
    log2 < 60.0
}

/// The columns of a particles table before the per-camera target columns
/// `t0,t1,...`.
pub const PARTICLE_COLUMNS: [&str; 8] = ["x", "y", "z", "sx", "sy", "sz", "rms_px", "cameras"];

/// Writes a particles table for `cameras` cameras,
/// `x,y,z,sx,sy,sz,rms_px,cameras,t0,...`, in the order given; `tC` is the
/// index of the particle's target in camera C's list, -1 where it has none.
pub fn format_particles(particles: &[Particle], cameras: usize) -> String {
    let mut text = PARTICLE_COLUMNS.join(",");
    for camera in 0..cameras {
        let _ = write!(text, ",t{camera}");
    }
    text.push('\n');
    let mut numbers = Numbers::default();
    for p in particles {
        for (k, value) in [
            p.position.x,
            p.position.y,
            p.position.z,
            p.sigma.x,
            p.sigma.y,
            p.sigma.z,
            p.rms_px,
        ]
        .into_iter()
        .enumerate()
        {
            if k > 0 {
                text.push(',');
            }
            numbers.float(&mut text, value);
        }
        text.push(',');
        numbers.int(&mut text, p.camera_count());
        for camera in 0..cameras {
            match p.targets.get(camera).copied().flatten() {
                Some(target) => {
                    text.push(',');
                    numbers.int(&mut text, target);
                }
                None => text.push_str(",-1"),
            }
        }
        text.push('\n');
    }
    text
}

fn header(columns: &[&str]) -> String {
    columns.join(",") + "\n"
}

/// The longest field quoted whole in an error message.
const MAX_QUOTED_CHARS: usize = 40;

/// A field for an error message: on one line, shortened if long.
fn quote(field: &str) -> String {
    if field.chars().count() <= MAX_QUOTED_CHARS {
        format!("{field:?}")
    } else {
        let head: String = field.chars().take(MAX_QUOTED_CHARS).collect();
        format!("{head:?}...")
    }
}

/// One data line of a table: the fields of the wanted columns.
struct Row<'a> {
    source: &'a str,
    /// Line number (from 1) where the record starts.
    line: u64,
    /// Names of the wanted columns.
    columns: &'a [&'a str],
    /// The record's fields, untrimmed.
    record: &'a csv::ByteRecord,
    /// Per wanted column, its field in `record`.
    indices: &'a [usize],
}

impl Row<'_> {
    fn error(&self, column: usize, reason: impl Into<String>) -> FormatError {
        FormatError::invalid(
            self.source,
            format!("line {}, column {}", self.line, self.columns[column]),
            reason,
        )
    }

    /// The field of wanted column `column`, trimmed. The table is `&str`
    /// and fields split at ASCII bytes, so a field is UTF-8; were the reader
    /// ever to split otherwise, that is an error here, not a panic.
    fn field(&self, column: usize) -> Result<&str, FormatError> {
        let bytes = &self.record[self.indices[column]];
        std::str::from_utf8(bytes).map(str::trim).map_err(|_| {
            self.error(
                column,
                format!(
                    "is not UTF-8 text: {}",
                    quote(&String::from_utf8_lossy(bytes))
                ),
            )
        })
    }

    fn number(&self, column: usize) -> Result<f64, FormatError> {
        let field = self.field(column)?;
        match field.parse::<f64>() {
            Ok(value) if value.is_finite() => Ok(value),
            _ if field.is_empty() => {
                Err(self.error(column, "expected a number, found an empty field"))
            }
            _ => Err(self.error(
                column,
                format!("expected a finite number, got {}", quote(field)),
            )),
        }
    }

    fn integer(&self, column: usize) -> Result<u64, FormatError> {
        let field = self.field(column)?;
        field.parse::<u64>().map_err(|_| {
            self.error(
                column,
                format!(
                    "expected a non-negative integer (at most {}), got {}",
                    u64::MAX,
                    quote(field)
                ),
            )
        })
    }
}

/// Line numbers of the records the csv reader returns.
///
/// The reader reports a record's position as the end of the record before
/// it, so its own line numbers miss blank lines and count `\r\n` as two
/// breaks; this counts from the text itself instead.
struct LineCounter<'t> {
    text: &'t [u8],
    /// Bytes already counted.
    offset: usize,
    /// The line (from 1) at `offset`.
    line: u64,
}

impl<'t> LineCounter<'t> {
    /// Counts lines of `text` from `first` (1 for a whole file).
    fn new(text: &'t str, first: u64) -> Self {
        LineCounter {
            text: text.as_bytes(),
            offset: 0,
            line: first,
        }
    }

    /// The line of the record whose position the reader reports as `byte`:
    /// the first line after it that is not empty (a record never starts
    /// with a line break). Calls must come in order of increasing `byte`.
    fn record_line(&mut self, byte: u64) -> u64 {
        let text = self.text;
        let mut start = usize::try_from(byte).map_or(text.len(), |b| b.min(text.len()));
        while start < text.len() && matches!(text[start], b'\r' | b'\n') {
            start += 1;
        }
        while self.offset < start {
            // A break is `\n`, `\r\n` or a lone `\r`, as for the reader.
            let is_break = match text[self.offset] {
                b'\n' => true,
                b'\r' => text.get(self.offset + 1) != Some(&b'\n'),
                _ => false,
            };
            if is_break {
                self.line += 1;
            }
            self.offset += 1;
        }
        self.line
    }
}

/// Reads a table, calling `row` on each data line in file order (one
/// record buffer, reused; only the wanted fields are trimmed and checked
/// for UTF-8: no allocation per line).
fn read_table(
    text: &str,
    source: &str,
    columns: &[&str],
    row: impl FnMut(&Row<'_>) -> Result<(), FormatError>,
) -> Result<(), FormatError> {
    read_table_from(text, source, columns, 1, row)
}

/// [`read_table`] of a text whose first line is line `first_line` of its
/// file (a header line and a slice of a file's rows, read as they arrive:
/// [`TargetRows`]).
fn read_table_from(
    text: &str,
    source: &str,
    columns: &[&str],
    first_line: u64,
    mut row: impl FnMut(&Row<'_>) -> Result<(), FormatError>,
) -> Result<(), FormatError> {
    let expected = columns.join(",");
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .from_reader(text.as_bytes());
    let mut lines = LineCounter::new(text, first_line);
    // The next record that is not a blank line, and its line; a line of
    // only whitespace reads as one empty field.
    let mut next = |record: &mut csv::ByteRecord| -> Result<Option<u64>, FormatError> {
        loop {
            let more = reader.read_byte_record(record).map_err(|error| {
                let line = error.position().map_or(1, |p| lines.record_line(p.byte()));
                FormatError::invalid(source, format!("line {line}"), error.to_string())
            })?;
            if !more {
                return Ok(None);
            }
            let blank = record.len() == 1
                && std::str::from_utf8(&record[0]).is_ok_and(|f| f.trim().is_empty());
            if !blank {
                return Ok(Some(
                    record.position().map_or(1, |p| lines.record_line(p.byte())),
                ));
            }
        }
    };

    let mut header = csv::ByteRecord::new();
    let Some(header_line) = next(&mut header)? else {
        return Err(FormatError::invalid(
            source,
            "line 1",
            format!("the table is empty; expected a header line naming the columns {expected}"),
        ));
    };
    let header: Vec<String> = header
        .iter()
        .map(|name| String::from_utf8_lossy(name).trim().to_owned())
        .collect();
    let mut indices = Vec::with_capacity(columns.len());
    for &column in columns {
        let mut found = header
            .iter()
            .enumerate()
            .filter(|(_, name)| *name == column);
        let Some((index, _)) = found.next() else {
            return Err(FormatError::invalid(
                source,
                format!("line {header_line}, column {column}"),
                format!(
                    "the header has no column `{column}`: the first line must name the columns \
                     {expected}, found {}",
                    quote(&header.join(","))
                ),
            ));
        };
        if let Some((again, _)) = found.next() {
            return Err(FormatError::invalid(
                source,
                format!("line {header_line}, column {column}"),
                format!(
                    "the header names column `{column}` twice, as fields {} and {}",
                    index + 1,
                    again + 1
                ),
            ));
        }
        indices.push(index);
    }

    let mut record = csv::ByteRecord::new();
    while let Some(line) = next(&mut record)? {
        if record.len() != header.len() {
            return Err(FormatError::invalid(
                source,
                format!("line {line}"),
                format!(
                    "has {} fields but the header has {}; every line needs one field per column",
                    record.len(),
                    header.len()
                ),
            ));
        }
        row(&Row {
            source,
            line,
            columns,
            record: &record,
            indices: &indices,
        })?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;
    use proptest::prelude::*;

    fn points_error(text: &str) -> String {
        parse_points(text, "points.csv").unwrap_err().to_string()
    }

    fn observations_error(text: &str) -> String {
        parse_observations(text, "obs.csv", 3)
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn points_columns_in_any_order_among_others() {
        let text = "\u{feff}id, z ,x,y,note\n7,3,1,2,a\n\n8, -0.5e1 ,4.25,-1,\"b,c\"\r\n";
        let points = parse_points(text, "points.csv").unwrap();
        assert_eq!(
            points,
            vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.25, -1.0, -5.0)]
        );
    }

    #[test]
    fn trajectories_read_as_ptv_track_writes_them() {
        let text = "trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras,t0,t1\n\
                    0,10,1.5,2,3,0.5,-1,0,,,,0.1,0.1,0.1,2,4,7\n\
                    0,11,2,1,3,NaN,NaN,NaN,,,,NaN,NaN,NaN,2,5,-1\n";
        let points = parse_trajectories(text, "t.csv").unwrap();
        assert_eq!(points.len(), 2);
        assert_eq!(points[0].trajectory, 0);
        assert_eq!(points[0].frame, 10);
        assert_eq!(points[0].position, Point3::new(1.5, 2.0, 3.0));
        assert_eq!(points[0].velocity, Some(Vector3::new(0.5, -1.0, 0.0)));
        assert_eq!(points[1].velocity, None);
        // Without velocities; errors name the file, line and column.
        let points = parse_trajectories("trajectory,frame,x,y,z\n3,1,0,0,0\n", "t").unwrap();
        assert_eq!(points[0].velocity, None);
        let error = parse_trajectories("trajectory,frame,x,y\n", "t.csv").unwrap_err();
        assert!(
            error.to_string().contains("t.csv: line 1, column z"),
            "{error}"
        );
        let error =
            parse_trajectories("trajectory,frame,x,y,z\n-1,0,0,0,0\n", "t.csv").unwrap_err();
        assert!(
            error.to_string().contains("line 2, column trajectory"),
            "{error}"
        );
    }

    #[test]
    fn header_only_is_no_points() {
        assert!(parse_points("x,y,z\n", "p").unwrap().is_empty());
        assert!(parse_observations("point,camera,x,y", "o", 2)
            .unwrap()
            .is_empty());
    }

    #[test]
    fn points_errors_name_line_and_column() {
        for (text, expected) in [
            (
                "x,y,z\n1,2,3\n4,abc,6\n",
                "points.csv: line 3, column y: expected a finite number, got \"abc\"",
            ),
            ("x,y,z\n1,2,NaN\n", "line 2, column z"),
            ("x,y,z\n1,inf,3\n", "line 2, column y"),
            (
                "x,y,z\n1,,3\n",
                "line 2, column y: expected a number, found an empty field",
            ),
            (
                "x,y\n1,2\n",
                "points.csv: line 1, column z: the header has no column `z`",
            ),
            ("1,2,3\n", "line 1, column x: the header has no column `x`"),
            (
                "x,y,z,x\n1,2,3,4\n",
                "line 1, column x: the header names column `x` twice",
            ),
            (
                "x,y,z\n1,2,3\n\n4,5\n",
                "points.csv: line 4: has 2 fields but the header has 3",
            ),
            ("x,y,z\n1,2,3,4\n", "line 2: has 4 fields"),
            ("", "points.csv: line 1: the table is empty"),
            ("  \n\n", "the table is empty"),
        ] {
            let message = points_error(text);
            assert!(message.contains(expected), "{text:?}: {message}");
        }
    }

    #[test]
    fn line_numbers_count_blank_lines_and_any_line_break() {
        for (text, line) in [
            ("x,y,z\n1,2,3\n\n\n4,a,6\n", 5),
            ("x,y,z\r\n1,2,3\r\n\r\n4,a,6\r\n", 4),
            ("x,y,z\r1,2,3\r4,a,6\r", 3),
            ("\n\nx,y,z\n1,2,3\n4,a,6", 5),
            ("x,y,z\n1,\"2\n\n\",3\n4,a,6\n", 5),
            ("x,y,z\n  \n1,2,3\n\t\n4,a,6\n", 5),
            ("\u{feff}x,y,z\n4,a,6\n", 2),
        ] {
            let message = points_error(text);
            assert!(
                message.contains(&format!("line {line}, column y")),
                "{text:?}: {message}"
            );
        }
    }

    #[test]
    fn error_messages_stay_on_one_short_line() {
        let long = "9".repeat(500);
        let message = points_error(&format!("x,y,z\n1,\"a\nb\",3\n1,{long}e9999,3\n"));
        assert!(
            message.contains("line 2, column y") && !message.contains('\n'),
            "{message}"
        );
        let message = points_error(&format!("x,y,z\n1,2,3\n1,{long}x,3\n"));
        assert!(
            message.contains("line 3, column y") && message.len() < 200,
            "{message}"
        );
    }

    #[test]
    fn observations_are_grouped_and_sorted_by_point() {
        let text = "point,camera,x,y\n12,2,1.5,2.5\n3,0,10,20\n12,0,-1,0.25\n3,1,11,21\n";
        let points = parse_observations(text, "obs.csv", 3).unwrap();
        let obs = |camera, x, y| Observation {
            camera,
            pixel: Point2::new(x, y),
        };
        assert_eq!(
            points,
            vec![
                ObservedPoint {
                    point: 3,
                    observations: vec![obs(0, 10.0, 20.0), obs(1, 11.0, 21.0)],
                },
                ObservedPoint {
                    point: 12,
                    observations: vec![obs(2, 1.5, 2.5), obs(0, -1.0, 0.25)],
                },
            ]
        );
    }

    #[test]
    fn observations_errors_name_line_and_column() {
        for (text, expected) in [
            ("point,camera,x,y\n0,3,1,2\n", "obs.csv: line 2, column camera: camera 3 does not exist: the calibration has 3 cameras"),
            ("point,camera,x,y\n0,-1,1,2\n", "line 2, column camera: expected a non-negative integer"),
            ("point,camera,x,y\n-4,0,1,2\n", "line 2, column point: expected a non-negative integer"),
            ("point,camera,x,y\n1.5,0,1,2\n", "line 2, column point"),
            ("point,camera,x,y\n99999999999999999999,0,1,2\n", "line 2, column point"),
            ("point,camera,x,y\n0,0,1,2\n1,0,1,2\n0,0,3,4\n", "line 4, column camera: point 0 already has an observation in camera 0, on line 2"),
            ("point,camera,x,y\n0,0,NaN,2\n", "line 2, column x"),
            ("point,camera,x,y\n0,0,1,-inf\n", "line 2, column y"),
            ("point,x,y\n0,1,2\n", "line 1, column camera: the header has no column `camera`"),
        ] {
            let message = observations_error(text);
            assert!(message.contains(expected), "{text:?}: {message}");
        }
    }

    #[test]
    fn targets_with_and_without_optional_columns() {
        let full = parse_targets("x,y,n,nx,ny,sumg\n1.5,2.5,9,3,3,400\n", "t.csv").unwrap();
        assert_eq!(
            full,
            vec![Target {
                x: 1.5,
                y: 2.5,
                n: 9,
                nx: 3,
                ny: 3,
                sumg: 400
            }]
        );
        assert_eq!(
            parse_targets(&format_targets(&full), "again").unwrap(),
            full
        );
        let bare = parse_targets("y,x\n2.5,1.5\n", "t.csv").unwrap();
        assert_eq!(
            bare,
            vec![Target {
                x: 1.5,
                y: 2.5,
                n: 0,
                nx: 0,
                ny: 0,
                sumg: 0
            }]
        );
        let message = parse_targets("x,y,n\n1,2,-3\n", "t.csv")
            .unwrap_err()
            .to_string();
        assert!(message.contains("line 2, column n"), "{message}");
        assert!(parse_targets("x,n\n1,2\n", "t.csv").is_err());
    }

    #[test]
    fn intersections_table() {
        let intersection = Intersection {
            point: Point3::new(1.0, -2.5, 0.1),
            sigma: Vector3::new(0.001, 0.002, 0.003),
            sigma0_px: 0.1,
            residuals_px: Vec::new(),
            rms_px: 0.05,
            iterations: 3,
        };
        assert_eq!(
            format_intersections(&[(4, intersection)]),
            "point,x,y,z,sx,sy,sz,rms_px\n4,1.0,-2.5,0.1,0.001,0.002,0.003,0.05\n"
        );
    }

    #[test]
    fn particles_table() {
        let particle = Particle {
            position: Point3::new(1.0, -2.5, 0.1),
            sigma: Vector3::new(0.001, 0.002, 0.003),
            rms_px: 0.05,
            targets: vec![Some(7), None, Some(0)],
        };
        assert_eq!(
            format_particles(&[particle], 3),
            "x,y,z,sx,sy,sz,rms_px,cameras,t0,t1,t2\n\
             1.0,-2.5,0.1,0.001,0.002,0.003,0.05,2,7,-1,0\n"
        );
        assert_eq!(
            format_particles(&[], 2),
            "x,y,z,sx,sy,sz,rms_px,cameras,t0,t1\n"
        );
    }

    #[test]
    fn particles_read_back_with_and_without_sigmas_and_targets() {
        let particle = Particle {
            position: Point3::new(1.0, -2.5, 0.1),
            sigma: Vector3::new(0.001, 0.002, 0.003),
            rms_px: 0.05,
            targets: vec![Some(7), None, Some(0)],
        };
        let read =
            parse_particles(&format_particles(std::slice::from_ref(&particle), 3), "p").unwrap();
        assert_eq!(
            read,
            vec![ParticleRow {
                position: particle.position,
                sigma: Some(particle.sigma),
                targets: particle.targets,
            }]
        );
        let bare = parse_particles("x,y,z\n1,2,3\n", "p").unwrap();
        assert_eq!(bare[0].sigma, None);
        assert!(bare[0].targets.is_empty());
        let error = parse_particles("x,y,z,t0\n1,2,3,-2\n", "p.csv")
            .unwrap_err()
            .to_string();
        assert!(error.contains("line 2, column t0"), "{error}");
    }

    /// `push_debug_f64` against `{:?}` at the edges of both exponent
    /// thresholds (1e-5, 1e-4, 1e16 and their neighbouring doubles), zero,
    /// subnormals, the extremes, non-finite values, typical mm values, and
    /// 200,000 random bit patterns (every exponent, so every path).
    #[test]
    fn debug_f64_writer_is_debug_byte_for_byte() {
        let mut values = vec![
            0.0,
            1.0,
            0.1,
            1e-3,
            1e-7,
            1e15,
            1e17,
            1e21,
            1e22,
            1e-300,
            123.456,
            17.539751611039996,
            -0.046441767655608146,
            0.020434514043289765,
            9999999999999998.0,
            f64::MIN_POSITIVE,
            f64::MIN_POSITIVE / 3.0,
            5e-324,
            f64::MAX,
            f64::EPSILON,
            f64::NAN,
            f64::INFINITY,
            // Ties between two shortest strings (see push_debug_f64).
            1_308_548_795_726_862.0 + 0.25,
            17.0 + 3.0 / 65536.0,
            17.0 + 12345.0 / 65536.0,
            0.5 + 1.0 / 1024.0,
        ];
        values.extend((1..2000).map(|i| 16.0 + f64::from(2 * i + 1) / 65536.0));
        for edge in [1e-5, 1e-4, 1e16, 2.9e-5] {
            let bits = f64::to_bits(edge);
            values.extend((bits - 3..=bits + 3).map(f64::from_bits));
        }
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        for _ in 0..200_000 {
            // splitmix64
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            let z = z ^ (z >> 31);
            values.push(f64::from_bits(z));
            // And a measured value's magnitude: 1e-3 up to 1e4 mm.
            let unit = (z >> 11) as f64 / (1u64 << 53) as f64;
            values.push(10f64.powf(-3.0 + 7.0 * unit));
        }
        let mut buffer = ryu::Buffer::new();
        for value in values.iter().flat_map(|v| [*v, -*v]) {
            let mut out = String::new();
            push_debug_f64(&mut out, &mut buffer, value);
            assert_eq!(out, format!("{value:?}"), "bits {:#x}", value.to_bits());
        }
    }

    /// A trajectory point's line, as the writer of `{:?}` and `write!` wrote
    /// it before it used Ryū and itoa.
    #[test]
    fn trajectory_point_lines_are_as_debug_writes_them() {
        let targets = [Some(12), None, Some(0)];
        for (velocity, acceleration, sigma, with_targets) in [
            (
                Some([-0.7464578964550697, 0.24667860351803483, 3e-5]),
                Some([-0.046441767655608146, 1e-17, 0.0]),
                Some([
                    0.020434514043289765,
                    0.0188086356392223,
                    0.048098095351484974,
                ]),
                true,
            ),
            (None, None, None, false),
        ] {
            let line = TrajectoryPointLine {
                trajectory: 17823,
                frame: 49,
                position: [17.539751611039996, -23.63364248053819, 1e16],
                velocity,
                acceleration,
                velocity_sigma: sigma,
                targets: with_targets.then_some(&targets[..]),
            };
            let mut out = String::new();
            write_trajectory_point(&mut out, &line, 3);
            let f = |v: Option<[f64; 3]>, none: &str| match v {
                Some([a, b, c]) => format!("{a:?},{b:?},{c:?}"),
                None => none.to_owned(),
            };
            let expected = format!(
                "17823,49,17.539751611039996,-23.63364248053819,1e16,{},{},{},{}\n",
                f(velocity, "NaN,NaN,NaN"),
                f(acceleration, ",,"),
                f(sigma, "NaN,NaN,NaN"),
                if with_targets { "2,12,-1,0" } else { ",,," },
            );
            assert_eq!(out, expected);
        }
    }

    fn finite() -> impl Strategy<Value = f64> {
        prop_oneof![
            -1e4..1e4f64,
            any::<f64>().prop_filter("finite", |v| v.is_finite()),
        ]
    }

    proptest! {
        #[test]
        fn points_round_trip_exactly(coords in prop::collection::vec((finite(), finite(), finite()), 0..20)) {
            let points: Vec<Point3<f64>> = coords.into_iter().map(|(x, y, z)| Point3::new(x, y, z)).collect();
            prop_assert_eq!(parse_points(&format_points(&points), "p").unwrap(), points);
        }

        #[test]
        fn observations_round_trip_exactly(
            table in prop::collection::btree_map(any::<u64>(), prop::collection::btree_map(0..4usize, (finite(), finite()), 0..4), 0..20)
        ) {
            let points: Vec<ObservedPoint> = table
                .into_iter()
                .filter(|(_, images)| !images.is_empty())
                .map(|(point, images)| ObservedPoint {
                    point,
                    observations: images
                        .into_iter()
                        .map(|(camera, (x, y))| Observation { camera, pixel: Point2::new(x, y) })
                        .collect(),
                })
                .collect();
            prop_assert_eq!(parse_observations(&format_observations(&points), "o", 4).unwrap(), points);
        }
    }
}
