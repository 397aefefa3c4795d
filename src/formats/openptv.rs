//! OpenPTV's calibration files: `.ori`, `.addpar` and `ptv.par`.
//!
//! - `.ori`: X0 Y0 Z0 (mm); omega phi kappa (rad); the 3x3 rotation matrix
//!   (informative: recomputed from the angles on read); xh yh (mm); c (mm);
//!   the glass vector (mm). Whitespace-separated, blank lines between blocks.
//! - `.addpar`: `k1 k2 k3 p1 p2 scx she` on one line; a missing file means
//!   no distortion.
//! - `ptv.par`: one value per line, in liboptv's `read_control_par` order
//!   and under its names ([`PtvPar`]): `num_cams`; per camera `img_name`
//!   and `img_cal`; `hp_flag`; `allcam_flag`; `tiff_flag`; `imx`, `imy`
//!   (px); `pix_x`, `pix_y` (mm); `chfield`; `mmp_n1` (air), `mmp_n2`
//!   (wall), `mmp_n3` (object); `mmp_d` (wall thickness, mm). This one
//!   reader serves the calibration import and the experiment importer
//!   ([`super::experiment`]), whose other `.par` files go through the same
//!   line reader; errors name the file, the line and the key.
//!
//! - `_targets` (`cam1.10001_targets`): the count, then per target
//!   `pnr x y n nx ny sumg tnr` (pixels; `pnr` numbers the targets 0..N-1 in
//!   file order; `tnr` links to a 3D result, -1 for none).
//!
//! OpenPTV describes one sensor and one wall for all cameras; export refuses
//! calibrations that do not fit that rather than silently changing them.
//! Numbers are written in their shortest exact form, so an export and
//! re-import returns the same calibration bit for bit.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use super::calibration;
use super::{read_text, write_text, FormatError};
use crate::photogrammetry::{
    Camera, CameraParameters, Distortion, Exterior, Interior, Media, Sensor, Target, Wall,
};

/// OpenPTV's `ptv.par`, every field of it, named as liboptv's
/// `read_control_par` and pyptv's YAML section `ptv` name them, in the
/// file's order.
#[derive(Clone, Debug, PartialEq)]
pub struct PtvPar {
    /// Per camera, the image of one frame (pyptv's single-frame preview).
    pub img_name: Vec<String>,
    /// Per camera, its calibration image.
    pub img_cal: Vec<String>,
    /// Whether images are high-pass filtered before detection.
    pub hp_flag: bool,
    /// Whether only particles seen by every camera are kept.
    pub allcam_flag: bool,
    /// Whether the images are TIFF files.
    pub tiff_flag: bool,
    /// Image width (px).
    pub imx: u32,
    /// Image height (px).
    pub imy: u32,
    /// Pixel size x (mm).
    pub pix_x: f64,
    /// Pixel size y (mm).
    pub pix_y: f64,
    /// 0 for full frames; 1 and 2 for the odd and even fields of
    /// interlaced images.
    pub chfield: i64,
    /// Refractive index of air (n1).
    pub mmp_n1: f64,
    /// Refractive index of the wall (n2).
    pub mmp_n2: f64,
    /// Refractive index of the object medium (n3).
    pub mmp_n3: f64,
    /// Wall thickness (mm).
    pub mmp_d: f64,
    /// The 1-based line of each key (`img_name[1]`, `imx`, ...).
    lines: BTreeMap<String, usize>,
}

impl PtvPar {
    /// The number of cameras (the first line).
    pub fn num_cams(&self) -> usize {
        self.img_name.len()
    }

    /// The sensor shared by all cameras.
    pub fn sensor(&self) -> Sensor {
        Sensor {
            width: self.imx,
            height: self.imy,
            pixel_size_x: self.pix_x,
            pixel_size_y: self.pix_y,
        }
    }

    /// Where `key` was read: `line 12, imx` (the key alone if unknown).
    pub fn location(&self, key: &str) -> String {
        match self.lines.get(key) {
            Some(line) => format!("line {line}, {key}"),
            None => key.to_owned(),
        }
    }

    /// Every key with the 1-based line it was read from, in key order.
    pub fn lines(&self) -> impl Iterator<Item = (&str, usize)> {
        self.lines.iter().map(|(key, &line)| (key.as_str(), line))
    }
}

/// An OpenPTV `.par` file: one value per line in a fixed order, each read
/// under its key (the first whitespace-separated token of the line, as
/// liboptv's `fscanf` takes it). Errors name the source, the line and the
/// key (`line 5, targ_rec.disco`, the key after a prefix naming the
/// section where the file is one of an experiment's).
pub(crate) struct ParLines {
    source: String,
    prefix: String,
    lines: Vec<String>,
    next: usize,
    read: BTreeMap<String, usize>,
}

