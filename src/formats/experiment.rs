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

// --- pyptv's YAML ---------------------------------------------------------

/// The most `[` and `{` a pyptv YAML may hold: 256. The YAML parser
/// (libyaml) scans every token against each flow collection open around it,
/// so flow nesting costs quadratic time before any depth check can run (a
/// 200 KB `[[[[...` took 20 s); counting the characters, in the text as
/// written, bounds that whatever the nesting. pyptv writes its lists as
/// `- item` lines (no brackets); a hand-written `[a, b]` per list of its
/// some 30 lists stays far below.
pub const MAX_YAML_FLOW: usize = 256;

/// The deepest nesting a pyptv YAML may have: 16 levels (sections are the
/// first, their keys' mappings or lists the second and third; pyptv's YAML
/// nests 3 deep).
pub const MAX_YAML_DEPTH: usize = 16;

/// Refuses a YAML text with more than [`MAX_YAML_FLOW`] flow brackets,
/// before it is parsed. Every `[` and `{` counts (inside strings too: an
/// over-count can only refuse, never let a nesting through), except on
/// comment lines, which the parser skips whatever they hold.
fn check_yaml_flow(text: &str, path: &Path) -> Result<(), ExperimentError> {
    let mut count = 0;
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with('#') {
            continue;
        }
        count += line.bytes().filter(|&b| b == b'[' || b == b'{').count();
        if count > MAX_YAML_FLOW {
            return Err(ExperimentError::Invalid {
                file: path.to_owned(),
                location: format!("line {}", i + 1),
                reason: format!(
                    "more than {MAX_YAML_FLOW} `[` and `{{` (flow lists and mappings), the most a \
                     pyptv YAML may have; write lists as `- item` lines, as pyptv does"
                ),
            });
        }
    }
    Ok(())
}

/// The most items (scalars, lists and mappings) a pyptv YAML may have,
/// an alias counted each time it is used: 32,768. pyptv's has about 400;
/// 64 KiB of text without aliases hold at most about 32k (`1,` each), so
/// this bounds what aliases may expand to (15 KB of `&a [1,1,...]` and
/// `[*a,*a,...]` made 640 MiB and 4 s of values) at what the largest plain
/// YAML costs.
pub const MAX_YAML_ITEMS: usize = 32_768;

/// Walks a YAML document as its parsers will (aliases expanded), building
/// nothing, and stops as soon as it has more than [`MAX_YAML_ITEMS`] items
/// or nests deeper than [`MAX_YAML_DEPTH`].
#[derive(Clone, Copy)]
struct YamlBudget<'a> {
    items: &'a std::cell::Cell<usize>,
    depth: usize,
}

/// The start of [`YamlBudget`]'s refusals (the YAML library appends the
/// position).
const YAML_LIMIT: &str = "beyond the limits of a pyptv YAML: ";

impl YamlBudget<'_> {
    fn item<E: serde::de::Error>(self) -> Result<(), E> {
        self.items.set(self.items.get() + 1);
        if self.items.get() > MAX_YAML_ITEMS {
            return Err(E::custom(format!(
                "{YAML_LIMIT}more than {MAX_YAML_ITEMS} items (values, lists and mappings, an \
                 alias counted each time it is used; pyptv's YAML has some 400)"
            )));
        }
        Ok(())
    }

    fn inner<E: serde::de::Error>(self) -> Result<Self, E> {
        self.item()?;
        if self.depth >= MAX_YAML_DEPTH {
            return Err(E::custom(format!(
                "{YAML_LIMIT}nested more than {MAX_YAML_DEPTH} levels deep (pyptv's nests 3: \
                 section, key, list)"
            )));
        }
        Ok(YamlBudget {
            depth: self.depth + 1,
            ..self
        })
    }
}

impl<'de> serde::de::DeserializeSeed<'de> for YamlBudget<'_> {
    type Value = ();

    fn deserialize<D: serde::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_any(self)
    }
}

impl<'de> serde::de::Visitor<'de> for YamlBudget<'_> {
    type Value = ();

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("any YAML value")
    }

    fn visit_bool<E: serde::de::Error>(self, _: bool) -> Result<(), E> {
        self.item()
    }

    fn visit_i64<E: serde::de::Error>(self, _: i64) -> Result<(), E> {
        self.item()
    }

    fn visit_u64<E: serde::de::Error>(self, _: u64) -> Result<(), E> {
        self.item()
    }

    fn visit_f64<E: serde::de::Error>(self, _: f64) -> Result<(), E> {
        self.item()
    }

    fn visit_i128<E: serde::de::Error>(self, _: i128) -> Result<(), E> {
        self.item()
    }

    fn visit_u128<E: serde::de::Error>(self, _: u128) -> Result<(), E> {
        self.item()
    }

    fn visit_char<E: serde::de::Error>(self, _: char) -> Result<(), E> {
        self.item()
    }

    fn visit_str<E: serde::de::Error>(self, _: &str) -> Result<(), E> {
        self.item()
    }

    fn visit_bytes<E: serde::de::Error>(self, _: &[u8]) -> Result<(), E> {
        self.item()
    }

    fn visit_unit<E: serde::de::Error>(self) -> Result<(), E> {
        self.item()
    }

    fn visit_none<E: serde::de::Error>(self) -> Result<(), E> {
        self.item()
    }

    fn visit_some<D: serde::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_any(self)
    }

    fn visit_newtype_struct<D: serde::Deserializer<'de>>(
        self,
        deserializer: D,
    ) -> Result<(), D::Error> {
        deserializer.deserialize_any(self)
    }

    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        let inner = self.inner()?;
        while seq.next_element_seed(inner)?.is_some() {}
        Ok(())
    }

    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        let inner = self.inner()?;
        while map.next_key_seed(inner)?.is_some() {
            map.next_value_seed(inner)?;
        }
        Ok(())
    }

    fn visit_enum<A: serde::de::EnumAccess<'de>>(self, data: A) -> Result<(), A::Error> {
        // A tagged value (`!tag value`): the tag, then the value.
        use serde::de::VariantAccess;
        let ((), variant) = data.variant_seed(self)?;
        variant.newtype_variant_seed(self)
    }
}

