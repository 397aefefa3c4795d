//! OpenPTV/pyptv experiments: the legacy `parameters/` folder of `.par`
//! files or pyptv's `parameters_*.yaml`, with the calibration files they
//! name, read into `ptv`'s own settings ([`Experiment`]).
//!
//! [`read_experiment`] takes a directory or a YAML file:
//!
//! - a YAML file (`parameters_Run1.yaml`): pyptv's sections `num_cams`,
//!   `ptv`, `cal_ori`, `criteria`, `targ_rec`, `sequence`, `masking`, ...;
//!   paths in it are relative to the YAML's directory;
//! - a directory with `parameters/ptv.par`: the legacy folder (`ptv.par`,
//!   `cal_ori.par`, `targ_rec.par`, `criteria.par`, `sequence.par`, ...,
//!   one value per line as liboptv's `parameters.c` reads them, through
//!   [`openptv`]'s one reader of `ptv.par` and its line reader for the
//!   others); paths are relative to the directory;
//! - a directory with exactly one `parameters_*.yaml` and no `parameters/`:
//!   that YAML. With several, the error lists them: give the file's path.
//! - a directory with both forms: the one that describes the experiment
//!   ([`choose_form`]). A `sequence.par` naming `--` for a camera is
//!   pyptv's splitter (its cameras are views of the first camera's image),
//!   which only the YAML says (`ptv.splitter`): the YAML. Otherwise the form
//!   whose files (calibration, first frame's images) are all there; where
//!   both are and they give the same settings, the `.par` folder; where
//!   they differ, an error naming both files and the first difference.
//! - the `parameters/` folder itself: the legacy form of its parent.
//!
//! Every file is opened through an [`ExperimentFiles`] the caller picks
//! ([`read_experiment_from`]): the command line's [`LocalFiles`] follow the
//! user's own paths; the service's [`UploadedFiles`] resolve a name only to
//! a file uploaded with it, and refuse absolute names and `..`
//! ([`ExperimentError::Refused`]). Parameter files are read up to
//! [`files::MAX_TEXT_BYTES`]; a YAML may hold [`MAX_YAML_FLOW`] `[`/`{`
//! and nest [`MAX_YAML_DEPTH`] levels with at most [`MAX_YAML_ITEMS`]
//! items (an alias counted at each use), for both.
//!
//! Both forms are first read into one set of sections named as pyptv's YAML
//! names them, then mapped, so the two give the same settings. The mapping
//! (design paper, sections 6.1 and 6.2):
//!
//! | OpenPTV | ptv |
//! | --- | --- |
//! | `ptv.par`: sensor, pixel size, n1/n2/n3, wall thickness; `cal_ori`'s `.ori` and `.addpar` | [`Camera`]s (the calibration JSON) |
//! | `hp_flag` | `highpass_radius` 25 (liboptv's `preprocess_image` box filter of half-width 25, pyptv's default) or 0 |
//! | `allcam_flag` | `min_cameras`: every camera, or 2 |
//! | `targ_rec.gvthres` | per camera `threshold` |
//! | `disco` | `split_depth` (absolute grey levels, OpenPTV's meaning), `split` on |
//! | `nnmin`/`nnmax`, `nxmin`/`nxmax`, `nymin`/`nymax` | `min_pixels`/`max_pixels`, `min_nx`/`max_nx`, `min_ny`/`max_ny` (inclusive in both) |
//! | `sumg_min` | `min_sumg` = `sumg_min + 1`: liboptv's `targ_rec` keeps a target whose sum of grey is strictly above `sumg_min`, ours at or above `min_sumg` (integer sums) |
//! | (none) | `min_snr` 0: OpenPTV has no noise-relative significance test |
//! | `criteria.eps0` (mm on the image plane) | `tolerance` (px): eps0 divided by the mean pixel size |
//! | `X_lay`, `Zmin_lay`, `Zmax_lay` | the observation [`Volume`], see below |
//! | `sequence.base_name`, `first`, `last` | [`SequenceFrames`] |
//! | `ptv.splitter` (pyptv) | [`Splitter::quadrants`] |
//! | `masking.mask_base_name` (pyptv, `%d` = camera 1..N) | `masks`: images pyptv subtracts from every frame (clipped at 0), and so does `ptv process-sequence` |
//! | `track.par`'s `dvxmin..dvzmax` (mm per frame, the search box per axis) | tracking's `max_velocity`: the radius of the sphere around the box, so every link OpenPTV can make ptv can make ([`map_tracking`]) |
//! | `track.dacc` (mm per frame²) | `max_acceleration`, the same bound |
//! | `track.flagNewParticles` | the image-space recovery (OpenPTV adds particles found in the images near a prediction; so does `ptv track` with targets) |
//! | `track.angle` (gon) | none: ptv ranks links by the change of acceleration (Malik et al. 1993) within `max_acceleration`, and has no angle limit |
//! | (none) | `max_gap` 1, `min_length` 3, the 5-point quadratic fit: `ptv`'s defaults. OpenPTV links adjacent frames only and keeps every trajectory; `ptv` bridges one missed frame and reports trajectories of 3 points or more |
//!
//! **The volume.** OpenPTV bounds depth only: between `X_lay[0]` and
//! `X_lay[1]` the range `Zmin..Zmax` is interpolated linearly in X, and Y is
//! not bounded at all (only by what the cameras see). `ptv`'s volume is a
//! box, so: X is `X_lay[0]..X_lay[1]`; Z is the smallest `Zmin_lay` to the
//! largest `Zmax_lay`, the box around a sloped range, which keeps every
//! point OpenPTV keeps and some more near the shallow end; Y is the union
//! over the cameras of where their image corners' rays meet the depth range,
//! that is every Y some camera can see.
//!
//! Everything else (`cnx`, `cny`, `cn`, `csumg`, `corrmin`, `cr_sz`,
//! `track`, calibration-only sections, ...) is listed in
//! [`Experiment::unmapped`] with the reason. Errors name the file, the line
//! and the key.
//!
//! The folder: `yaml` reads pyptv's YAML and `legacy` the `.par` folder
//! into the sections (here), `map` maps them; `files` opens what they name,
//! `calibration_settings` and `multi_planes` read the calibration's own
//! settings and target files.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Point2, Point3, Vector3};
use serde::Deserialize;