impl ParLines {
    /// `prefix` goes before every key in errors: `targ_rec.` or empty.
    pub(crate) fn new(text: &str, source: &str, prefix: &str) -> Self {
        ParLines {
            source: source.to_owned(),
            prefix: prefix.to_owned(),
            lines: text.lines().map(|l| l.trim().to_owned()).collect(),
            next: 0,
            read: BTreeMap::new(),
        }
    }

    /// An error about `key`, placed at its line (or at the line last read).
    pub(crate) fn invalid(&self, key: &str, reason: impl Into<String>) -> FormatError {
        let line = self.line_of(key).unwrap_or(self.next.max(1));
        FormatError::invalid(
            &self.source,
            format!("line {line}, {}{key}", self.prefix),
            reason,
        )
    }

    /// The next line's first token, read as `key`.
    pub(crate) fn text(&mut self, key: &str) -> Result<String, FormatError> {
        let index = self.next;
        self.next += 1;
        match self.lines.get(index) {
            Some(line) if !line.is_empty() => {
                self.read.insert(key.to_owned(), index + 1);
                Ok(line.split_whitespace().next().unwrap_or(line).to_owned())
            }
            found => Err(FormatError::invalid(
                &self.source,
                format!("line {}, {}{key}", index + 1, self.prefix),
                format!(
                    "expected {key}, found {}",
                    if found.is_some() {
                        "an empty line"
                    } else {
                        "the end of the file"
                    }
                ),
            )),
        }
    }

    /// The next value as a finite number.
    pub(crate) fn number(&mut self, key: &str) -> Result<f64, FormatError> {
        let token = self.text(key)?;
        token
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| self.invalid(key, format!("expected a number, got `{token}`")))
    }

    /// The next value as an integer (liboptv's `%d`).
    pub(crate) fn integer(&mut self, key: &str) -> Result<i64, FormatError> {
        let token = self.text(key)?;
        token
            .parse::<i64>()
            .map_err(|_| self.invalid(key, format!("expected an integer, got `{token}`")))
    }

    /// The next value as a whole number >= 0.
    pub(crate) fn unsigned(&mut self, key: &str) -> Result<u64, FormatError> {
        let value = self.integer(key)?;
        u64::try_from(value)
            .map_err(|_| self.invalid(key, format!("expected a whole number >= 0, got {value}")))
    }

    /// The next value as a flag: an integer, non-zero for on.
    pub(crate) fn flag(&mut self, key: &str) -> Result<bool, FormatError> {
        Ok(self.integer(key)? != 0)
    }

    /// The 1-based line `key` was read from.
    pub(crate) fn line_of(&self, key: &str) -> Option<usize> {
        self.read.get(key).copied()
    }

    /// The keys read so far with their 1-based lines.
    pub(crate) fn read(&self) -> impl Iterator<Item = (&str, usize)> {
        self.read.iter().map(|(key, &line)| (key.as_str(), line))
    }
}

/// A token as a finite number, or an error naming the source, the line and
/// what was expected.
pub(crate) fn finite_number(
    token: &str,
    source: &str,
    line: usize,
    what: &str,
) -> Result<f64, FormatError> {
    token
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| {
            FormatError::invalid(
                source,
                format!("line {line}"),
                format!("{what} must be a finite number, got `{token}`"),
            )
        })
}

/// A whitespace-separated token with its 1-based line number.
struct Tokens<'a> {
    source: &'a str,
    tokens: Vec<(usize, &'a str)>,
    next: usize,
    last_line: usize,
}

impl<'a> Tokens<'a> {
    fn new(text: &'a str, source: &'a str) -> Self {
        let tokens = text
            .lines()
            .enumerate()
            .flat_map(|(i, line)| line.split_whitespace().map(move |t| (i + 1, t)))
            .collect();
        Tokens {
            source,
            tokens,
            next: 0,
            last_line: text.lines().count().max(1),
        }
    }

    fn number(&mut self, what: &str) -> Result<f64, FormatError> {
        let Some(&(line, token)) = self.tokens.get(self.next) else {
            return Err(FormatError::invalid(
                self.source,
                format!("line {}", self.last_line),
                format!("the file ends where {what} was expected"),
            ));
        };
        self.next += 1;
        finite_number(token, self.source, line, what)
    }

    fn finish(&self) -> Result<(), FormatError> {
        match self.tokens.get(self.next) {
            None => Ok(()),
            Some(&(line, token)) => Err(FormatError::invalid(
                self.source,
                format!("line {line}"),
                format!("unexpected extra value `{token}` after the last expected one"),
            )),
        }
    }
}