/// The YAML library's message for nesting beyond its own limit (128), in
/// this importer's words.
fn yaml_reason(message: String) -> String {
    if let Some(limit) = message.find(YAML_LIMIT) {
        message[limit + YAML_LIMIT.len()..].to_owned()
    } else if message.starts_with("recursion limit exceeded") {
        format!(
            "nested more than {MAX_YAML_DEPTH} levels deep, the most a pyptv YAML may be \
             (pyptv's nests 3: section, key, list)"
        )
    } else {
        message
    }
}

/// The lines (1-based) of a YAML text's top-level `section:` lines and of
/// the `key:` lines inside each, found in one pass (the first of each).
#[derive(Default)]
struct YamlLines {
    sections: BTreeMap<String, usize>,
    keys: BTreeMap<(String, String), usize>,
}

impl YamlLines {
    fn new(text: &str) -> Self {
        let mut lines = YamlLines::default();
        let mut section: Option<String> = None;
        for (i, line) in text.lines().enumerate() {
            let indented = line.starts_with(' ') || line.starts_with('\t');
            let trimmed = line.trim_start();
            if trimmed.is_empty() {
                continue;
            }
            if !indented {
                let name = trimmed.split(':').next().unwrap_or(trimmed).to_owned();
                lines.sections.entry(name.clone()).or_insert(i + 1);
                section = Some(name);
            } else if let (Some(section), Some((key, _))) = (&section, trimmed.split_once(':')) {
                lines
                    .keys
                    .entry((section.clone(), key.to_owned()))
                    .or_insert(i + 1);
            }
        }
        lines
    }

    /// The line of `key:` inside `section:`, or of `section:` itself for an
    /// empty key.
    fn line(&self, section: &str, key: &str) -> Option<usize> {
        if key.is_empty() {
            self.sections.get(section).copied()
        } else {
            self.keys
                .get(&(section.to_owned(), key.to_owned()))
                .copied()
        }
    }
}

fn read_yaml(
    files: &dyn ExperimentFiles,
    path: &Path,
    root: &Path,
) -> Result<Experiment, ExperimentError> {
    let text = files.read_text(path)?;
    check_yaml_flow(&text, path)?;
    // The items and depth first, aliases expanded, nothing built: the
    // sections skip what they ignore at any depth, and the value would
    // expand aliases without bound.
    let yaml_error = |error: serde_norway::Error| {
        let line = error.location().map(|l| l.line());
        let mut reason = yaml_reason(error.to_string());
        if let Some(at) = reason.find(" at line ") {
            reason.truncate(at);
        }
        ExperimentError::Invalid {
            file: path.to_owned(),
            location: line.map_or_else(|| "the whole file".to_owned(), |l| format!("line {l}")),
            reason,
        }
    };
    let items = std::cell::Cell::new(0);
    serde::de::DeserializeSeed::deserialize(
        YamlBudget {
            items: &items,
            depth: 0,
        },
        serde_norway::Deserializer::from_str(&text),
    )
    .or_else(|error| {
        // A text that does not parse fails before any item is walked: the
        // sections' own reading names the key where it breaks. Anything
        // else (a limit passed, a value the walk cannot take) is refused
        // here, before a parser that expands aliases runs.
        if items.get() == 0 && !error.to_string().contains(YAML_LIMIT) {
            Ok(())
        } else {
            Err(yaml_error(error))
        }
    })?;
    let value = serde_norway::from_str::<serde_norway::Value>(&text);
    let deserializer = serde_norway::Deserializer::from_str(&text);
    let sections: Sections = serde_path_to_error::deserialize(deserializer).map_err(|err| {
        let key = err.path().to_string();
        let inner = err.into_inner();
        let line = inner.location().map(|l| l.line());
        // The YAML library's message ends with its own position; the
        // location says it once.
        let mut reason = yaml_reason(inner.to_string());
        if let Some(at) = reason.find(" at line ") {
            reason.truncate(at);
        }
        // ... and may start with the key, which the location also names.
        if let Some(rest) = reason.strip_prefix(&format!("{key}: ")) {
            reason = rest.to_owned();
        }
        ExperimentError::Invalid {
            file: path.to_owned(),
            location: match (line, key.as_str()) {
                (Some(line), ".") => format!("line {line}"),
                (Some(line), key) => format!("line {line}, {key}"),
                (None, key) => key.to_owned(),
            },
            reason,
        }
    })?;
    let mut places = BTreeMap::new();
    let mut section_files = BTreeMap::new();
    // The sections read, the value may still have failed: a key given
    // twice in a section they ignore.
    let value = value.map_err(yaml_error)?;
    let lines = YamlLines::new(&text);
    let mut unmapped = Vec::new();
    if let serde_norway::Value::Mapping(top) = &value {
        for (section, body) in top {
            let Some(section) = section.as_str() else {
                continue;
            };
            section_files.insert(section.to_owned(), path.to_owned());
            if let Some(line) = lines.line(section, "") {
                places.insert(section.to_owned(), (path.to_owned(), line));
            }
            let per_key = matches!(
                section,
                "ptv" | "cal_ori" | "criteria" | "targ_rec" | "sequence" | "masking" | "track"
            );
            match body {
                serde_norway::Value::Mapping(keys) if per_key => {
                    for (key, value) in keys {
                        let Some(key) = key.as_str() else { continue };
                        let full = format!("{section}.{key}");
                        if let Some(line) = lines.line(section, key) {
                            places.insert(full.clone(), (path.to_owned(), line));
                        }
                        if let Some(reason) = unmapped_reason(section, key) {
                            unmapped.push(UnmappedSetting {
                                file: path.display().to_string(),
                                key: full,
                                value: yaml_value_text(value),
                                reason: reason.to_owned(),
                            });
                        }
                    }
                }
                other => {
                    if let Some(reason) = unmapped_reason(section, "") {
                        unmapped.push(UnmappedSetting {
                            file: path.display().to_string(),
                            key: section.to_owned(),
                            value: match other {
                                serde_norway::Value::Mapping(_) => "(the whole section)".into(),
                                other => yaml_value_text(other),
                            },
                            reason: reason.to_owned(),
                        });
                    }
                }
            }
        }
    }
    let locator = Locator {
        places,
        section_files,
    };
    map(files, sections, root, &locator, unmapped)
}

