//! OpenPTV's calibration files: `.ori`, `.addpar` and `ptv.par`.
//!
//! - `.ori`: X0 Y0 Z0 (mm); omega phi kappa (rad); the 3x3 rotation matrix
//!   (informative: recomputed from the angles on read); xh yh (mm); c (mm);
//!   the glass vector (mm). Whitespace-separated, blank lines between blocks.
//! - `.addpar`: `k1 k2 k3 p1 p2 scx she` on one line; a missing file means
//!   no distortion.
//! - `ptv.par`: one value per line: number of cameras; per camera an image
//!   name and a calibration image name; highpass flag; all-cameras flag;
//!   TIFF flag; image width; image height; pixel size x; pixel size y; field
//!   flag; n1 (air); n2 (wall); n3 (object); wall thickness (mm).
//!
//! - `_targets` (`cam1.10001_targets`): the count, then per target
//!   `pnr x y n nx ny sumg tnr` (pixels; `pnr` numbers the targets 0..N-1 in
//!   file order; `tnr` links to a 3D result, -1 for none).
//!
//! OpenPTV describes one sensor and one wall for all cameras; export refuses
//! calibrations that do not fit that rather than silently changing them.
//! Numbers are written in their shortest exact form, so an export and
//! re-import returns the same calibration bit for bit.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use super::calibration;
use super::{read_text, write_text, FormatError};
use crate::photogrammetry::{
    Camera, CameraParameters, Distortion, Exterior, Interior, Media, Sensor, Target, Wall,
};

/// The parts of OpenPTV's `ptv.par` that describe the cameras.
#[derive(Clone, Debug, PartialEq)]
pub struct PtvPar {
    /// Per camera: image name and calibration image name.
    pub image_names: Vec<(String, String)>,
    /// The sensor shared by all cameras.
    pub sensor: Sensor,
    /// Refractive index of air (n1).
    pub n_air: f64,
    /// Refractive index of the wall (n2).
    pub n_wall: f64,
    /// Refractive index of the object medium (n3).
    pub n_object: f64,
    /// Wall thickness (mm).
    pub thickness: f64,
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
        Some((i, line)) => line.trim().parse::<usize>().map_err(|_| {
            FormatError::invalid(
                source,
                format!("line {}", i + 1),
                format!("expected the number of targets, got `{}`", line.trim()),
            )
        })?,
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
        let at = format!("line {}", i + 1);
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != 8 {
            return Err(FormatError::invalid(
                source,
                at,
                format!(
                    "expected 8 values `pnr x y n nx ny sumg tnr`, found {}",
                    fields.len()
                ),
            ));
        }
        let integer = |k: usize, what: &str| -> Result<u64, FormatError> {
            fields[k].parse::<u64>().map_err(|_| {
                FormatError::invalid(
                    source,
                    at.clone(),
                    format!("{what} must be a non-negative integer, got `{}`", fields[k]),
                )
            })
        };
        let small = |k: usize, what: &str| -> Result<u32, FormatError> {
            u32::try_from(integer(k, what)?).map_err(|_| {
                FormatError::invalid(source, at.clone(), format!("{what} is too large"))
            })
        };
        let coordinate = |k: usize, what: &str| finite_number(fields[k], source, i + 1, what);
        let pnr = integer(0, "pnr")?;
        if pnr != targets.len() as u64 {
            return Err(FormatError::invalid(
                source,
                at,
                format!("pnr {pnr} out of sequence: targets must be numbered 0, 1, 2, ... in file order, expected {}", targets.len()),
            ));
        }
        targets.push(Target {
            x: coordinate(1, "x")?,
            y: coordinate(2, "y")?,
            n: small(3, "n")?,
            nx: small(4, "nx")?,
            ny: small(5, "ny")?,
            sumg: integer(6, "sumg")?,
        });
        fields[7].parse::<i64>().map_err(|_| {
            FormatError::invalid(
                source,
                format!("line {}", i + 1),
                format!("tnr must be an integer, got `{}`", fields[7]),
            )
        })?;
    }
    if targets.len() != count {
        return Err(FormatError::invalid(
            source,
            "line 1",
            format!(
                "announces {count} targets but the file lists {}",
                targets.len()
            ),
        ));
    }
    Ok(targets)
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