/// Parses a `.ori` file into exterior and interior orientation and the glass vector.
pub fn parse_ori(
    text: &str,
    source: &str,
) -> Result<(Exterior, Interior, Vector3<f64>), FormatError> {
    let mut t = Tokens::new(text, source);
    let position = Vector3::new(t.number("X0")?, t.number("Y0")?, t.number("Z0")?);
    let (omega, phi, kappa) = (t.number("omega")?, t.number("phi")?, t.number("kappa")?);
    for i in 0..9 {
        t.number(&format!("rotation matrix element {}", i + 1))?;
    }
    let (xh, yh) = (t.number("xh")?, t.number("yh")?);
    let c = t.number("the principal distance c")?;
    let glass = Vector3::new(
        t.number("glass vector x")?,
        t.number("glass vector y")?,
        t.number("glass vector z")?,
    );
    t.finish()?;
    Ok((
        Exterior {
            position,
            omega,
            phi,
            kappa,
        },
        Interior { c, xh, yh },
        glass,
    ))
}

/// Parses a `.addpar` file.
pub fn parse_addpar(text: &str, source: &str) -> Result<Distortion, FormatError> {
    let mut t = Tokens::new(text, source);
    let distortion = Distortion {
        k1: t.number("k1")?,
        k2: t.number("k2")?,
        k3: t.number("k3")?,
        p1: t.number("p1")?,
        p2: t.number("p2")?,
        scx: t.number("scx")?,
        shear: t.number("she")?,
    };
    t.finish()?;
    Ok(distortion)
}

/// Parses a `_targets` file; the targets keep their file order, which is
/// their `pnr`.
pub fn parse_targets(text: &str, source: &str) -> Result<Vec<Target>, FormatError> {
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let count = match lines.next() {
        Some((i, line)) => parse_target_count(line, i + 1, source)?,
        None => {
            return Err(FormatError::invalid(
                source,
                "line 1",
                "the file is empty; expected the number of targets",
            ))
        }
    };
    let mut targets = Vec::with_capacity(count.min(1 << 20));
    for (i, line) in lines {
        targets.push(parse_target_line(line, i + 1, targets.len(), source)?);
    }
    check_target_count(count, targets.len(), source)?;
    Ok(targets)
}

/// A `_targets` file's first line (line `number`, from 1): the count.
pub(crate) fn parse_target_count(
    line: &str,
    number: usize,
    source: &str,
) -> Result<usize, FormatError> {
    line.trim().parse::<usize>().map_err(|_| {
        FormatError::invalid(
            source,
            format!("line {number}"),
            format!("expected the number of targets, got `{}`", line.trim()),
        )
    })
}

/// Whether a `_targets` file listed the `count` targets it announced.
pub(crate) fn check_target_count(
    count: usize,
    listed: usize,
    source: &str,
) -> Result<(), FormatError> {
    if listed != count {
        return Err(FormatError::invalid(
            source,
            "line 1",
            format!("announces {count} targets but the file lists {listed}"),
        ));
    }
    Ok(())
}

/// A `_targets` file's target line (line `number`, from 1, not blank),
/// whose `pnr` must be `index`, its place in the file.
pub(crate) fn parse_target_line(
    line: &str,
    number: usize,
    index: usize,
    source: &str,
) -> Result<Target, FormatError> {
    // The line's name only for an error, and its fields without an
    // allocation: 10,000 targets are read in a few ms.
    let at = || format!("line {number}");
    let mut fields = [""; 8];
    let found = ascii_fields(line, &mut fields);
    if found != 8 {
        return Err(FormatError::invalid(
            source,
            at(),
            format!("expected 8 values `pnr x y n nx ny sumg tnr`, found {found}"),
        ));
    }
    let integer = |k: usize, what: &str| -> Result<u64, FormatError> {
        fields[k].parse::<u64>().map_err(|_| {
            FormatError::invalid(
                source,
                at(),
                format!("{what} must be a non-negative integer, got `{}`", fields[k]),
            )
        })
    };
    let small = |k: usize, what: &str| -> Result<u32, FormatError> {
        u32::try_from(integer(k, what)?)
            .map_err(|_| FormatError::invalid(source, at(), format!("{what} is too large")))
    };
    let coordinate = |k: usize, what: &str| finite_number(fields[k], source, number, what);
    let pnr = integer(0, "pnr")?;
    if pnr != index as u64 {
        return Err(FormatError::invalid(
            source,
            at(),
            format!("pnr {pnr} out of sequence: targets must be numbered 0, 1, 2, ... in file order, expected {index}"),
        ));
    }
    let target = Target {
        x: coordinate(1, "x")?,
        y: coordinate(2, "y")?,
        n: small(3, "n")?,
        nx: small(4, "nx")?,
        ny: small(5, "ny")?,
        sumg: integer(6, "sumg")?,
    };
    fields[7].parse::<i64>().map_err(|_| {
        FormatError::invalid(
            source,
            at(),
            format!("tnr must be an integer, got `{}`", fields[7]),
        )
    })?;
    Ok(target)
}