fn yaml_value_text(value: &serde_norway::Value) -> String {
    match value {
        serde_norway::Value::String(s) => s.clone(),
        other => serde_norway::to_string(other)
            .map(|s| s.trim().replace('\n', " "))
            .unwrap_or_default(),
    }
}

/// Why a `section.key` is not used, or `None` for the keys that are.
fn unmapped_reason(section: &str, key: &str) -> Option<&'static str> {
    let used = match section {
        "num_cams" => return None,
        "ptv" => matches!(
            key,
            "n_img"
                | "hp_flag"
                | "allcam_flag"
                | "imx"
                | "imy"
                | "pix_x"
                | "pix_y"
                | "mmp_n1"
                | "mmp_n2"
                | "mmp_n3"
                | "mmp_d"
                | "splitter"
        ),
        "cal_ori" => key == "img_ori",
        "criteria" => matches!(key, "X_lay" | "Zmin_lay" | "Zmax_lay" | "eps0"),
        "targ_rec" => matches!(
            key,
            "gvthres"
                | "disco"
                | "nnmin"
                | "nnmax"
                | "nxmin"
                | "nxmax"
                | "nymin"
                | "nymax"
                | "sumg_min"
        ),
        "sequence" => matches!(key, "base_name" | "first" | "last"),
        "masking" => matches!(key, "mask_flag" | "mask_base_name"),
        "track" => matches!(
            key,
            "dvxmin"
                | "dvxmax"
                | "dvymin"
                | "dvymax"
                | "dvzmin"
                | "dvzmax"
                | "dacc"
                | "flagNewParticles"
        ),
        _ => false,
    };
    if used {
        return None;
    }
    Some(match (section, key) {
        ("ptv", "img_name") => {
            "the images of one frame for pyptv's single-frame preview; ptv takes the sequence's"
        }
        ("ptv", "img_cal") => {
            "the calibration images; ptv takes each camera's orientation from the .ori that \
             cal_ori.img_ori names"
        }
        ("ptv", "tiff_flag") | ("cal_ori", "tiff_flag") => {
            "ptv reads the image format from the file itself"
        }
        ("ptv", "chfield") | ("cal_ori", "chfield") => {
            "field-interlaced images; ptv reads full frames (0 is the only value it supports)"
        }
        ("ptv", "inverse") => "inverted (negative) images are not supported; invert them first",
        ("criteria", "cnx" | "cny" | "cn" | "csumg") => {
            "OpenPTV's similarity limits on the targets' extent, size and brightness; ptv matches \
             by epipolar geometry alone here"
        }
        ("criteria", "corrmin") => {
            "OpenPTV's least correlation of a candidate; ptv ranks candidates by their \
             intersection residual"
        }
        ("targ_rec", "cr_sz") => {
            "the size of the cross OpenPTV draws on targets in its GUI; nothing to detect"
        }
        ("track", "angle") => {
            "OpenPTV's largest turning angle of a link (gon); ptv has no angle limit: it ranks a \
             trajectory's candidates by the change of acceleration over four positions (Malik et \
             al. 1993) within max_acceleration (dacc), which already refuses sharp turns at speed"
        }
        ("track", "") => {
            "the tracking settings (dv*, dacc, flagNewParticles are read; see the others' reasons)"
        }
        ("track", _) => "ptv's tracking has no such setting",
        (
            "cal_ori"
            | "detect_plate"
            | "man_ori"
            | "man_ori_coordinates"
            | "orient"
            | "shaking"
            | "multi_planes"
            | "dumbbell"
            | "sortgrid"
            | "examine",
            _,
        ) => {
            "a calibration setting; ptv calibrates with `ptv calibrate`, this import takes the \
             calibration from the .ori files"
        }
        ("unsharp_mask", _) => {
            "pyptv's unsharp-mask preprocessing; ptv's detection uses its high-pass filter \
             (hp_flag) only"
        }
        ("plugins", _) => "pyptv's Python plugins cannot run in ptv",
        ("pft_version", _) => {
            "reading existing targets instead of images; ptv detects from the images"
        }
        _ => "ptv has no such setting",
    })
}