use super::frames::{FramePattern, WithoutNumber};
use super::{calibration, openptv, FormatError};

pub mod calibration_settings;
pub mod files;
pub mod multi_planes;
use crate::photogrammetry::correspond::MatchingParameters;
use crate::photogrammetry::track::TrackingParameters;
use crate::photogrammetry::{
    Camera, CameraParameters, Centroid, DetectionParameters, Distortion, Media, Sensor, Splitter,
    Volume, Wall,
};
pub use calibration_settings::{read_calibration_settings, CalibrationSettings};
pub use files::{ExperimentFiles, LocalFiles, Refused, UploadedFiles};

/// The high-pass radius `hp_flag` stands for: liboptv's
/// `preprocess_image(img, 0, cpar, 25)` as pyptv calls it subtracts a box
/// average of half-width 25 px.
pub const OPENPTV_HIGHPASS_RADIUS: u32 = 25;

/// An OpenPTV experiment in `ptv`'s terms.
#[derive(Clone, Debug)]
pub struct Experiment {
    /// The experiment directory: image and calibration paths are relative
    /// to it.
    pub root: PathBuf,
    /// From `ptv.par` and `cal_ori`'s `.ori`/`.addpar`.
    pub cameras: Vec<Camera>,
    /// pyptv's splitter: the cameras are the quadrants of one image.
    pub splitter: Option<Splitter>,
    /// One set per camera (their thresholds differ).
    pub detection: Vec<DetectionParameters>,
    /// The correspondence search.
    pub matching: MatchingParameters,
    /// The image sequence.
    pub sequence: SequenceFrames,
    /// pyptv's masking images, one per camera, if masking is on. pyptv
    /// subtracts them from each frame (clipped at 0), like a background;
    /// they are not "non-zero = use the pixel" masks.
    pub masks: Option<Vec<PathBuf>>,
    /// The tracking settings of `track.par` (pyptv's `track:`), where the
    /// experiment has them.
    pub tracking: Option<ExperimentTracking>,
    /// The settings `ptv` cannot map, and why.
    pub unmapped: Vec<UnmappedSetting>,
}

