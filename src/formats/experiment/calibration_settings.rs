//! An OpenPTV experiment's calibration settings, from the legacy
//! `parameters/` folder or pyptv's YAML (the same sections):
//!
//! | OpenPTV | `ptv` |
//! | --- | --- |
//! | `cal_ori`: `fixp_name`, `img_cal_name` | the control points (`id X Y Z`) and the calibration image per camera |
//! | `detect_plate`: `gvth_1..4`, `min_npix`, `max_npix`, `min_npix_x/y`, `max_npix_x/y`, `sum_grey`, `tol_dis` | [`DetectionParameters`] per camera: threshold, pixel counts, extents, `min_sumg`, `split_depth` (`size_cross` only draws crosses in pyptv's GUI) |
//! | `orient`: `cc`, `xh`, `yh`, `k1`..`p2`, `scale`, `shear` (1 = estimate) | the parameters held at the `.ori`/`.addpar` values (0 = fixed); `pnfo` and `interf` are not used |
//! | `man_ori` (`nr`: 4 point ids per camera) with `man_ori.dat` (legacy: 4 lines `x y` per camera) or `man_ori_coordinates` (YAML) | per camera the manually identified reference points (`id x y`), the start of the mark identification |
//! | `examine`: `Combine_Flag` | 1: calibrate from `multi_planes`' plane files instead of `cal_ori`'s images, as OpenPTV's multi-plane orientation does; 0 (or no `examine`): from the images (`Examine_Flag` only shows OpenPTV's GUI more) |
//! | `multi_planes`: `n_planes`, `plane_name` | with `Combine_Flag` 1, the planes' identified points (`<plane><cam>.tif.fix`/`.crd`, [`super::multi_planes`]); otherwise listed as not used, saying whether the files are present |
//!
//! pyptv's `orient` flags are "1 = the parameter is adjusted"; every flag
//! 0 (the test_cavity experiment's choice) is an exterior-only resection
//! with the setup's interior orientation and distortion.

use std::path::{Path, PathBuf};

use nalgebra::Point2;
use serde::Deserialize;

use super::multi_planes::{self, PlaneFiles};
use super::{ExperimentError, ExperimentFiles, ParFile, UnmappedSetting};
use crate::photogrammetry::calibrate::{ControlPoint, MarkObservation, Parameter};
use crate::photogrammetry::DetectionParameters;

/// Manually identified points per camera in OpenPTV's `man_ori`.
pub const MANUAL_POINTS: usize = 4;

/// An experiment's calibration settings.
#[derive(Clone, Debug)]
pub struct CalibrationSettings {
    /// The control points' file (`cal_ori.fixp_name`), resolved.
    pub control: PathBuf,
    /// Per camera its calibration image (`cal_ori.img_cal_name`), resolved.
    pub images: Vec<PathBuf>,
    /// Per camera the detection of the plate's marks (`detect_plate`).
    pub detection: Vec<DetectionParameters>,
    /// The parameters held at the setup's values (`orient` flags 0).
    pub fixed: Vec<Parameter>,
    /// Per camera the manual orientation points: `man_ori.nr` ids with
    /// their image positions (px), not yet checked against the control
    /// points ([`CalibrationSettings::references`] does).
    pub manual: Vec<Vec<(u64, Point2<f64>)>>,
    /// OpenPTV's multi-plane calibration (`examine.Combine_Flag` 1): the
    /// planes' files, to calibrate from instead of `images`; empty
    /// otherwise.
    pub planes: Vec<PlaneFiles>,
    /// The file that names the planes (for errors).
    pub planes_source: PathBuf,
    /// Settings read but not used, and why.
    pub unmapped: Vec<UnmappedSetting>,
    /// Where the manual points' ids come from (for errors).
    manual_source: String,
}

impl CalibrationSettings {
    /// The planes of OpenPTV's multi-plane calibration, read through
    /// `files` ([`multi_planes::read_planes`]); empty unless
    /// `examine.Combine_Flag` is 1.
    pub fn read_planes(
        &self,
        files: &dyn ExperimentFiles,
    ) -> Result<Vec<crate::photogrammetry::calibrate::Plane>, ExperimentError> {
        multi_planes::read_planes(files, &self.planes_source, &self.planes)
    }