// --- The legacy parameters/ folder ----------------------------------------

/// One `.par` file of the `parameters/` folder, read by OpenPTV's line
/// reader ([`openptv::ParLines`]) under `section.key`, each key's line
/// recorded for errors found later.
struct ParFile<'a> {
    path: PathBuf,
    lines: openptv::ParLines,
    section: &'static str,
    places: &'a mut BTreeMap<String, (PathBuf, usize)>,
}

impl<'a> ParFile<'a> {
    fn open(
        files: &dyn ExperimentFiles,
        dir: &Path,
        name: &str,
        section: &'static str,
        places: &'a mut BTreeMap<String, (PathBuf, usize)>,
    ) -> Result<Self, ExperimentError> {
        let path = dir.join("parameters").join(name);
        let text = files.read_text(&path)?;
        let lines =
            openptv::ParLines::new(&text, &path.display().to_string(), &format!("{section}."));
        Ok(ParFile {
            path,
            lines,
            section,
            places,
        })
    }

    /// Records where `key` was read.
    fn record(&mut self, key: &str) {
        if let Some(line) = self.lines.line_of(key) {
            self.places
                .insert(format!("{}.{key}", self.section), (self.path.clone(), line));
        }
    }

    fn text(&mut self, key: &str) -> Result<String, ExperimentError> {
        let value = self.lines.text(key)?;
        self.record(key);
        Ok(value)
    }

    fn number(&mut self, key: &str) -> Result<f64, ExperimentError> {
        let value = self.lines.number(key)?;
        self.record(key);
        Ok(value)
    }

    fn integer(&mut self, key: &str) -> Result<i64, ExperimentError> {
        let value = self.lines.integer(key)?;
        self.record(key);
        Ok(value)
    }

    fn unsigned(&mut self, key: &str) -> Result<u64, ExperimentError> {
        let value = self.lines.unsigned(key)?;
        self.record(key);
        Ok(value)
    }
}

fn read_legacy(files: &dyn ExperimentFiles, dir: &Path) -> Result<Experiment, ExperimentError> {
    let mut places = BTreeMap::new();
    let mut section_files = BTreeMap::new();
    let mut unmapped = Vec::new();
    let par = |name: &str| dir.join("parameters").join(name);
    for (section, file) in LEGACY_FILES {
        section_files.insert(section.to_owned(), par(file));
    }
    let ptv = read_legacy_ptv(files, &par("ptv.par"), &mut places, &mut unmapped)?;
    let n = ptv.n_img.unwrap_or_default();
    let cal_ori = read_legacy_cal_ori(files, dir, n, &mut places, &mut unmapped)?;
    let criteria = read_legacy_criteria(files, dir, &mut places, &mut unmapped)?;
    let targ_rec = read_legacy_targ_rec(files, dir, n, &mut places, &mut unmapped)?;
    let sequence = read_legacy_sequence(files, dir, n, &mut places)?;
    let track = if files.is_file(&par("track.par")) {
        Some(read_legacy_track(files, dir, &mut places, &mut unmapped)?)
    } else {
        None
    };
    // The other files are calibration's or the GUI's.
    let others: Vec<String> = files
        .list(&dir.join("parameters"))
        .into_iter()
        .filter(|name| name.ends_with(".par"))
        .filter(|name| !LEGACY_FILES.iter().any(|(_, file)| file == name))
        .collect();
    for name in others {
        let section = name.trim_end_matches(".par").to_owned();
        unmapped.push(UnmappedSetting {
            file: par(&name).display().to_string(),
            key: section.clone(),
            value: "(the whole file)".into(),
            reason: unmapped_reason(&section, "").unwrap_or_default().into(),
        });
    }

    let sections = Sections {
        num_cams: Some(n),
        ptv,
        cal_ori,
        criteria,
        targ_rec,
        sequence,
        masking: None,
        track,
    };
    let locator = Locator {
        places,
        section_files,
    };
    map(files, sections, dir, &locator, unmapped)
}

/// A setting of a `.par` file that `ptv` reads but does not use, with the
/// module table's reason.
fn legacy_unmapped(file: &Path, section: &str, key: &str, value: String) -> UnmappedSetting {
    UnmappedSetting {
        file: file.display().to_string(),
        key: format!("{section}.{key}"),
        value,
        reason: unmapped_reason(section, key).unwrap_or_default().into(),
    }
}

/// The `.par` files read as the sections of pyptv's YAML.
const LEGACY_FILES: [(&str, &str); 6] = [
    ("ptv", "ptv.par"),
    ("cal_ori", "cal_ori.par"),
    ("criteria", "criteria.par"),
    ("targ_rec", "targ_rec.par"),
    ("sequence", "sequence.par"),
    ("track", "track.par"),
];