/// An experiment's tracking, from `track.par` (see the module's table).
#[derive(Clone, Debug, PartialEq)]
pub struct ExperimentTracking {
    /// The limits: `max_velocity` from the `dv*` box, `max_acceleration`
    /// from `dacc`; the rest `ptv`'s defaults ([`TrackingParameters::new`]).
    pub parameters: TrackingParameters,
    /// `flagNewParticles`: look in the images for the particles the
    /// correspondences missed ([`crate::photogrammetry::track::ImageSpaceRecovery`]).
    pub recovery: bool,
}

/// The frames of an experiment.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SequenceFrames {
    /// Per camera (one with a splitter), the image name pattern relative to
    /// the root, with a printf-style `%d` (or `%05d`, ...) for the frame;
    /// without one, the frame is appended after a dot (OpenPTV's naming).
    pub base_names: Vec<FramePattern>,
    /// The first frame.
    pub first: u64,
    /// The last frame (inclusive).
    pub last: u64,
}

impl SequenceFrames {
    /// The image of `camera` (0-based) at `frame`.
    pub fn image_path(&self, root: &Path, camera: usize, frame: u64) -> PathBuf {
        match self.base_names.get(camera).or(self.base_names.last()) {
            Some(pattern) => root.join(pattern.path(frame)),
            None => root.to_owned(),
        }
    }
}

/// A setting read but not used, with the reason.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct UnmappedSetting {
    /// The file it is in.
    pub file: String,
    /// Its key: `criteria.cn`.
    pub key: String,
    /// Its value as written.
    pub value: String,
    /// Why `ptv` does not use it.
    pub reason: String,
}

/// `FILE: KEY = VALUE: REASON`, the line the command line prints for it.
impl std::fmt::Display for UnmappedSetting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {} = {}: {}",
            self.file, self.key, self.value, self.reason
        )
    }
}

/// Why an experiment cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    /// A file that does not parse, or a value out of range.
    #[error("{}: {location}: {reason}", file.display())]
    Invalid {
        /// The parameter file.
        file: PathBuf,
        /// `line 5 (disco)`, `line 12, targ_rec.gvthres[2]`.
        location: String,
        /// What is wrong and what is expected.
        reason: String,
    },
    /// A file the experiment names is not there.
    #[error(
        "{}: {location}: names {}, which does not exist; copy it there or correct the name",
        file.display(), missing.display()
    )]
    Missing {
        /// The parameter file.
        file: PathBuf,
        /// Where it names it.
        location: String,
        /// The missing file.
        missing: PathBuf,
    },
    /// A name written in the experiment's files that may not be followed:
    /// from an uploaded set ([`UploadedFiles`]), an absolute path, one with
    /// `..`, or one that is no plain relative path.
    #[error(
        "{}: {location}: names `{}`, which is {}; an uploaded experiment may name only the \
         files sent with it, by their paths inside the experiment directory (e.g. \
         cal/cam1.tif.ori)",
        file.display(), name.escape_debug(), reason.0
    )]
    Refused {
        /// The parameter file.
        file: PathBuf,
        /// Where it names it.
        location: String,
        /// The name as written.
        name: String,
        /// Why it is refused.
        reason: Refused,
    },
    /// The directory holds no experiment, or several YAMLs.
    #[error("{}: {reason}", dir.display())]
    NotAnExperiment {
        /// The directory given.
        dir: PathBuf,
        /// What was found and what to give.
        reason: String,
    },
    /// A calibration file (`.ori`, `.addpar`) that does not parse, or a
    /// camera the model refuses.
    #[error(transparent)]
    Format(#[from] FormatError),
}