    /// The manual orientation points as reference observations, each id
    /// checked against `control`: an id the target does not have is an
    /// error naming the camera and the file.
    pub fn references(
        &self,
        control: &[ControlPoint],
    ) -> Result<Vec<Vec<MarkObservation>>, ExperimentError> {
        self.manual
            .iter()
            .enumerate()
            .map(|(camera, points)| {
                points
                    .iter()
                    .map(|(id, pixel)| {
                        if control.iter().any(|p| p.id == *id) {
                            Ok(MarkObservation {
                                id: *id,
                                pixel: *pixel,
                            })
                        } else {
                            Err(ExperimentError::Invalid {
                                file: PathBuf::from(&self.manual_source),
                                location: format!("man_ori.nr, camera {}", camera + 1),
                                reason: format!(
                                    "names point {id}, which the calibration target ({}) does \
                                     not have; give the numbers of {MANUAL_POINTS} of the \
                                     target's points (its first column) that the camera sees",
                                    self.control.display()
                                ),
                            })
                        }
                    })
                    .collect()
            })
            .collect()
    }
}

/// The `orient` flags in OpenPTV's order, with the parameters they free.
const ORIENT_FLAGS: [(&str, Parameter); 10] = [
    ("cc", Parameter::C),
    ("xh", Parameter::Xh),
    ("yh", Parameter::Yh),
    ("k1", Parameter::K1),
    ("k2", Parameter::K2),
    ("k3", Parameter::K3),
    ("p1", Parameter::P1),
    ("p2", Parameter::P2),
    ("scale", Parameter::Scx),
    ("shear", Parameter::She),
];

/// `detect_plate` as pyptv's YAML names it.
#[derive(Debug, Deserialize)]
struct DetectPlate {
    gvth_1: i64,
    gvth_2: i64,
    gvth_3: i64,
    gvth_4: i64,
    tol_dis: i64,
    min_npix: i64,
    max_npix: i64,
    min_npix_x: i64,
    max_npix_x: i64,
    min_npix_y: i64,
    max_npix_y: i64,
    sum_grey: i64,
}

#[derive(Debug, Deserialize)]
struct CalOri {
    fixp_name: String,
    img_cal_name: Vec<String>,
}

#[derive(Debug, Deserialize)]
struct ManOri {
    nr: Vec<i64>,
}

#[derive(Debug, Deserialize)]
struct ManualPoint {
    x: f64,
    y: f64,
}

#[derive(Debug, Deserialize)]
struct YamlSections {
    cal_ori: CalOri,
    detect_plate: DetectPlate,
    orient: std::collections::BTreeMap<String, i64>,
    man_ori: ManOri,
    #[serde(default)]
    man_ori_coordinates:
        std::collections::BTreeMap<String, std::collections::BTreeMap<String, ManualPoint>>,
    #[serde(default)]
    multi_planes: Option<MultiPlanes>,
    #[serde(default)]
    examine: Option<Examine>,
}

/// pyptv's `multi_planes` section.
#[derive(Debug, Deserialize)]
struct MultiPlanes {
    n_planes: i64,
    #[serde(default)]
    plane_name: Vec<String>,
}

/// pyptv's `examine` section: its flags are booleans (or 0/1).
#[derive(Debug, Deserialize)]
struct Examine {
    #[serde(rename = "Combine_Flag", default)]
    combine_flag: Option<serde_norway::Value>,
}