/// ptv.par: OpenPTV's one reader of it, keys as pyptv's YAML names them.
fn read_legacy_ptv(
    files: &dyn ExperimentFiles,
    ptv_path: &Path,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<PtvSection, ExperimentError> {
    let ptv_par = openptv::read_ptv_par(
        &files.read_text(ptv_path)?,
        &ptv_path.display().to_string(),
        "ptv.",
    )?;
    for (key, line) in ptv_par.lines() {
        places.insert(format!("ptv.{key}"), (ptv_path.to_owned(), line));
    }
    let n = ptv_par.num_cams();
    let ptv = PtvSection {
        n_img: Some(n),
        img_name: ptv_par.img_name,
        hp_flag: ptv_par.hp_flag,
        allcam_flag: ptv_par.allcam_flag,
        tiff_flag: ptv_par.tiff_flag,
        imx: ptv_par.imx,
        imy: ptv_par.imy,
        pix_x: ptv_par.pix_x,
        pix_y: ptv_par.pix_y,
        chfield: ptv_par.chfield,
        mmp_n1: ptv_par.mmp_n1,
        mmp_n2: ptv_par.mmp_n2,
        mmp_n3: ptv_par.mmp_n3,
        mmp_d: ptv_par.mmp_d,
        splitter: false,
    };
    let img_name = ptv.img_name.join(" ");
    unmapped.push(legacy_unmapped(ptv_path, "ptv", "img_name", img_name));
    let tiff_flag = u8::from(ptv.tiff_flag).to_string();
    unmapped.push(legacy_unmapped(ptv_path, "ptv", "tiff_flag", tiff_flag));
    Ok(ptv)
}

/// cal_ori.par: the `.ori` file of each camera.
fn read_legacy_cal_ori(
    files: &dyn ExperimentFiles,
    dir: &Path,
    n: usize,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<CalOriSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "cal_ori.par", "cal_ori", places)?;
    let fixp_name = f.text("fixp_name")?;
    let mut img_ori = Vec::new();
    for i in 0..n {
        f.text(&format!("img_cal_name[{i}]"))?;
        img_ori.push(f.text(&format!("img_ori[{i}]"))?);
    }
    let cal_ori_path = f.path.clone();
    unmapped.push(legacy_unmapped(
        &cal_ori_path,
        "cal_ori",
        "fixp_name",
        fixp_name,
    ));
    Ok(CalOriSection { img_ori })
}

/// criteria.par: the layers, the band; the similarity terms are not used.
fn read_legacy_criteria(
    files: &dyn ExperimentFiles,
    dir: &Path,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<CriteriaSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "criteria.par", "criteria", places)?;
    let mut lay = [[0.0; 3]; 2];
    for (i, layer) in lay.iter_mut().enumerate() {
        layer[0] = f.number(&format!("X_lay[{i}]"))?;
        layer[1] = f.number(&format!("Zmin_lay[{i}]"))?;
        layer[2] = f.number(&format!("Zmax_lay[{i}]"))?;
    }
    let mut similarity = Vec::new();
    for key in ["cnx", "cny", "cn", "csumg", "corrmin"] {
        similarity.push((key, f.number(key)?));
    }
    let criteria = CriteriaSection {
        X_lay: vec![lay[0][0], lay[1][0]],
        Zmin_lay: vec![lay[0][1], lay[1][1]],
        Zmax_lay: vec![lay[0][2], lay[1][2]],
        eps0: f.number("eps0")?,
    };
    let criteria_path = f.path.clone();
    for (key, value) in similarity {
        unmapped.push(legacy_unmapped(
            &criteria_path,
            "criteria",
            key,
            value.to_string(),
        ));
    }
    Ok(criteria)
}

/// targ_rec.par: detection. liboptv reads four thresholds whatever the
/// camera count.
fn read_legacy_targ_rec(
    files: &dyn ExperimentFiles,
    dir: &Path,
    n: usize,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<TargRecSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "targ_rec.par", "targ_rec", places)?;
    let mut gvthres = Vec::new();
    for i in 0..n.max(4) {
        gvthres.push(f.integer(&format!("gvthres[{i}]"))?);
    }
    let targ_rec = TargRecSection {
        gvthres,
        disco: f.integer("disco")?,
        nnmin: f.integer("nnmin")?,
        nnmax: f.integer("nnmax")?,
        nxmin: f.integer("nxmin")?,
        nxmax: f.integer("nxmax")?,
        nymin: f.integer("nymin")?,
        nymax: f.integer("nymax")?,
        sumg_min: f.integer("sumg_min")?,
    };
    let cr_sz = f.integer("cr_sz")?;
    unmapped.push(legacy_unmapped(
        &f.path,
        "targ_rec",
        "cr_sz",
        cr_sz.to_string(),
    ));
    Ok(targ_rec)
}

/// sequence.par: the image names and the frames.
fn read_legacy_sequence(
    files: &dyn ExperimentFiles,
    dir: &Path,
    n: usize,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
) -> Result<SequenceSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "sequence.par", "sequence", places)?;
    let mut base_name = Vec::new();
    for i in 0..n {
        let name = f.text(&format!("base_name[{i}]"))?;
        if name == "--" {
            return Err(ExperimentError::Invalid {
                file: f.path.clone(),
                location: format!("base_name[{i}]"),
                reason: "names `--` for this camera: pyptv's splitter, whose cameras are views \
                         of the first camera's image, which the .par files cannot say; give \
                         pyptv's YAML of the experiment (parameters_*.yaml, with ptv.splitter: \
                         true)"
                    .into(),
            });
        }
        base_name.push(name);
    }
    Ok(SequenceSection {
        base_name,
        first: f.unsigned("first")?,
        last: f.unsigned("last")?,
    })
}