/// Splits `line` at ASCII whitespace, the separators of liboptv's `fscanf`
/// (as `str::split_ascii_whitespace`, a byte scan without its iterator
/// adapters: a `_targets` line is mostly padding), into the first `N` slots
/// of `fields`; returns how many fields the line has, `N` or not.
fn ascii_fields<'a, const N: usize>(line: &'a str, fields: &mut [&'a str; N]) -> usize {
    let bytes = line.as_bytes();
    let (mut count, mut i) = (0, 0);
    loop {
        while i < bytes.len() && bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        if i == bytes.len() {
            return count;
        }
        let start = i;
        while i < bytes.len() && !bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        // Both ends sit next to ASCII bytes or the line's ends: char
        // boundaries.
        if let Some(slot) = fields.get_mut(count) {
            *slot = &line[start..i];
        }
        count += 1;
    }
}

/// Writes a `_targets` file (full precision; `tnr` -1).
pub fn format_targets(targets: &[Target]) -> String {
    let mut text = format!("{}\n", targets.len());
    for (pnr, t) in targets.iter().enumerate() {
        let _ = writeln!(
            text,
            "{pnr:4} {:?} {:?} {:5} {:5} {:5} {:5} -1",
            t.x, t.y, t.n, t.nx, t.ny, t.sumg
        );
    }
    text
}

/// Parses `ptv.par` (the order of liboptv's `read_control_par`); errors
/// name the line and the key: `ptv.par: line 3, img_name[1]: ...`.
pub fn parse_ptv_par(text: &str, source: &str) -> Result<PtvPar, FormatError> {
    read_ptv_par(text, source, "")
}

/// [`parse_ptv_par`] with `prefix` before every key in errors (`ptv.`,
/// the section pyptv's YAML gives these keys, for an experiment's file).
pub(crate) fn read_ptv_par(text: &str, source: &str, prefix: &str) -> Result<PtvPar, FormatError> {
    let mut f = ParLines::new(text, source, prefix);
    let count = f.integer("num_cams")?;
    if count < 1 {
        return Err(f.invalid(
            "num_cams",
            format!("the number of cameras must be at least 1, got {count}"),
        ));
    }
    // Before the per-camera lists are allocated.
    if count > calibration::MAX_CAMERAS as i64 {
        return Err(f.invalid(
            "num_cams",
            format!(
                "the number of cameras is {count}, more than the limit of {} (MAX_CAMERAS); \
                 give the rig's camera count",
                calibration::MAX_CAMERAS
            ),
        ));
    }
    let count = count as usize;
    let (mut img_name, mut img_cal) = (Vec::with_capacity(count), Vec::with_capacity(count));
    for k in 0..count {
        img_name.push(f.text(&format!("img_name[{k}]"))?);
        img_cal.push(f.text(&format!("img_cal[{k}]"))?);
    }
    let hp_flag = f.flag("hp_flag")?;
    let allcam_flag = f.flag("allcam_flag")?;
    let tiff_flag = f.flag("tiff_flag")?;
    let mut size = |key: &str| -> Result<u32, FormatError> {
        let value = f.integer(key)?;
        u32::try_from(value)
            .ok()
            .filter(|&v| v >= 1)
            .ok_or_else(|| {
                f.invalid(
                    key,
                    format!("the image size must be a positive integer (px), got {value}"),
                )
            })
    };
    let imx = size("imx")?;
    let imy = size("imy")?;
    let mut par = PtvPar {
        img_name,
        img_cal,
        hp_flag,
        allcam_flag,
        tiff_flag,
        imx,
        imy,
        pix_x: f.number("pix_x")?,
        pix_y: f.number("pix_y")?,
        chfield: f.integer("chfield")?,
        mmp_n1: f.number("mmp_n1")?,
        mmp_n2: f.number("mmp_n2")?,
        mmp_n3: f.number("mmp_n3")?,
        mmp_d: f.number("mmp_d")?,
        lines: BTreeMap::new(),
    };
    par.lines = f.read().map(|(key, line)| (key.to_owned(), line)).collect();
    Ok(par)
}

/// The `.addpar` file beside a `.ori` file: `cam1.tif.ori` -> `cam1.tif.addpar`.
pub fn addpar_path(ori: &Path) -> PathBuf {
    let name = ori
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stem = name.strip_suffix(".ori").unwrap_or(&name);
    ori.with_file_name(format!("{stem}.addpar"))
}

/// A camera name from a `.ori` path: `cal/cam1.tif.ori` -> `cam1`.
fn camera_name(ori: &Path, index: usize) -> String {
    let name = ori
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut stem = name.strip_suffix(".ori").unwrap_or(&name);
    for extension in [".tif", ".tiff", ".png", ".bmp", ".jpg"] {
        if let Some(s) = stem.strip_suffix(extension) {
            stem = s;
        }
    }
    if stem.is_empty() {
        format!("cam{}", index + 1)
    } else {
        stem.to_owned()
    }
}