/// Reads the calibration settings of the experiment at `dir` (as
/// [`super::read_experiment`] takes it) for `cameras` cameras.
pub fn read_calibration_settings(
    files: &dyn ExperimentFiles,
    dir: &Path,
    cameras: usize,
) -> Result<CalibrationSettings, ExperimentError> {
    if files.is_dir(dir) && files.is_file(&dir.join("parameters").join("ptv.par")) {
        return read_legacy(files, dir, cameras);
    }
    let yaml = if files.is_file(dir) {
        dir.to_owned()
    } else {
        files
            .list(dir)
            .into_iter()
            .filter(|n| {
                n.starts_with("parameters") && (n.ends_with(".yaml") || n.ends_with(".yml"))
            })
            .map(|n| dir.join(n))
            .find(|p| files.is_file(p))
            .ok_or_else(|| ExperimentError::NotAnExperiment {
                dir: dir.to_owned(),
                reason: "has neither parameters/ptv.par nor a parameters_*.yaml".into(),
            })?
    };
    let root = if files.is_file(dir) {
        dir.parent().unwrap_or(Path::new(".")).to_owned()
    } else {
        dir.to_owned()
    };
    read_yaml(files, &yaml, &root, cameras)
}

fn count_error(file: &Path, key: &str, reason: String) -> ExperimentError {
    ExperimentError::Invalid {
        file: file.to_owned(),
        location: key.to_owned(),
        reason,
    }
}

fn resolve(
    files: &dyn ExperimentFiles,
    file: &Path,
    root: &Path,
    key: &str,
    name: &str,
) -> Result<PathBuf, ExperimentError> {
    files
        .resolve(root, name.trim())
        .map_err(|reason| ExperimentError::Refused {
            file: file.to_owned(),
            location: key.to_owned(),
            name: name.to_owned(),
            reason,
        })
}

/// One camera's `detect_plate` detection: liboptv's target recognition
/// with the plate's thresholds; a mark's extent bounded as OpenPTV bounds
/// it.
fn plate_detection(
    threshold: i64,
    d: &DetectPlate,
    file: &Path,
) -> Result<DetectionParameters, ExperimentError> {
    let value = |key: &str, v: i64| {
        u32::try_from(v).map_err(|_| {
            count_error(
                file,
                &format!("detect_plate.{key}"),
                format!("{v} is not a count of pixels or grey levels (0 or more)"),
            )
        })
    };
    let defaults = DetectionParameters::default();
    let parameters = DetectionParameters {
        threshold: u16::try_from(threshold).map_err(|_| {
            count_error(
                file,
                "detect_plate.gvth",
                format!("{threshold} is not a grey level (0..65535)"),
            )
        })?,
        min_pixels: value("min_npix", d.min_npix)?,
        max_pixels: value("max_npix", d.max_npix)?,
        min_nx: value("min_npix_x", d.min_npix_x)?,
        max_nx: value("max_npix_x", d.max_npix_x)?,
        min_ny: value("min_npix_y", d.min_npix_y)?,
        max_ny: value("max_npix_y", d.max_npix_y)?,
        min_sumg: u64::from(value("sum_grey", d.sum_grey)?),
        split_depth: Some(u16::try_from(d.tol_dis.clamp(0, i64::from(u16::MAX))).unwrap_or(0)),
        // OpenPTV has no noise-relative test; its sum of grey is the bound.
        min_snr: 0,
        ..defaults
    };
    parameters
        .validate()
        .map_err(|e| count_error(file, "detect_plate", e.to_string()))?;
    Ok(parameters)
}

fn fixed_from_flags(
    flags: impl Fn(&str) -> Result<i64, ExperimentError>,
) -> Result<Vec<Parameter>, ExperimentError> {
    let mut fixed = Vec::new();
    for (key, parameter) in ORIENT_FLAGS {
        if flags(key)? == 0 {
            fixed.push(parameter);
        }
    }
    Ok(fixed)
}

fn manual_ids(nr: &[i64], cameras: usize, file: &Path) -> Result<Vec<Vec<u64>>, ExperimentError> {
    if nr.len() < MANUAL_POINTS * cameras {
        return Err(count_error(
            file,
            "man_ori.nr",
            format!(
                "{} point numbers given, {MANUAL_POINTS} per camera are needed for {cameras} \
                 cameras",
                nr.len()
            ),
        ));
    }
    nr.chunks(MANUAL_POINTS)
        .take(cameras)
        .enumerate()
        .map(|(camera, ids)| {
            ids.iter()
                .map(|&id| {
                    u64::try_from(id).map_err(|_| {
                        count_error(
                            file,
                            &format!("man_ori.nr, camera {}", camera + 1),
                            format!("{id} is not a point number"),
                        )
                    })
                })
                .collect()
        })
        .collect()
}