/// track.par: nine values, liboptv's `read_track_par` (pyptv's later
/// lines, one per camera, are not read by liboptv either).
fn read_legacy_track(
    files: &dyn ExperimentFiles,
    dir: &Path,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<TrackSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "track.par", "track", places)?;
    let mut dv = [0.0; 6];
    for (value, key) in dv
        .iter_mut()
        .zip(["dvxmin", "dvxmax", "dvymin", "dvymax", "dvzmin", "dvzmax"])
    {
        *value = f.number(key)?;
    }
    let angle = f.number("angle")?;
    let dacc = f.number("dacc")?;
    let new_particles = f.integer("flagNewParticles")?;
    unmapped.push(legacy_unmapped(
        &f.path,
        "track",
        "angle",
        angle.to_string(),
    ));
    Ok(TrackSection {
        dvxmin: dv[0],
        dvxmax: dv[1],
        dvymin: dv[2],
        dvymax: dv[3],
        dvzmin: dv[4],
        dvzmax: dv[5],
        angle: Some(angle),
        dacc,
        flagNewParticles: new_particles != 0,
    })
}

// --- The mapping ----------------------------------------------------------

fn map(
    files: &dyn ExperimentFiles,
    s: Sections,
    root: &Path,
    at: &Locator,
    unmapped: Vec<UnmappedSetting>,
) -> Result<Experiment, ExperimentError> {
    let (n, splitter) = camera_count(&s, at)?;
    let cameras = map_cameras(files, &s, root, at, n)?;
    let detection = map_detection(&s, at, n)?;
    let matching = map_matching(&s, at, &cameras, n)?;
    let sequence = map_sequence(&s, at, splitter)?;
    let masks = map_masks(files, &s, root, at, n)?;
    let tracking = s.track.as_ref().map(|t| map_tracking(t, at)).transpose()?;

    Ok(Experiment {
        root: root.to_owned(),
        cameras,
        splitter,
        detection,
        matching,
        tracking,
        sequence,
        masks,
        unmapped,
    })
}

/// The number of cameras, and pyptv's splitter if the images are its
/// quadrants; each per-camera list checked against the number.
fn camera_count(s: &Sections, at: &Locator) -> Result<(usize, Option<Splitter>), ExperimentError> {
    let n = match (s.num_cams, s.ptv.n_img) {
        (Some(n), _) | (None, Some(n)) => n,
        (None, None) => return Err(at.invalid("num_cams", "the number of cameras is missing")),
    };
    if !(1..=calibration::MAX_CAMERAS).contains(&n) {
        return Err(at.invalid(
            "num_cams",
            format!(
                "the number of cameras must be 1..{}, got {n}",
                calibration::MAX_CAMERAS
            ),
        ));
    }
    if s.ptv.chfield != 0 {
        return Err(at.invalid(
            "ptv.chfield",
            format!(
                "field-interlaced images (chfield {}) are not supported; set it to 0",
                s.ptv.chfield
            ),
        ));
    }
    let count = |key: &str, len: usize, at_least: bool| {
        if len == n || (at_least && len > n) {
            Ok(())
        } else {
            Err(at.invalid(
                key,
                format!("gives {len} values for {n} cameras; give one per camera, in camera order"),
            ))
        }
    };
    count("cal_ori.img_ori", s.cal_ori.img_ori.len(), false)?;
    count("targ_rec.gvthres", s.targ_rec.gvthres.len(), true)?;
    let splitter = s.ptv.splitter.then(Splitter::quadrants);
    if let Some(splitter) = splitter {
        if splitter.views() != n {
            return Err(at.invalid(
                "ptv.splitter",
                format!(
                    "pyptv's splitter makes {} views of one image, but the experiment has {n} \
                     cameras",
                    splitter.views()
                ),
            ));
        }
    } else {
        count("sequence.base_name", s.sequence.base_name.len(), false)?;
    }
    if s.sequence.base_name.is_empty() {
        return Err(at.invalid("sequence.base_name", "no image name pattern is given"));
    }

    Ok((n, splitter))
}

/// The cameras: each `.ori` (and `.addpar`) of `cal_ori` on `ptv.par`'s
/// sensor and media.
fn map_cameras(
    files: &dyn ExperimentFiles,
    s: &Sections,
    root: &Path,
    at: &Locator,
    n: usize,
) -> Result<Vec<Camera>, ExperimentError> {
    let sensor = Sensor {
        width: s.ptv.imx,
        height: s.ptv.imy,
        pixel_size_x: s.ptv.pix_x,
        pixel_size_y: s.ptv.pix_y,
    };
    let mut parameters = Vec::with_capacity(n);
    for (i, ori) in s.cal_ori.img_ori.iter().enumerate() {
        let key = format!("cal_ori.img_ori[{i}]");
        let ori_path = files
            .resolve(root, ori)
            .map_err(|reason| ExperimentError::Refused {
                file: at.file_of(&key),
                location: at.location(&key),
                name: ori.clone(),
                reason,
            })?;
        if !files.is_file(&ori_path) {
            return Err(ExperimentError::Missing {
                file: at.file_of(&key),
                location: at.location(&key),
                missing: ori_path,
            });
        }
        let source = ori_path.display().to_string();
        let (exterior, interior, glass_vector) =
            openptv::parse_ori(&files.read_text(&ori_path)?, &source)?;
        let addpar = openptv::addpar_path(&ori_path);
        let distortion = if files.is_file(&addpar) {
            openptv::parse_addpar(&files.read_text(&addpar)?, &addpar.display().to_string())?
        } else {
            Distortion::default()
        };
        let name = Path::new(ori)
            .file_name()
            .and_then(|n| n.to_str())
            .map(|n| n.split('.').next().unwrap_or(n).to_owned())
            .filter(|n| !n.is_empty())
            .unwrap_or_else(|| format!("cam{}", i + 1));
        parameters.push(CameraParameters {
            name,
            sensor: sensor.clone(),
            exterior,
            interior,
            distortion,
            media: Media {
                n_air: s.ptv.mmp_n1,
                walls: vec![Wall {
                    n: s.ptv.mmp_n2,
                    thickness: s.ptv.mmp_d,
                }],
                n_object: s.ptv.mmp_n3,
                glass_vector,
            },
        });
    }
    Ok(calibration::from_parameters(
        parameters,
        &format!(
            "{} with the .ori files of cal_ori",
            at.file_of("ptv.imx").display()
        ),
    )?)
}