/// Builds cameras from `ptv.par` and one `.ori` per camera, in camera
/// order, each with its optional `.addpar` beside it.
pub fn import(ptv_par: &Path, oris: &[PathBuf]) -> Result<Vec<Camera>, FormatError> {
    let par_text = read_text(ptv_par)?;
    let mut texts = Vec::with_capacity(oris.len());
    for (index, ori) in oris.iter().enumerate() {
        let addpar = addpar_path(ori);
        let addpar = match std::fs::read_to_string(&addpar) {
            Ok(text) => Some((text, addpar.display().to_string())),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(reason) => {
                return Err(FormatError::Io {
                    path: addpar,
                    reason,
                })
            }
        };
        texts.push(OriTexts {
            name: camera_name(ori, index),
            ori: (read_text(ori)?, ori.display().to_string()),
            addpar,
        });
    }
    import_texts(&par_text, &ptv_par.display().to_string(), &texts)
}

/// One camera's OpenPTV files as text, each with the source to name in
/// errors, for callers that have them in memory (uploads).
#[derive(Clone, Debug)]
pub struct OriTexts {
    /// The camera's name.
    pub name: String,
    /// The `.ori` file's text and source.
    pub ori: (String, String),
    /// The `.addpar` file's text and source, if any (else no distortion).
    pub addpar: Option<(String, String)>,
}

/// Builds cameras from `ptv.par`'s text and, in camera order, each camera's
/// `.ori` and optional `.addpar` texts.
pub fn import_texts(
    ptv_par: &str,
    par_source: &str,
    cameras: &[OriTexts],
) -> Result<Vec<Camera>, FormatError> {
    let par = parse_ptv_par(ptv_par, par_source)?;
    if par.chfield != 0 {
        return Err(FormatError::invalid(
            par_source,
            par.location("chfield"),
            format!(
                "field-interlaced images (chfield {}) are not supported; set it to 0",
                par.chfield
            ),
        ));
    }
    if par.num_cams() != cameras.len() {
        return Err(FormatError::invalid(
            par_source,
            par.location("num_cams"),
            format!(
                "describes {} cameras but {} .ori files were given; give one .ori per camera, in camera order",
                par.num_cams(),
                cameras.len()
            ),
        ));
    }
    let mut parameters = Vec::with_capacity(cameras.len());
    for camera in cameras {
        let (exterior, interior, glass_vector) = parse_ori(&camera.ori.0, &camera.ori.1)?;
        let distortion = match &camera.addpar {
            Some((text, source)) => parse_addpar(text, source)?,
            None => Distortion::default(),
        };
        parameters.push(CameraParameters {
            name: camera.name.clone(),
            sensor: par.sensor(),
            exterior,
            interior,
            distortion,
            media: Media {
                n_air: par.mmp_n1,
                walls: vec![Wall {
                    n: par.mmp_n2,
                    thickness: par.mmp_d,
                }],
                n_object: par.mmp_n3,
                glass_vector,
            },
        });
    }
    calibration::from_parameters(parameters, &format!("{par_source} with its .ori files"))
}

/// Writes a `.ori` file's text.
pub fn format_ori(camera: &Camera) -> String {
    let p = camera.parameters();
    let (e, i) = (&p.exterior, &p.interior);
    let g = openptv_glass_vector(p);
    let r = camera.rotation();
    let mut text = String::new();
    let _ = writeln!(text, "{} {} {}", e.position.x, e.position.y, e.position.z);
    let _ = writeln!(text, "    {} {} {}\n", e.omega, e.phi, e.kappa);
    for row in 0..3 {
        let _ = writeln!(
            text,
            "    {:10.7} {:10.7} {:10.7}",
            r[(row, 0)],
            r[(row, 1)],
            r[(row, 2)]
        );
    }
    let _ = writeln!(text, "\n    {} {}\n    {}\n", i.xh, i.yh, i.c);
    let _ = writeln!(text, "    {} {} {}", g.x, g.y, g.z);
    text
}

/// Writes a `.addpar` file's text.
pub fn format_addpar(distortion: &Distortion) -> String {
    let d = distortion;
    format!(
        "{} {} {} {} {} {} {}\n",
        d.k1, d.k2, d.k3, d.p1, d.p2, d.scx, d.shear
    )
}

/// OpenPTV divides by the glass vector's length even without refraction, so
/// a camera whose media do not refract gets a plane halfway between the
/// origin and the camera, which changes nothing when all indices are equal.
fn openptv_glass_vector(p: &CameraParameters) -> Vector3<f64> {
    if p.media.glass_vector.norm() > 0.0 {
        p.media.glass_vector
    } else {
        p.exterior.position / 2.0
    }
}