// --- The sections, as pyptv's YAML names them --------------------------------

#[derive(Debug, Deserialize)]
struct Sections {
    num_cams: Option<usize>,
    ptv: PtvSection,
    cal_ori: CalOriSection,
    criteria: CriteriaSection,
    targ_rec: TargRecSection,
    sequence: SequenceSection,
    #[serde(default)]
    masking: Option<MaskingSection>,
    #[serde(default)]
    track: Option<TrackSection>,
}

/// OpenPTV's `track.par` (pyptv's `track:`): the search box of the
/// velocity (mm per frame, per axis), the turning angle (gon), the largest
/// acceleration (mm per frame²) and whether to add particles found in the
/// images.
#[allow(non_snake_case)]
#[derive(Debug, Deserialize)]
struct TrackSection {
    dvxmin: f64,
    dvxmax: f64,
    dvymin: f64,
    dvymax: f64,
    dvzmin: f64,
    dvzmax: f64,
    #[serde(default)]
    #[allow(dead_code)]
    angle: Option<f64>,
    dacc: f64,
    #[serde(default, deserialize_with = "flag")]
    flagNewParticles: bool,
}

/// A flag written `true`/`false` (pyptv's YAML) or `0`/`1` (the `.par`
/// files' way, also seen in hand-written YAMLs).
fn flag<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<bool, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Flag {
        Bool(bool),
        Number(i64),
    }
    Ok(match Flag::deserialize(deserializer)? {
        Flag::Bool(b) => b,
        Flag::Number(n) => n != 0,
    })
}

#[derive(Debug, Deserialize)]
struct PtvSection {
    #[serde(default)]
    n_img: Option<usize>,
    #[serde(default)]
    img_name: Vec<String>,
    hp_flag: bool,
    allcam_flag: bool,
    #[serde(default)]
    tiff_flag: bool,
    imx: u32,
    imy: u32,
    pix_x: f64,
    pix_y: f64,
    #[serde(default)]
    chfield: i64,
    mmp_n1: f64,
    mmp_n2: f64,
    mmp_n3: f64,
    mmp_d: f64,
    #[serde(default)]
    splitter: bool,
}

#[derive(Debug, Deserialize)]
struct CalOriSection {
    img_ori: Vec<String>,
}

#[allow(non_snake_case)]
#[derive(Debug, Deserialize)]
struct CriteriaSection {
    X_lay: Vec<f64>,
    Zmin_lay: Vec<f64>,
    Zmax_lay: Vec<f64>,
    eps0: f64,
}

#[derive(Debug, Deserialize)]
struct TargRecSection {
    gvthres: Vec<i64>,
    disco: i64,
    nnmin: i64,
    nnmax: i64,
    nxmin: i64,
    nxmax: i64,
    nymin: i64,
    nymax: i64,
    sumg_min: i64,
}

#[derive(Debug, Deserialize)]
struct SequenceSection {
    base_name: Vec<String>,
    first: u64,
    last: u64,
}

#[derive(Debug, Deserialize)]
struct MaskingSection {
    #[serde(default)]
    mask_flag: bool,
    #[serde(default)]
    mask_base_name: String,
}

/// Where each `section.key` was read: its file and line.
struct Locator {
    /// Per `section.key` (list items as `section.key[i]` where known).
    places: BTreeMap<String, (PathBuf, usize)>,
    /// The file of a section with no recorded line.
    section_files: BTreeMap<String, PathBuf>,
}

impl Locator {
    fn file_of(&self, key: &str) -> PathBuf {
        let section = key.split('.').next().unwrap_or(key);
        self.places
            .get(key)
            .map(|(file, _)| file.clone())
            .or_else(|| self.section_files.get(section).cloned())
            .unwrap_or_default()
    }