/// Detection per camera from `targ_rec.par` (and `ptv.par`'s high-pass
/// flag).
fn map_detection(
    s: &Sections,
    at: &Locator,
    n: usize,
) -> Result<Vec<DetectionParameters>, ExperimentError> {
    let t = &s.targ_rec;
    let range = |key: &str, value: i64, max: i64| -> Result<i64, ExperimentError> {
        if (0..=max).contains(&value) {
            Ok(value)
        } else {
            Err(at.invalid(key, format!("must be 0..{max}, got {value}")))
        }
    };
    let u16_max = i64::from(u16::MAX);
    let u32_max = i64::from(u32::MAX);
    let base = DetectionParameters {
        threshold: 0,
        highpass_radius: if s.ptv.hp_flag {
            OPENPTV_HIGHPASS_RADIUS
        } else {
            0
        },
        min_pixels: range("targ_rec.nnmin", t.nnmin, u32_max)? as u32,
        max_pixels: range("targ_rec.nnmax", t.nnmax, u32_max)? as u32,
        min_nx: range("targ_rec.nxmin", t.nxmin, u32_max)? as u32,
        max_nx: range("targ_rec.nxmax", t.nxmax, u32_max)? as u32,
        min_ny: range("targ_rec.nymin", t.nymin, u32_max)? as u32,
        max_ny: range("targ_rec.nymax", t.nymax, u32_max)? as u32,
        // liboptv keeps `sumg > sumg_min`; ours keeps `sumg >= min_sumg`.
        min_sumg: range("targ_rec.sumg_min", t.sumg_min, i64::MAX - 1)? as u64 + 1,
        split: true,
        split_depth: Some(range("targ_rec.disco", t.disco, u16_max)? as u16),
        // OpenPTV's targ_rec: the grey value weighted centroid.
        centroid: Centroid::Weighted,
        // OpenPTV has no noise-relative test: its `sumg_min` decides.
        min_snr: 0,
    };
    let mut detection = Vec::with_capacity(n);
    for (i, &threshold) in t.gvthres.iter().take(n).enumerate() {
        let parameters = DetectionParameters {
            threshold: range(&format!("targ_rec.gvthres[{i}]"), threshold, u16_max)? as u16,
            ..base.clone()
        };
        parameters.validate().map_err(|e| {
            let key = match e.field {
                "min_pixels" => "nnmin",
                "min_nx" => "nxmin",
                "min_ny" => "nymin",
                other => other,
            };
            at.invalid(&format!("targ_rec.{key}"), e.reason)
        })?;
        detection.push(parameters);
    }
    Ok(detection)
}

/// Matching from `criteria.par`: the band, and the volume between its
/// layers that the cameras see.
fn map_matching(
    s: &Sections,
    at: &Locator,
    cameras: &[Camera],
    n: usize,
) -> Result<MatchingParameters, ExperimentError> {
    let c = &s.criteria;
    for key in ["X_lay", "Zmin_lay", "Zmax_lay"] {
        let len = match key {
            "X_lay" => c.X_lay.len(),
            "Zmin_lay" => c.Zmin_lay.len(),
            _ => c.Zmax_lay.len(),
        };
        if len != 2 {
            return Err(at.invalid(
                &format!("criteria.{key}"),
                format!("must have 2 values (the two layers), got {len}"),
            ));
        }
    }
    if c.X_lay[0] >= c.X_lay[1] {
        return Err(at.invalid(
            "criteria.X_lay",
            format!(
                "X_lay[0] ({}) must be smaller than X_lay[1] ({})",
                c.X_lay[0], c.X_lay[1]
            ),
        ));
    }
    for i in 0..2 {
        if c.Zmin_lay[i] >= c.Zmax_lay[i] {
            return Err(at.invalid(
                &format!("criteria.Zmin_lay[{i}]"),
                format!(
                    "Zmin_lay[{i}] ({}) must be smaller than Zmax_lay[{i}] ({})",
                    c.Zmin_lay[i], c.Zmax_lay[i]
                ),
            ));
        }
    }
    if !(c.eps0.is_finite() && c.eps0 > 0.0) {
        return Err(at.invalid(
            "criteria.eps0",
            format!("must be a positive length (mm), got {}", c.eps0),
        ));
    }
    let z_min = c.Zmin_lay[0].min(c.Zmin_lay[1]);
    let z_max = c.Zmax_lay[0].max(c.Zmax_lay[1]);
    let (y_min, y_max) = seen_y_range(cameras, z_min, z_max).ok_or_else(|| {
        at.invalid(
            "criteria.Zmin_lay",
            "no camera sees the depth range Zmin_lay..Zmax_lay; check the volume and the \
             calibration",
        )
    })?;
    Ok(MatchingParameters {
        tolerance: c.eps0 / ((s.ptv.pix_x + s.ptv.pix_y) / 2.0),
        volume: Some(Volume {
            min: Point3::new(c.X_lay[0], y_min, z_min),
            max: Point3::new(c.X_lay[1], y_max, z_max),
        }),
        min_cameras: if s.ptv.allcam_flag { n.max(2) } else { 2 },
        ..MatchingParameters::default()
    })
}