/// Checks that the cameras fit OpenPTV's one-sensor, one-wall `ptv.par` and
/// returns its text.
pub fn format_ptv_par(cameras: &[Camera]) -> Result<String, String> {
    let first = cameras.first().ok_or("there are no cameras")?.parameters();
    let wall_of = |p: &CameraParameters| -> Result<Wall, String> {
        match p.media.walls.as_slice() {
            [] => Ok(Wall {
                n: p.media.n_air,
                thickness: 0.0,
            }),
            [wall] => Ok(wall.clone()),
            walls => Err(format!(
                "camera {} looks through {} walls, but OpenPTV's ptv.par describes exactly one",
                p.name,
                walls.len()
            )),
        }
    };
    let wall = wall_of(first)?;
    for camera in cameras {
        let p = camera.parameters();
        if p.sensor != first.sensor {
            return Err(format!(
                "camera {} has another sensor than camera {}; OpenPTV's ptv.par has one for all",
                p.name, first.name
            ));
        }
        if p.media.n_air != first.media.n_air
            || p.media.n_object != first.media.n_object
            || wall_of(p)? != wall
        {
            return Err(format!(
                "camera {} sees other media than camera {}; OpenPTV's ptv.par has one set of refractive indices and one wall for all",
                p.name, first.name
            ));
        }
    }
    let mut text = format!("{}\n", cameras.len());
    for camera in cameras {
        let _ = write!(text, "img/{0}\ncal/{0}.tif\n", camera.name());
    }
    let s = &first.sensor;
    let _ = write!(
        text,
        "1\n0\n1\n{}\n{}\n{}\n{}\n0\n{}\n{}\n{}\n{}\n",
        s.width,
        s.height,
        s.pixel_size_x,
        s.pixel_size_y,
        first.media.n_air,
        wall.n,
        first.media.n_object,
        wall.thickness
    );
    Ok(text)
}

/// Writes `ptv.par` and, per camera, `NAME.ori` and `NAME.addpar` into
/// `dir` (created if missing); returns the files written.
pub fn export(cameras: &[Camera], dir: &Path) -> Result<Vec<PathBuf>, FormatError> {
    let ptv_par = format_ptv_par(cameras)
        .map_err(|reason| FormatError::invalid("calibration", "cameras", reason))?;
    let mut names: Vec<&str> = cameras.iter().map(Camera::name).collect();
    names.sort_unstable();
    if let Some(pair) = names.windows(2).find(|w| w[0] == w[1]) {
        return Err(FormatError::invalid(
            "calibration",
            "cameras",
            format!("two cameras are named `{}`; OpenPTV files are named after the cameras, so names must differ", pair[0]),
        ));
    }
    if let Some(bad) = cameras.iter().find(|c| {
        c.name().is_empty() || c.name().contains(['/', '\\']) || c.name().starts_with('.')
    }) {
        return Err(FormatError::invalid(
            "calibration",
            "cameras",
            format!("camera name `{}` cannot be used as a file name", bad.name()),
        ));
    }
    std::fs::create_dir_all(dir).map_err(|reason| FormatError::Io {
        path: dir.to_owned(),
        reason,
    })?;
    let mut written = Vec::new();
    let mut write = |name: String, text: &str| -> Result<(), FormatError> {
        let path = dir.join(name);
        write_text(&path, text)?;
        written.push(path);
        Ok(())
    };
    write("ptv.par".into(), &ptv_par)?;
    for camera in cameras {
        write(format!("{}.ori", camera.name()), &format_ori(camera))?;
        write(
            format!("{}.addpar", camera.name()),
            &format_addpar(&camera.parameters().distortion),
        )?;
    }
    Ok(written)
}