/// Where each key of the `.par` files was read (for errors found later).
type Places = std::collections::BTreeMap<String, (PathBuf, usize)>;

/// Each camera's manually identified points: number and pixel position.
type ManualPoints = Vec<Vec<(u64, Point2<f64>)>>;

fn read_legacy(
    files: &dyn ExperimentFiles,
    dir: &Path,
    cameras: usize,
) -> Result<CalibrationSettings, ExperimentError> {
    let mut places = Places::new();
    let (control, images) = legacy_cal_ori(files, dir, cameras, &mut places)?;
    let detection = legacy_detect_plate(files, dir, cameras, &mut places)?;
    let (fixed, pnfo) = legacy_orient(files, dir, &mut places)?;
    let (manual, man_ori) = legacy_man_ori(files, dir, cameras, &mut places)?;
    let mut unmapped = vec![pnfo];
    let (planes, planes_source) = legacy_planes(files, dir, cameras, &mut places, &mut unmapped)?;
    Ok(CalibrationSettings {
        control,
        images,
        detection,
        fixed,
        manual,
        planes,
        planes_source,
        unmapped,
        manual_source: man_ori.display().to_string(),
    })
}

/// `cal_ori.par`: the control points' file and each camera's calibration
/// image, resolved.
fn legacy_cal_ori(
    files: &dyn ExperimentFiles,
    dir: &Path,
    cameras: usize,
    places: &mut Places,
) -> Result<(PathBuf, Vec<PathBuf>), ExperimentError> {
    let mut f = ParFile::open(files, dir, "cal_ori.par", "cal_ori", places)?;
    let fixp = f.text("fixp_name")?;
    let mut names = Vec::new();
    for i in 0..cameras {
        names.push(f.text(&format!("img_cal_name[{i}]"))?);
        f.text(&format!("img_ori[{i}]"))?;
    }
    let cal_ori = f.path.clone();
    let control = resolve(files, &cal_ori, dir, "cal_ori.fixp_name", &fixp)?;
    let images = names
        .iter()
        .enumerate()
        .map(|(i, n)| {
            resolve(
                files,
                &cal_ori,
                dir,
                &format!("cal_ori.img_cal_name[{i}]"),
                n,
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((control, images))
}

/// `detect_plate.par`: the marks' detection per camera.
fn legacy_detect_plate(
    files: &dyn ExperimentFiles,
    dir: &Path,
    cameras: usize,
    places: &mut Places,
) -> Result<Vec<DetectionParameters>, ExperimentError> {
    let mut f = ParFile::open(files, dir, "detect_plate.par", "detect_plate", places)?;
    let mut gvth = Vec::new();
    for i in 1..=4 {
        gvth.push(f.integer(&format!("gvth_{i}"))?);
    }
    let mut d = DetectPlate {
        gvth_1: gvth[0],
        gvth_2: gvth[1],
        gvth_3: gvth[2],
        gvth_4: gvth[3],
        tol_dis: 0,
        min_npix: 0,
        max_npix: 0,
        min_npix_x: 0,
        max_npix_x: 0,
        min_npix_y: 0,
        max_npix_y: 0,
        sum_grey: 0,
    };
    d.tol_dis = f.integer("tol_dis")?;
    d.min_npix = f.integer("min_npix")?;
    d.max_npix = f.integer("max_npix")?;
    d.min_npix_x = f.integer("min_npix_x")?;
    d.max_npix_x = f.integer("max_npix_x")?;
    d.min_npix_y = f.integer("min_npix_y")?;
    d.max_npix_y = f.integer("max_npix_y")?;
    d.sum_grey = f.integer("sum_grey")?;
    let detect_file = f.path.clone();
    thresholds(&d, cameras)
        .into_iter()
        .map(|t| plate_detection(t, &d, &detect_file))
        .collect()
}

/// `orient.par`: the parameters held, and its `pnfo` as an unmapped
/// setting.
fn legacy_orient(
    files: &dyn ExperimentFiles,
    dir: &Path,
    places: &mut Places,
) -> Result<(Vec<Parameter>, UnmappedSetting), ExperimentError> {
    let mut f = ParFile::open(files, dir, "orient.par", "orient", places)?;
    let pnfo = f.integer("pnfo")?;
    let mut flags = std::collections::BTreeMap::new();
    for (key, _) in ORIENT_FLAGS {
        flags.insert(key, f.integer(key)?);
    }
    let orient_file = f.path.clone();
    let fixed = fixed_from_flags(|key| Ok(flags[key]))?;
    let pnfo = UnmappedSetting {
        file: orient_file.display().to_string(),
        key: "orient.pnfo".into(),
        value: pnfo.to_string(),
        reason: "OpenPTV's choice of points for the orientation; ptv uses every identified mark \
                 and excludes gross errors by data snooping"
            .into(),
    };
    Ok((fixed, pnfo))
}

/// `man_ori.par` and `man_ori.dat`: each camera's manually identified
/// points (number and pixel position), and the `.par`'s path.
fn legacy_man_ori(
    files: &dyn ExperimentFiles,
    dir: &Path,
    cameras: usize,
    places: &mut Places,
) -> Result<(ManualPoints, PathBuf), ExperimentError> {
    let mut f = ParFile::open(files, dir, "man_ori.par", "man_ori", places)?;
    let mut nr = Vec::new();
    for i in 0..MANUAL_POINTS * cameras {
        nr.push(f.integer(&format!("nr[{i}]"))?);
    }
    let man_ori = f.path.clone();
    let ids = manual_ids(&nr, cameras, &man_ori)?;
    // man_ori.dat: `x y` per line, 4 lines per camera, beside the .par.
    let dat = dir.join("parameters").join("man_ori.dat");
    let coordinates = manual_coordinates(&files.read_text(&dat)?, &dat)?;
    if coordinates.len() < MANUAL_POINTS * cameras {
        return Err(count_error(
            &dat,
            "the whole file",
            format!(
                "{} points given; man_ori.par names {MANUAL_POINTS} per camera, {} for {cameras} \
                 cameras",
                coordinates.len(),
                MANUAL_POINTS * cameras
            ),
        ));
    }
    let manual = ids
        .iter()
        .zip(coordinates.chunks(MANUAL_POINTS))
        .map(|(ids, xy)| ids.iter().copied().zip(xy.iter().copied()).collect())
        .collect();
    Ok((manual, man_ori))
}

/// The points of `man_ori.dat` (`x y` per line, pixels).
fn manual_coordinates(text: &str, dat: &Path) -> Result<Vec<Point2<f64>>, ExperimentError> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(n, l)| {
            let v: Vec<f64> = l
                .split_whitespace()
                .map(str::parse)
                .collect::<Result<_, _>>()
                .map_err(|_| {
                    count_error(dat, &format!("line {}", n + 1), "not `x y` (pixels)".into())
                })?;
            match v.as_slice() {
                [x, y] if x.is_finite() && y.is_finite() => Ok(Point2::new(*x, *y)),
                _ => Err(count_error(
                    dat,
                    &format!("line {}", n + 1),
                    "not `x y` (two finite numbers, pixels)".into(),
                )),
            }
        })
        .collect()
}

/// `examine.par` and `multi_planes.par`: the planes of a multi-plane
/// calibration where OpenPTV would combine them, and the `.par`'s path.
fn legacy_planes(
    files: &dyn ExperimentFiles,
    dir: &Path,
    cameras: usize,
    places: &mut Places,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<(Vec<PlaneFiles>, PathBuf), ExperimentError> {
    let planes_source = dir.join("parameters").join("multi_planes.par");
    let examine = dir.join("parameters").join("examine.par");
    let combine = if files.is_file(&examine) {
        let mut f = ParFile::open(files, dir, "examine.par", "examine", places)?;
        f.integer("Examine_Flag")?;
        f.integer("Combine_Flag")? != 0
    } else {
        false
    };
    let names = if files.is_file(&planes_source) {
        let mut f = ParFile::open(files, dir, "multi_planes.par", "multi_planes", places)?;
        let n = f.integer("n_planes")?;
        let n = plane_count(n, &planes_source)?;
        let mut names = Vec::with_capacity(n);
        for i in 0..n {
            names.push(f.text(&format!("plane_name[{i}]"))?);
        }
        Some(names)
    } else {
        None
    };
    let planes = use_planes(
        files,
        combine,
        names,
        (&examine, &planes_source),
        dir,
        cameras,
        unmapped,
    )?;
    Ok((planes, planes_source))
}

/// The most planes `multi_planes` may name (liboptv reads at most 10).
const MAX_PLANES: usize = 100;

fn plane_count(n: i64, file: &Path) -> Result<usize, ExperimentError> {
    usize::try_from(n)
        .ok()
        .filter(|n| (1..=MAX_PLANES).contains(n))
        .ok_or_else(|| {
            count_error(
                file,
                "multi_planes.n_planes",
                format!("{n} planes; give 1 to {MAX_PLANES}, one plane_name each"),
            )
        })
}

/// The planes' files if `combine` (examine.Combine_Flag) asks for them
/// (an error if `names`, multi_planes' plane names, are missing); else
/// multi_planes listed as not used, saying whether its files are there.
/// The two paths are examine's and multi_planes' files (for errors).
fn use_planes(
    files: &dyn ExperimentFiles,
    combine: bool,
    names: Option<Vec<String>>,
    (examine, planes_source): (&Path, &Path),
    root: &Path,
    cameras: usize,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<Vec<PlaneFiles>, ExperimentError> {
    match (combine, names) {
        (true, Some(names)) => {
            multi_planes::plane_files(files, planes_source, root, &names, cameras)
        }
        (true, None) => Err(count_error(
            examine,
            "examine.Combine_Flag",
            format!(
                "1 (calibrate from several planes), but there is no multi_planes setting ({}); \
                 name the planes there, or set Combine_Flag to 0 to calibrate from cal_ori's \
                 images",
                planes_source.display()
            ),
        )),
        (false, Some(names)) => {
            let planes = multi_planes::plane_files(files, planes_source, root, &names, 1);
            let present = planes
                .as_ref()
                .map(|p| p.iter().filter(|p| files.is_file(&p.cameras[0].0)).count())
                .unwrap_or(0);
            unmapped.push(UnmappedSetting {
                file: planes_source.display().to_string(),
                key: "multi_planes".into(),
                value: format!("{} planes: {}", names.len(), names.join(" ")),
                reason: format!(
                    "examine.Combine_Flag is 0, so ptv calibrates from cal_ori's image per \
                     camera, as OpenPTV does; with Combine_Flag 1 it calibrates from the \
                     planes' identified points (<plane><camera>.tif.fix and .crd; {present} of \
                     the {} planes' files for camera 1 are present here). From images of the \
                     plate at several positions: `ptv calibrate --plane \
                     CONTROL:IMAGE1,IMAGE2,...` once per position",
                    names.len()
                ),
            });
            Ok(Vec::new())
        }
        (false, None) => Ok(Vec::new()),
    }
}

/// The thresholds per camera: `gvth_1..4`, the last repeated past four.
fn thresholds(d: &DetectPlate, cameras: usize) -> Vec<i64> {
    let all = [d.gvth_1, d.gvth_2, d.gvth_3, d.gvth_4];
    (0..cameras).map(|k| all[k.min(3)]).collect()
}

fn read_yaml(
    files: &dyn ExperimentFiles,
    path: &Path,
    root: &Path,
    cameras: usize,
) -> Result<CalibrationSettings, ExperimentError> {
    // The caller read the experiment first (`read_experiment`), which
    // checks the YAML's size, flow and depth limits before any parse.
    let text = files.read_text(path)?;
    let s: YamlSections = serde_norway::from_str(&text).map_err(|e| ExperimentError::Invalid {
        file: path.to_owned(),
        location: e.location().map_or_else(
            || "the whole file".to_owned(),
            |l| format!("line {}", l.line()),
        ),
        reason: format!("{e} (the calibration sections cal_ori, detect_plate, orient, man_ori)"),
    })?;
    if s.cal_ori.img_cal_name.len() < cameras {
        return Err(count_error(
            path,
            "cal_ori.img_cal_name",
            format!(
                "{} calibration images named for {cameras} cameras",
                s.cal_ori.img_cal_name.len()
            ),
        ));
    }
    let control = resolve(files, path, root, "cal_ori.fixp_name", &s.cal_ori.fixp_name)?;
    let images = s.cal_ori.img_cal_name[..cameras]
        .iter()
        .enumerate()
        .map(|(i, n)| resolve(files, path, root, &format!("cal_ori.img_cal_name[{i}]"), n))
        .collect::<Result<Vec<_>, _>>()?;
    let detection = thresholds(&s.detect_plate, cameras)
        .into_iter()
        .map(|t| plate_detection(t, &s.detect_plate, path))
        .collect::<Result<Vec<_>, _>>()?;
    let fixed = fixed_from_flags(|key| {
        s.orient.get(key).copied().ok_or_else(|| {
            count_error(
                path,
                &format!("orient.{key}"),
                "missing; give 0 (fixed) or 1 (adjusted)".into(),
            )
        })
    })?;
    let ids = manual_ids(&s.man_ori.nr, cameras, path)?;
    let mut manual = Vec::with_capacity(cameras);
    for (camera, ids) in ids.iter().enumerate() {
        let points = s
            .man_ori_coordinates
            .get(&format!("camera_{camera}"))
            .ok_or_else(|| {
                count_error(
                    path,
                    &format!("man_ori_coordinates.camera_{camera}"),
                    "missing: the manual points' image positions (point_1..point_4: x, y)".into(),
                )
            })?;
        let mut list = Vec::with_capacity(MANUAL_POINTS);
        for (k, id) in ids.iter().enumerate() {
            let key = format!("point_{}", k + 1);
            let p = points.get(&key).ok_or_else(|| {
                count_error(
                    path,
                    &format!("man_ori_coordinates.camera_{camera}.{key}"),
                    "missing".into(),
                )
            })?;
            if !(p.x.is_finite() && p.y.is_finite()) {
                return Err(count_error(
                    path,
                    &format!("man_ori_coordinates.camera_{camera}.{key}"),
                    "not finite numbers".into(),
                ));
            }
            list.push((*id, Point2::new(p.x, p.y)));
        }
        manual.push(list);
    }
    let mut unmapped = Vec::new();
    if let Some(value) = s.orient.get("pnfo") {
        unmapped.push(UnmappedSetting {
            file: path.display().to_string(),
            key: "orient.pnfo".into(),
            value: value.to_string(),
            reason: "OpenPTV's choice of points for the orientation; ptv uses every identified \
                     mark and excludes gross errors by data snooping"
                .into(),
        });
    }
    let combine = match s.examine.as_ref().and_then(|e| e.combine_flag.as_ref()) {
        None => false,
        Some(serde_norway::Value::Bool(b)) => *b,
        Some(v) => match v.as_i64() {
            Some(0) => false,
            Some(1) => true,
            _ => {
                return Err(count_error(
                    path,
                    "examine.Combine_Flag",
                    "not a flag; give true/false (or 1/0)".into(),
                ))
            }
        },
    };
    let names = match &s.multi_planes {
        Some(planes) => {
            let n = plane_count(planes.n_planes, path)?;
            if planes.plane_name.len() < n {
                return Err(count_error(
                    path,
                    "multi_planes.plane_name",
                    format!(
                        "{} names for n_planes {n}; give one per plane",
                        planes.plane_name.len()
                    ),
                ));
            }
            Some(planes.plane_name[..n].to_vec())
        }
        None => None,
    };
    let planes = use_planes(
        files,
        combine,
        names,
        (path, path),
        root,
        cameras,
        &mut unmapped,
    )?;
    Ok(CalibrationSettings {
        control,
        images,
        detection,
        fixed,
        manual,
        planes,
        planes_source: path.to_owned(),
        unmapped,
        manual_source: path.display().to_string(),
    })
}