/// The frames of `sequence.par`, and its image name patterns (one with a
/// splitter).
fn map_sequence(
    s: &Sections,
    at: &Locator,
    splitter: Option<Splitter>,
) -> Result<SequenceFrames, ExperimentError> {
    if s.sequence.first > s.sequence.last {
        return Err(at.invalid(
            "sequence.first",
            format!(
                "the first frame ({}) is after the last ({})",
                s.sequence.first, s.sequence.last
            ),
        ));
    }
    let base_names = if splitter.is_some() {
        &s.sequence.base_name[..1]
    } else {
        &s.sequence.base_name[..]
    };
    let base_names = base_names
        .iter()
        .map(|name| {
            FramePattern::parse(name, WithoutNumber::AppendAfterDot)
                .map_err(|reason| at.invalid("sequence.base_name", reason))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(SequenceFrames {
        base_names,
        first: s.sequence.first,
        last: s.sequence.last,
    })
}

/// pyptv's masks, `mask_base_name % (camera + 1)`, each an existing
/// file.
fn map_masks(
    files: &dyn ExperimentFiles,
    s: &Sections,
    root: &Path,
    at: &Locator,
    n: usize,
) -> Result<Option<Vec<PathBuf>>, ExperimentError> {
    Ok(match &s.masking {
        Some(m) if m.mask_flag => {
            let pattern = FramePattern::parse(&m.mask_base_name, WithoutNumber::AppendAfterDot)
                .map_err(|reason| at.invalid("masking.mask_base_name", reason))?;
            let mut list = Vec::with_capacity(n);
            for camera in 0..n {
                let name = pattern.format(camera as u64 + 1);
                let path =
                    files
                        .resolve(root, &name)
                        .map_err(|reason| ExperimentError::Refused {
                            file: at.file_of("masking.mask_base_name"),
                            location: at.location("masking.mask_base_name"),
                            name: name.clone(),
                            reason,
                        })?;
                if !files.is_file(&path) {
                    return Err(ExperimentError::Missing {
                        file: at.file_of("masking.mask_base_name"),
                        location: at.location("masking.mask_base_name"),
                        missing: path,
                    });
                }
                list.push(path);
            }
            Some(list)
        }
        _ => None,
    })
}

/// `track.par` in `ptv`'s terms (the module's table).
///
/// OpenPTV searches a trajectory's next particle in the box `dvmin..dvmax`
/// (per axis, mm per frame) around its position (a new trajectory) or its
/// prediction; `ptv` searches a new trajectory's first link within the
/// sphere of `max_velocity` around it. `max_velocity` is the radius of the
/// sphere around the box, `|(max(|dvxmin|, |dvxmax|), ...)|`: every link
/// OpenPTV can make, ptv can too (the box's corners are the farthest).
/// `dacc` is the same bound in both: the largest change of velocity
/// between two frames (mm per frame²), `ptv`'s `max_acceleration`.
fn map_tracking(t: &TrackSection, at: &Locator) -> Result<ExperimentTracking, ExperimentError> {
    let axes = [
        ("dvxmin", t.dvxmin, "dvxmax", t.dvxmax),
        ("dvymin", t.dvymin, "dvymax", t.dvymax),
        ("dvzmin", t.dvzmin, "dvzmax", t.dvzmax),
    ];
    let mut reach = Vector3::zeros();
    for (i, (min_key, min, max_key, max)) in axes.into_iter().enumerate() {
        if min > max {
            return Err(at.invalid(
                &format!("track.{min_key}"),
                format!(
                    "{min_key} ({min}) is above {max_key} ({max}); give the smallest and largest \
                     displacement per frame along the axis (mm), e.g. -{0} and {0}",
                    max.abs().max(min.abs())
                ),
            ));
        }
        reach[i] = min.abs().max(max.abs());
    }
    let parameters = TrackingParameters {
        max_acceleration: t.dacc,
        ..TrackingParameters::new(reach.norm())
    };
    parameters.validate().map_err(|e| {
        let key = if e.to_string().contains("max_acceleration") {
            "track.dacc"
        } else {
            "track.dvxmax"
        };
        at.invalid(key, e.to_string())
    })?;
    Ok(ExperimentTracking {
        parameters,
        recovery: t.flagNewParticles,
    })
}

/// The Y range some camera sees between depths `z_min` and `z_max`: the
/// union over the cameras of where the rays through their image corners
/// meet those depths.
fn seen_y_range(cameras: &[Camera], z_min: f64, z_max: f64) -> Option<(f64, f64)> {
    let mut range: Option<(f64, f64)> = None;
    for camera in cameras {
        let s = camera.sensor();
        let (w, h) = (f64::from(s.width), f64::from(s.height));
        for pixel in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
            let Ok(ray) = camera.ray(Point2::new(pixel.0, pixel.1)) else {
                continue;
            };
            for z in [z_min, z_max] {
                if let Some(point) = ray.at_z(z) {
                    let y = point.y;
                    if y.is_finite() {
                        range = Some(match range {
                            None => (y, y),
                            Some((lo, hi)) => (lo.min(y), hi.max(y)),
                        });
                    }
                }
            }
        }
    }
    range.filter(|(lo, hi)| hi > lo)
}

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