/// Writes particles as OpenPTV's `rt_is` file: the count, then per particle
/// `pnr x y z t0 t1 ...` (pnr from 1, mm with 3 decimals as OpenPTV writes
/// them, each camera's target index or -1), one column per camera.
pub fn format_rt_is(
    particles: &[crate::photogrammetry::correspond::Particle],
    cameras: usize,
) -> String {
    use std::fmt::Write as _;
    let mut text = format!("{}\n", particles.len());
    for (index, p) in particles.iter().enumerate() {
        let _ = write!(
            text,
            "{:4} {:9.3} {:9.3} {:9.3}",
            index + 1,
            p.position.x,
            p.position.y,
            p.position.z
        );
        for camera in 0..cameras {
            let target = p.targets.get(camera).copied().flatten();
            let _ = write!(text, " {:4}", target.map_or(-1, |t| t as i64));
        }
        text.push('\n');
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    const ORI: &str = "82.96897532 12.21372353 -569.03076947\n    -56.54284096  2.97360259  56.53126707\n\n    -0.9857736 -0.0171549  0.1672010\n    -0.0164254  0.9998486  0.0057447\n    -0.1672743  0.0029167 -0.9859061\n\n      0.0000   0.0000\n     70.0000\n\n       0.0 0.0 -125.0\n";

    #[test]
    fn parses_ori() {
        let (e, i, g) = parse_ori(ORI, "cam1.tif.ori").unwrap();
        assert_eq!(
            e.position,
            Vector3::new(82.96897532, 12.21372353, -569.03076947)
        );
        assert_eq!(
            (e.omega, e.phi, e.kappa),
            (-56.54284096, 2.97360259, 56.53126707)
        );
        assert_eq!((i.xh, i.yh, i.c), (0.0, 0.0, 70.0));
        assert_eq!(g, Vector3::new(0.0, 0.0, -125.0));
    }

    #[test]
    fn ori_errors_name_the_line() {
        let truncated = ORI.replace("       0.0 0.0 -125.0\n", "       0.0 0.0\n");
        let message = parse_ori(&truncated, "cam1.ori").unwrap_err().to_string();
        assert!(
            message.contains("cam1.ori") && message.contains("glass vector z"),
            "{message}"
        );
        let garbage = ORI.replace("70.0000", "seventy");
        let message = parse_ori(&garbage, "cam1.ori").unwrap_err().to_string();
        assert!(
            message.contains("line 9") && message.contains("seventy"),
            "{message}"
        );
        let extra = format!("{ORI} 5");
        assert!(parse_ori(&extra, "x")
            .unwrap_err()
            .to_string()
            .contains("extra"));
    }

    #[test]
    fn addpar_round_trips() {
        let d = Distortion {
            k1: 0.00023688,
            k2: 4e-8,
            k3: 0.0,
            p1: -6.58e-6,
            p2: -8.72e-6,
            scx: 1.00151973,
            shear: -0.001529723,
        };
        assert_eq!(parse_addpar(&format_addpar(&d), "a").unwrap(), d);
        assert!(parse_addpar("1 2 3", "a").is_err());
    }

    #[test]
    fn targets_round_trip_and_errors_name_the_line() {
        let text = "2\n   0  126.0498    9.5295    10     3     6   271   671\n   1  128.0154   12.8830    16     5     5  1919    -1\n";
        let targets = parse_targets(text, "cam1.10001_targets").unwrap();
        assert_eq!(
            targets[1],
            Target {
                x: 128.0154,
                y: 12.883,
                n: 16,
                nx: 5,
                ny: 5,
                sumg: 1919
            }
        );
        assert_eq!(
            parse_targets(&format_targets(&targets), "again").unwrap(),
            targets
        );
        for (bad, expected) in [
            ("3\n   0  1 2 3 4 5 6 -1\n", "announces 3"),
            ("1\n   1  1 2 3 4 5 6 -1\n", "line 2"),
            ("1\n   0  1 x 3 4 5 6 -1\n", "line 2"),
            ("1\n   0  1 2 3 4 5\n", "8 values"),
            ("", "empty"),
        ] {
            let message = parse_targets(bad, "t").unwrap_err().to_string();
            assert!(message.contains(expected), "{bad:?}: {message}");
        }
        assert_eq!(parse_targets("0\n", "t").unwrap(), vec![]);
    }

    proptest::proptest! {
        #[test]
        fn target_fields_split_as_split_ascii_whitespace(
            line in "[ \t\r\x0b\x0c0-9a-z.\u{a0}\u{3000}é-]{0,60}"
        ) {
            let mut fields = [""; 8];
            let count = ascii_fields(&line, &mut fields);
            let expected: Vec<&str> = line.split_ascii_whitespace().collect();
            proptest::prop_assert_eq!(count, expected.len());
            let kept = count.min(8);
            proptest::prop_assert_eq!(&fields[..kept], &expected[..kept]);
        }
    }

    #[test]
    fn ptv_par_camera_count_is_bounded_before_the_names_are_read() {
        let par = |count: usize| {
            let mut text = format!("{count}\n");
            for k in 1..=count {
                text += &format!("img/cam{k}.10003\ncal/cam{k}.tif\n");
            }
            text + "1\n0\n1\n1280\n1024\n0.012\n0.012\n0\n1\n1.33\n1.46\n6\n"
        };
        assert_eq!(parse_ptv_par(&par(16), "ptv.par").unwrap().num_cams(), 16);
        let message = parse_ptv_par(&par(17), "ptv.par").unwrap_err().to_string();
        assert!(
            message.starts_with(
                "ptv.par: line 1, num_cams: the number of cameras is 17, more \
                 than the limit of 16 (MAX_CAMERAS)"
            ),
            "{message}"
        );
        // Refused from the count alone, as a billion would be.
        let message = parse_ptv_par("1000000000\n", "ptv.par")
            .unwrap_err()
            .to_string();
        assert!(message.contains("MAX_CAMERAS"), "{message}");
    }

    #[test]
    fn imported_camera_names_are_checked() {
        let ori = include_str!("../../tests/data/openptv/test_cavity/cal/cam1.tif.ori");
        let par = include_str!("../../tests/data/openptv/test_cavity/parameters/ptv.par");
        let texts = |first: &str| -> Vec<OriTexts> {
            (0..4)
                .map(|k| OriTexts {
                    name: if k == 0 {
                        first.to_owned()
                    } else {
                        format!("cam{}", k + 1)
                    },
                    ori: (ori.to_owned(), "cam.ori".to_owned()),
                    addpar: None,
                })
                .collect()
        };
        assert!(import_texts(par, "ptv.par", &texts("cam1")).is_ok());
        let message = import_texts(par, "ptv.par", &texts("../../etc/passwd"))
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("cameras[0].name: the camera name"),
            "{message}"
        );
    }

    #[test]
    fn ptv_par_keeps_every_field_with_its_line() {
        let text = include_str!("../../tests/data/openptv/test_cavity/parameters/ptv.par");
        let par = parse_ptv_par(text, "ptv.par").unwrap();
        assert_eq!(par.num_cams(), 4);
        assert_eq!(par.img_name[3], "img/cam4.10003");
        assert_eq!(par.img_cal[1], "cal/cam2.tif");
        assert_eq!(
            (par.hp_flag, par.allcam_flag, par.tiff_flag),
            (true, false, true)
        );
        assert_eq!(
            (par.imx, par.imy, par.pix_x, par.pix_y),
            (1280, 1024, 0.012, 0.012)
        );
        assert_eq!(par.chfield, 0);
        assert_eq!(
            (par.mmp_n1, par.mmp_n2, par.mmp_n3, par.mmp_d),
            (1.0, 1.33, 1.46, 6.0)
        );
        // 4 cameras: names on lines 2..9, then hp_flag on 10 ... mmp_d on 21.
        assert_eq!(par.location("img_cal[3]"), "line 9, img_cal[3]");
        assert_eq!(par.location("hp_flag"), "line 10, hp_flag");
        assert_eq!(par.location("mmp_d"), "line 21, mmp_d");
        assert_eq!(par.lines().count(), 1 + 2 * 4 + 12);
    }

    #[test]
    fn ptv_par_bad_values_name_the_line_and_the_key() {
        let text = include_str!("../../tests/data/openptv/test_cavity/parameters/ptv.par");
        let with_line = |line: usize, value: &str| {
            let mut lines: Vec<&str> = text.lines().collect();
            lines[line - 1] = value;
            lines.join("\n")
        };
        for (line, value, expected) in [
            (
                3,
                "",
                "ptv.par: line 3, img_cal[0]: expected img_cal[0], found an empty line",
            ),
            (
                11,
                "all",
                "ptv.par: line 11, allcam_flag: expected an integer, got `all`",
            ),
            (
                13,
                "1280.5",
                "ptv.par: line 13, imx: expected an integer, got `1280.5`",
            ),
            (
                14,
                "0",
                "ptv.par: line 14, imy: the image size must be a positive integer",
            ),
            (
                16,
                "NaN",
                "ptv.par: line 16, pix_y: expected a number, got `NaN`",
            ),
            (
                20,
                "glass",
                "ptv.par: line 20, mmp_n3: expected a number, got `glass`",
            ),
            (
                1,
                "0",
                "ptv.par: line 1, num_cams: the number of cameras must be at least 1",
            ),
        ] {
            let message = parse_ptv_par(&with_line(line, value), "ptv.par")
                .unwrap_err()
                .to_string();
            assert!(message.starts_with(expected), "{value:?}: {message}");
        }
        // A field the import cannot use is refused there, at its line.
        let ori = include_str!("../../tests/data/openptv/test_cavity/cal/cam1.tif.ori");
        let texts: Vec<OriTexts> = (0..4)
            .map(|k| OriTexts {
                name: format!("cam{}", k + 1),
                ori: (ori.to_owned(), "cam.ori".to_owned()),
                addpar: None,
            })
            .collect();
        let message = import_texts(&with_line(17, "1"), "ptv.par", &texts)
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("ptv.par: line 17, chfield: field-interlaced"),
            "{message}"
        );
        let message = import_texts(text, "ptv.par", &texts[..3])
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("ptv.par: line 1, num_cams: describes 4 cameras but 3 .ori"),
            "{message}"
        );
    }

    #[test]
    fn ptv_par_errors_name_the_line() {
        let message = parse_ptv_par("2\na\nb\nc\n", "ptv.par")
            .unwrap_err()
            .to_string();
        assert!(message.contains("line 5"), "{message}");
        let message = parse_ptv_par("two\n", "ptv.par").unwrap_err().to_string();
        assert!(message.contains("line 1"), "{message}");
    }
}