    fn location(&self, key: &str) -> String {
        let base = key.split('[').next().unwrap_or(key);
        match self.places.get(key).or_else(|| self.places.get(base)) {
            Some((_, line)) => format!("line {line}, {key}"),
            None => key.to_owned(),
        }
    }

    fn invalid(&self, key: &str, reason: impl Into<String>) -> ExperimentError {
        ExperimentError::Invalid {
            file: self.file_of(key),
            location: self.location(key),
            reason: reason.into(),
        }
    }
}

/// Reads an experiment: a directory (the legacy `parameters/` folder, or
/// its one `parameters_*.yaml`) or a pyptv YAML file.
pub fn read_experiment(dir: &Path) -> Result<Experiment, ExperimentError> {
    read_experiment_from(&LocalFiles, dir)
}

/// Reads an experiment from `files` (the local file system, or an uploaded
/// set whose root is the empty path): every file the importer opens is
/// opened through it, so names inside the experiment's files resolve only
/// where `files` lets them.
pub fn read_experiment_from(
    files: &dyn ExperimentFiles,
    dir: &Path,
) -> Result<Experiment, ExperimentError> {
    if files.is_file(dir) {
        let root = dir.parent().unwrap_or(Path::new(".")).to_owned();
        return read_yaml(files, dir, &root);
    }
    if !files.is_dir(dir) {
        return Err(ExperimentError::NotAnExperiment {
            dir: dir.to_owned(),
            reason: "no such file or directory; give an OpenPTV experiment directory (with \
                     parameters/ptv.par) or a pyptv parameters_*.yaml"
                .into(),
        });
    }
    // `DIR/parameters` given: the legacy form of DIR.
    if dir.file_name().is_some_and(|n| n == "parameters") && files.is_file(&dir.join("ptv.par")) {
        let parent = dir.parent().unwrap_or(Path::new("")).to_owned();
        return read_legacy(files, &parent);
    }
    let legacy = files.is_file(&dir.join("parameters").join("ptv.par"));
    let yamls: Vec<PathBuf> = files
        .list(dir)
        .into_iter()
        .filter(|n| n.starts_with("parameters") && (n.ends_with(".yaml") || n.ends_with(".yml")))
        .map(|n| dir.join(n))
        .filter(|path| files.is_file(path))
        .collect();
    if legacy {
        return match yamls.as_slice() {
            [] => read_legacy(files, dir),
            [yaml] => choose_form(files, dir, yaml),
            several => {
                if names_splitter_placeholder(files, dir) {
                    Err(ExperimentError::NotAnExperiment {
                        dir: dir.to_owned(),
                        reason: format!(
                            "parameters/sequence.par names `--` for a camera (pyptv's splitter, \
                             which only its YAML describes) and there are several YAMLs ({}); \
                             give the path of the one to use",
                            file_names(several)
                        ),
                    })
                } else {
                    read_legacy(files, dir)
                }
            }
        };
    }
    match yamls.as_slice() {
        [one] => read_yaml(files, one, dir),
        [] => Err(ExperimentError::NotAnExperiment {
            dir: dir.to_owned(),
            reason: "has neither parameters/ptv.par nor a parameters_*.yaml; give an OpenPTV \
                     experiment directory or a pyptv YAML file"
                .into(),
        }),
        several => Err(ExperimentError::NotAnExperiment {
            dir: dir.to_owned(),
            reason: format!(
                "has several pyptv YAMLs ({}); give the path of the one to use",
                file_names(several)
            ),
        }),
    }
}