/// Parses `ptv.par`.
pub fn parse_ptv_par(text: &str, source: &str) -> Result<PtvPar, FormatError> {
    let lines: Vec<&str> = text.lines().map(str::trim).collect();
    let line = |index: usize, what: &str| -> Result<&str, FormatError> {
        match lines.get(index) {
            Some(l) if !l.is_empty() => Ok(l.split_whitespace().next().unwrap_or(l)),
            _ => Err(FormatError::invalid(
                source,
                format!("line {}", index + 1),
                format!(
                    "expected {what}, found {}",
                    if index < lines.len() {
                        "an empty line"
                    } else {
                        "the end of the file"
                    }
                ),
            )),
        }
    };
    let parse = |index: usize, what: &str| -> Result<f64, FormatError> {
        finite_number(line(index, what)?, source, index + 1, what)
    };
    let count = parse(0, "the number of cameras")?;
    if count < 1.0 || count.fract() != 0.0 {
        return Err(FormatError::invalid(
            source,
            "line 1",
            format!("the number of cameras must be a positive integer, got {count}"),
        ));
    }
    // Before the per-camera lists are allocated.
    if count > calibration::MAX_CAMERAS as f64 {
        return Err(FormatError::invalid(
            source,
            "line 1",
            format!(
                "the number of cameras is {count}, more than the limit of {} (MAX_CAMERAS); \
                 give the rig's camera count",
                calibration::MAX_CAMERAS
            ),
        ));
    }
    let count = count as usize;
    let mut image_names = Vec::with_capacity(count);
    for k in 0..count {
        image_names.push((
            line(1 + 2 * k, &format!("the image name of camera {}", k + 1))?.to_owned(),
            line(
                2 + 2 * k,
                &format!("the calibration image name of camera {}", k + 1),
            )?
            .to_owned(),
        ));
    }
    let base = 1 + 2 * count;
    let size = |index: usize, what: &str| -> Result<u32, FormatError> {
        let value = parse(index, what)?;
        if value >= 1.0 && value.fract() == 0.0 && value <= f64::from(u32::MAX) {
            Ok(value as u32)
        } else {
            Err(FormatError::invalid(
                source,
                format!("line {}", index + 1),
                format!("{what} must be a positive integer, got {value}"),
            ))
        }
    };
    let width = size(base + 3, "the image width")?;
    let height = size(base + 4, "the image height")?;
    let pixel_size_x = parse(base + 5, "the pixel size x")?;
    let pixel_size_y = parse(base + 6, "the pixel size y")?;
    let field = parse(base + 7, "the field flag")?;
    if field != 0.0 {
        return Err(FormatError::invalid(
            source,
            format!("line {}", base + 8),
            format!("field-interlaced images (field flag {field}) are not supported; set it to 0"),
        ));
    }
    Ok(PtvPar {
        image_names,
        sensor: Sensor {
            width,
            height,
            pixel_size_x,
            pixel_size_y,
        },
        n_air: parse(base + 8, "n1 (air)")?,
        n_wall: parse(base + 9, "n2 (wall)")?,
        n_object: parse(base + 10, "n3 (object medium)")?,
        thickness: parse(base + 11, "the wall thickness")?,
    })
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
    if par.image_names.len() != cameras.len() {
        return Err(FormatError::invalid(
            par_source,
            "line 1",
            format!(
                "describes {} cameras but {} .ori files were given; give one .ori per camera, in camera order",
                par.image_names.len(),
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
            sensor: par.sensor.clone(),
            exterior,
            interior,
            distortion,
            media: Media {
                n_air: par.n_air,
                walls: vec![Wall {
                    n: par.n_wall,
                    thickness: par.thickness,
                }],
                n_object: par.n_object,
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

    #[test]
    fn ptv_par_camera_count_is_bounded_before_the_names_are_read() {
        let par = |count: usize| {
            let mut text = format!("{count}\n");
            for k in 1..=count {
                text += &format!("img/cam{k}.10003\ncal/cam{k}.tif\n");
            }
            text + "1\n0\n1\n1280\n1024\n0.012\n0.012\n0\n1\n1.33\n1.46\n6\n"
        };
        assert_eq!(
            parse_ptv_par(&par(16), "ptv.par")
                .unwrap()
                .image_names
                .len(),
            16
        );
        let message = parse_ptv_par(&par(17), "ptv.par").unwrap_err().to_string();
        assert!(
            message.starts_with(
                "ptv.par: line 1: the number of cameras is 17, more than the \
                                 limit of 16 (MAX_CAMERAS)"
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
    fn ptv_par_errors_name_the_line() {
        let message = parse_ptv_par("2\na\nb\nc\n", "ptv.par")
            .unwrap_err()
            .to_string();
        assert!(message.contains("line 5"), "{message}");
        let message = parse_ptv_par("two\n", "ptv.par").unwrap_err().to_string();
        assert!(message.contains("line 1"), "{message}");
    }
}