fn file_names(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Whether the legacy `sequence.par` names `--` for a camera: pyptv's
/// splitter placeholder (cameras 2..N are views of camera 1's image).
fn names_splitter_placeholder(files: &dyn ExperimentFiles, dir: &Path) -> bool {
    files
        .read_text(&dir.join("parameters").join("sequence.par"))
        .is_ok_and(|text| text.lines().any(|line| line.trim() == "--"))
}

/// Whether every file an experiment reads at run time is there: its first
/// frame's images (the calibration files were read already).
fn images_present(files: &dyn ExperimentFiles, experiment: &Experiment) -> bool {
    let views = if experiment.splitter.is_some() {
        1
    } else {
        experiment.cameras.len()
    };
    (0..views).all(|camera| {
        files.is_file(&experiment.sequence.image_path(
            &experiment.root,
            camera,
            experiment.sequence.first,
        ))
    })
}

/// The first setting two readings of an experiment differ in, if any.
fn first_difference(a: &Experiment, b: &Experiment) -> Option<&'static str> {
    let cameras = |e: &Experiment| calibration::to_json_with_splitter(&e.cameras, e.splitter);
    if cameras(a) != cameras(b) {
        return Some("the cameras (ptv.par, cal_ori and the .ori files)");
    }
    if a.sequence != b.sequence {
        return Some("the sequence (sequence.base_name, first, last)");
    }
    if format!("{:?}", a.detection) != format!("{:?}", b.detection) {
        return Some("the detection (targ_rec, ptv.hp_flag)");
    }
    if format!("{:?}", a.matching) != format!("{:?}", b.matching) {
        return Some("the correspondences (criteria, ptv.allcam_flag)");
    }
    if a.tracking != b.tracking {
        return Some("the tracking (track)");
    }
    if a.masks != b.masks {
        return Some("the masking");
    }
    None
}

/// A directory with both the `parameters/` folder and one
/// `parameters_*.yaml`: the form that describes the experiment (see the
/// module's docs), or an error naming both files.
fn choose_form(
    files: &dyn ExperimentFiles,
    dir: &Path,
    yaml: &Path,
) -> Result<Experiment, ExperimentError> {
    let ptv_par = dir.join("parameters").join("ptv.par");
    if names_splitter_placeholder(files, dir) {
        // Only the YAML can say the cameras are views of one image.
        return read_yaml(files, yaml, dir);
    }
    let both = || {
        format!(
            "both {} (the .par folder) and {} (pyptv's YAML)",
            ptv_par.display(),
            yaml.display()
        )
    };
    let give = || {
        format!(
            "give {} for the .par files or {} for the YAML",
            dir.join("parameters").display(),
            yaml.display()
        )
    };
    match (read_legacy(files, dir), read_yaml(files, yaml, dir)) {
        (Ok(legacy), Ok(from_yaml)) => {
            match (
                images_present(files, &legacy),
                images_present(files, &from_yaml),
            ) {
                (true, false) => return Ok(legacy),
                (false, true) => return Ok(from_yaml),
                _ => {}
            }
            match first_difference(&legacy, &from_yaml) {
                None => Ok(legacy),
                Some(what) => Err(ExperimentError::NotAnExperiment {
                    dir: dir.to_owned(),
                    reason: format!("has {} and they differ in {what}; {}", both(), give()),
                }),
            }
        }
        (Ok(legacy), Err(_)) => Ok(legacy),
        (Err(_), Ok(from_yaml)) => Ok(from_yaml),
        (Err(legacy), Err(_)) => Err(legacy),
    }
}

mod legacy;
mod map;
mod yaml;

use self::legacy::*;
use self::map::*;
use self::yaml::*;
pub use self::yaml::{MAX_YAML_DEPTH, MAX_YAML_FLOW, MAX_YAML_ITEMS};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_lines_are_found_inside_their_section() {
        let text = "ptv:\n  imx: 1\ntarg_rec:\n  disco: 100\n  nnmin: 4\nsequence:\n  first: 1\n";
        let lines = YamlLines::new(text);
        assert_eq!(lines.line("targ_rec", "nnmin"), Some(5));
        assert_eq!(lines.line("targ_rec", ""), Some(3));
        assert_eq!(lines.line("ptv", "nnmin"), None);
    }
}
