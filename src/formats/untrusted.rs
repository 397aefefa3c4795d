//! Every parser of untrusted input, fed mutated and random documents
//! (proptest in place of a fuzzer, which would need a nightly toolchain CI
//! does not have).
//!
//! Each property starts from a valid document of its format (the repository's
//! OpenPTV test files, or one written here) and applies up to a dozen
//! mutations: bytes flipped, tokens that break number parsers (`NaN`,
//! `inf`, `1e999`, 20-digit integers, `-0`), separators and brackets
//! inserted, spans deleted, the text truncated or a line repeated. Random
//! text of any characters is tried too. What must hold for any input:
//!
//! - the parser returns, without panicking, within the case;
//! - an error names its source (the message a user gets says which file);
//! - a value it accepts is one the core can take: finite coordinates,
//!   cameras that passed `Camera::new`, images whose sample count is
//!   width x height.
//!
//! `cargo test --lib untrusted` runs each property for proptest's default
//! 256 cases (a few seconds); `PROPTEST_CASES=100000 cargo test --release
//! --lib untrusted` fuzzes longer.

use proptest::prelude::*;

use super::{calibration, control, csv, image, openptv, FormatError};

/// The source named in every parser call.
const SOURCE: &str = "fuzzed input";

/// Tokens that break careless number and structure parsing.
const TOKENS: &[&str] = &[
    "NaN",
    "nan",
    "inf",
    "-inf",
    "1e999",
    "-1e308",
    "99999999999999999999",
    "-0",
    "0x10",
    "\n",
    "\r\n",
    "\0",
    " ",
    ",",
    "\"",
    "{",
    "}",
    "[",
    "]",
    ":",
    "-",
    "é",
    "\u{feff}",
    "4294967296",
];

/// One edit of a document.
#[derive(Clone, Debug)]
enum Mutation {
    /// Replace the byte at this fraction of the length.
    Flip(f64, u8),
    /// Insert a token at this fraction of the length.
    Insert(f64, usize),
    /// Delete up to this many bytes from this fraction on.
    Delete(f64, usize),
    /// Keep only this fraction of the document.
    Truncate(f64),
    /// Repeat the line at this fraction of the lines.
    RepeatLine(f64),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (0.0..1.0, any::<u8>()).prop_map(|(at, byte)| Mutation::Flip(at, byte)),
        (0.0..1.0, 0..TOKENS.len()).prop_map(|(at, token)| Mutation::Insert(at, token)),
        (0.0..1.0, 1usize..40).prop_map(|(at, n)| Mutation::Delete(at, n)),
        (0.0..1.0).prop_map(Mutation::Truncate),
        (0.0..1.0).prop_map(Mutation::RepeatLine),
    ]
}

/// Index at fraction `at` of `len`.
fn position(at: f64, len: usize) -> usize {
    ((at * len as f64) as usize).min(len)
}

/// Applies the mutations to a document's bytes.
fn mutate(seed: &[u8], mutations: &[Mutation]) -> Vec<u8> {
    let mut bytes = seed.to_vec();
    for m in mutations {
        match *m {
            Mutation::Flip(at, byte) => {
                if !bytes.is_empty() {
                    let i = position(at, bytes.len() - 1);
                    bytes[i] = byte;
                }
            }
            Mutation::Insert(at, token) => {
                let i = position(at, bytes.len());
                bytes.splice(i..i, TOKENS[token].bytes());
            }
            Mutation::Delete(at, n) => {
                let i = position(at, bytes.len());
                let end = (i + n).min(bytes.len());
                bytes.drain(i..end);
            }
            Mutation::Truncate(at) => bytes.truncate(position(at, bytes.len())),
            Mutation::RepeatLine(at) => {
                let lines: Vec<&[u8]> = bytes.split(|b| *b == b'\n').collect();
                let i = position(at, lines.len().saturating_sub(1));
                let mut out = Vec::with_capacity(bytes.len() * 2);
                for (k, line) in lines.iter().enumerate() {
                    out.extend_from_slice(line);
                    out.push(b'\n');
                    if k == i {
                        out.extend_from_slice(line);
                        out.push(b'\n');
                    }
                }
                bytes = out;
            }
        }
    }
    bytes
}

/// Mutated text of a seed (invalid UTF-8 replaced, as an HTTP layer that
/// checked UTF-8 would have refused it).
fn mutated_text(seed: &'static str) -> impl Strategy<Value = String> {
    prop::collection::vec(mutation(), 0..12)
        .prop_map(move |m| String::from_utf8_lossy(&mutate(seed.as_bytes(), &m)).into_owned())
}

/// Mutated text of a seed, or arbitrary text.
fn text_input(seed: &'static str) -> impl Strategy<Value = String> {
    prop_oneof![4 => mutated_text(seed), 1 => ".{0,400}"]
}

/// An error must say which input it is about.
fn names_its_source(error: &FormatError) -> bool {
    error.to_string().contains(SOURCE)
}

const ORI: &str = include_str!("../../tests/data/openptv/test_cavity/cal/cam1.tif.ori");
const ADDPAR: &str = include_str!("../../tests/data/openptv/golden/rig_a/cam1.addpar");
const PTV_PAR: &str = include_str!("../../tests/data/openptv/test_cavity/parameters/ptv.par");
const OPENPTV_TARGETS: &str =
    include_str!("../../tests/data/openptv/test_cavity/img_orig/cam1.10001_targets");
const CONTROL: &str = include_str!("../../tests/data/openptv/test_cavity/cal/target_on_a_side.txt");
const CSV_TARGETS: &str = "x,y,n,nx,ny,sumg\n10.5,20.25,9,3,3,1200\n600.125,400.5,12,4,4,2400\n";
const POINTS: &str = "x,y,z\n0,0,0\n10,-5,3.5\n";
const OBSERVATIONS: &str = "point,camera,x,y\n0,0,640.5,512.25\n0,1,600,500\n1,0,10,20\n";
const MARKS: &str = "1 100.5 200.25\n2 300 400\n3 500.75 600\n";

/// The first camera of the test_cavity calibration, as calibration JSON
/// with a wall: every field the format has.
fn calibration_seed() -> &'static str {
    static SEED: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    SEED.get_or_init(|| {
        let texts: Vec<openptv::OriTexts> = (1..=4)
            .map(|k| openptv::OriTexts {
                name: format!("cam{k}"),
                ori: (ORI.to_owned(), "ori".to_owned()),
                addpar: Some((ADDPAR.to_owned(), "addpar".to_owned())),
            })
            .collect();
        let cameras = openptv::import_texts(PTV_PAR, "ptv.par", &texts).expect("seed cameras");
        calibration::to_json(&cameras)
    })
}

fn calibration_input() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => prop::collection::vec(mutation(), 0..12).prop_map(|m| {
            String::from_utf8_lossy(&mutate(calibration_seed().as_bytes(), &m)).into_owned()
        }),
        1 => ".{0,400}",
    ]
}

/// A small greyscale image encoded as PNG or TIFF, 8 or 16 bits.
fn encoded_image(tiff: bool, sixteen: bool) -> Vec<u8> {
    use ::image::{ExtendedColorType, ImageEncoder};
    let (width, height) = (13u32, 7u32);
    let mut bytes = Vec::new();
    let cursor = std::io::Cursor::new(&mut bytes);
    let (samples, kind): (Vec<u8>, ExtendedColorType) = if sixteen {
        let pixels: Vec<u16> = (0..width * height).map(|i| (i * 397) as u16).collect();
        let raw = pixels.iter().flat_map(|p| p.to_ne_bytes()).collect();
        (raw, ExtendedColorType::L16)
    } else {
        (
            (0..width * height).map(|i| (i * 7) as u8).collect(),
            ExtendedColorType::L8,
        )
    };
    let written = if tiff {
        ::image::codecs::tiff::TiffEncoder::new(cursor).write_image(&samples, width, height, kind)
    } else {
        ::image::codecs::png::PngEncoder::new(cursor).write_image(&samples, width, height, kind)
    };
    written.expect("encoding the seed image");
    bytes
}

fn image_input() -> impl Strategy<Value = Vec<u8>> {
    let seeds: Vec<Vec<u8>> = [(false, false), (false, true), (true, false), (true, true)]
        .iter()
        .map(|&(tiff, sixteen)| encoded_image(tiff, sixteen))
        .collect();
    prop_oneof![
        4 => (0..seeds.len(), prop::collection::vec(mutation(), 0..6))
            .prop_map(move |(seed, m)| mutate(&seeds[seed], &m)),
        1 => prop::collection::vec(any::<u8>(), 0..200),
    ]
}

proptest! {
    #[test]
    fn calibration_json(text in calibration_input()) {
        match calibration::from_json(&text, SOURCE) {
            // Cameras exist only through Camera::new: accepted means valid.
            Ok(cameras) => prop_assert!(
                (calibration::MIN_CAMERAS..=calibration::MAX_CAMERAS).contains(&cameras.len())
            ),
            Err(error) => prop_assert!(names_its_source(&error), "{error}"),
        }
        if let Err(error) = calibration::parameters_from_json(&text, SOURCE) {
            prop_assert!(names_its_source(&error), "{error}");
        }
    }

    #[test]
    fn openptv_ori_and_addpar(ori in text_input(ORI), addpar in text_input(ADDPAR)) {
        match openptv::parse_ori(&ori, SOURCE) {
            Ok((exterior, interior, glass)) => {
                prop_assert!(exterior.position.iter().all(|v| v.is_finite()));
                prop_assert!(interior.c.is_finite() && glass.iter().all(|v| v.is_finite()));
            }
            Err(error) => prop_assert!(names_its_source(&error), "{error}"),
        }
        if let Err(error) = openptv::parse_addpar(&addpar, SOURCE) {
            prop_assert!(names_its_source(&error), "{error}");
        }
    }

    #[test]
    fn openptv_ptv_par_and_import(par in text_input(PTV_PAR), ori in text_input(ORI)) {
        if let Err(error) = openptv::parse_ptv_par(&par, SOURCE) {
            prop_assert!(names_its_source(&error), "{error}");
        }
        let texts: Vec<openptv::OriTexts> = (0..4)
            .map(|k| openptv::OriTexts {
                name: format!("cam{k}"),
                ori: (ori.clone(), SOURCE.to_owned()),
                addpar: None,
            })
            .collect();
        if let Err(error) = openptv::import_texts(&par, SOURCE, &texts) {
            prop_assert!(names_its_source(&error), "{error}");
        }
    }

    #[test]
    fn targets_in_either_format(
        openptv_text in text_input(OPENPTV_TARGETS),
        csv_text in text_input(CSV_TARGETS),
    ) {
        for text in [&openptv_text, &csv_text] {
            match super::parse_targets(text, SOURCE) {
                Ok(targets) => prop_assert!(
                    targets.iter().all(|t| t.x.is_finite() && t.y.is_finite()),
                    "a target with a non-finite position was accepted"
                ),
                Err(error) => prop_assert!(names_its_source(&error), "{error}"),
            }
        }
    }

    #[test]
    fn csv_points_and_observations(
        points in text_input(POINTS),
        observations in text_input(OBSERVATIONS),
    ) {
        match csv::parse_points(&points, SOURCE) {
            Ok(points) => prop_assert!(points.iter().all(|p| p.iter().all(|v| v.is_finite()))),
            Err(error) => prop_assert!(names_its_source(&error), "{error}"),
        }
        match csv::parse_observations(&observations, SOURCE, 4) {
            Ok(points) => prop_assert!(points
                .iter()
                .all(|p| p.observations.iter().all(|o| o.pixel.x.is_finite() && o.pixel.y.is_finite()))),
            Err(error) => prop_assert!(names_its_source(&error), "{error}"),
        }
    }

    #[test]
    fn control_points_and_marks(block in text_input(CONTROL), marks in text_input(MARKS)) {
        match control::parse_control_points(&block, SOURCE) {
            Ok(points) => prop_assert!(points.iter().all(|p| p.position.iter().all(|v| v.is_finite()))),
            Err(error) => prop_assert!(names_its_source(&error), "{error}"),
        }
        match control::parse_mark_observations(&marks, SOURCE) {
            Ok(marks) => prop_assert!(marks.iter().all(|m| m.pixel.x.is_finite() && m.pixel.y.is_finite())),
            Err(error) => prop_assert!(names_its_source(&error), "{error}"),
        }
        if let Err(error) = control::parse_check_ids(&marks, SOURCE) {
            prop_assert!(names_its_source(&error), "{error}");
        }
    }

    #[test]
    fn images(bytes in image_input()) {
        match image::decode_image(&bytes, SOURCE) {
            Ok(decoded) => {
                let samples = match decoded.pixels() {
                    crate::photogrammetry::GreyPixels::Eight(p) => p.len(),
                    crate::photogrammetry::GreyPixels::Sixteen(p) => p.len(),
                };
                prop_assert_eq!(samples as u64, decoded.width() as u64 * decoded.height() as u64);
                prop_assert!(decoded.width() <= crate::photogrammetry::MAX_SENSOR_SIDE);
                prop_assert!(samples as u64 <= crate::photogrammetry::MAX_SENSOR_PIXELS);
            }
            Err(error) => prop_assert!(names_its_source(&error), "{error}"),
        }
    }
}

#[test]
fn mutations_reach_every_kind_of_edit() {
    // The generator is what makes the properties worth running: check that
    // each edit changes a document the way it says.
    let seed = b"line one\nline two\n";
    assert_eq!(mutate(seed, &[Mutation::Truncate(0.5)]), b"line one\n");
    assert_eq!(mutate(seed, &[Mutation::Flip(0.0, b'L')])[0], b'L');
    assert!(mutate(seed, &[Mutation::Insert(0.0, 0)]).starts_with(b"NaN"));
    assert_eq!(
        mutate(seed, &[Mutation::Delete(0.0, 5)]),
        b"one\nline two\n"
    );
    assert_eq!(
        mutate(seed, &[Mutation::RepeatLine(0.0)]),
        b"line one\nline one\nline two\n\n"
    );
}

// --- An uploaded experiment (issue 29) ------------------------------------
//
// The importer reading an uploaded set ([`experiment::UploadedFiles`]) with
// hostile names where the experiment's files name other files (`cal_ori`'s
// `.ori` files, pyptv's `img_ori` and `mask_base_name`), hostile part
// names, and mutated contents in any of its files. Planted on this machine
// are a file holding a secret and a valid `.ori` with a position no
// experiment has; names point at them (absolute, through `..`), at
// `/proc/self/environ` and `/etc/passwd`. What must hold: the importer
// returns; nothing outside the set is read (the secret, this process's
// environment and the planted camera never show, in an error or in what is
// imported); a name that is absolute or has `..` is refused, never missing;
// a refusal names its file, line and name.

use super::experiment::{self, ExperimentError, ExperimentFiles, UploadedFiles};

const RECORDING: &[(&str, &str)] = &[
    (
        "parameters/ptv.par",
        include_str!("../../tests/data/openptv/test_cavity_recording/parameters/ptv.par"),
    ),
    (
        "parameters/criteria.par",
        include_str!("../../tests/data/openptv/test_cavity_recording/parameters/criteria.par"),
    ),
    (
        "parameters/targ_rec.par",
        include_str!("../../tests/data/openptv/test_cavity_recording/parameters/targ_rec.par"),
    ),
    (
        "parameters/sequence.par",
        include_str!("../../tests/data/openptv/test_cavity_recording/parameters/sequence.par"),
    ),
    (
        "parameters/cal_ori.par",
        include_str!("../../tests/data/openptv/test_cavity_recording/parameters/cal_ori.par"),
    ),
    (
        "parameters/track.par",
        include_str!("../../tests/data/openptv/test_cavity_recording/parameters/track.par"),
    ),
];
const RECORDING_YAML: &str =
    include_str!("../../tests/data/openptv/test_cavity_recording/parameters_Run1.yaml");
const RECORDING_CAL: &[(&str, &str)] = &[
    (
        "cal/cam1.tif.ori",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam1.tif.ori"),
    ),
    (
        "cal/cam1.tif.addpar",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam1.tif.addpar"),
    ),
    (
        "cal/cam2.tif.ori",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam2.tif.ori"),
    ),
    (
        "cal/cam2.tif.addpar",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam2.tif.addpar"),
    ),
    (
        "cal/cam3.tif.ori",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam3.tif.ori"),
    ),
    (
        "cal/cam3.tif.addpar",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam3.tif.addpar"),
    ),
    (
        "cal/cam4.tif.ori",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam4.tif.ori"),
    ),
    (
        "cal/cam4.tif.addpar",
        include_str!("../../tests/data/openptv/test_cavity_recording/cal/cam4.tif.addpar"),
    ),
];

/// The secret a planted file holds.
const PLANTED_SECRET: &str = "PLANTED-SECRET-5c0f9e1d";
/// X0 of the planted `.ori` (no experiment's camera is there).
const PLANTED_X0: f64 = 4242.4242;

/// The planted files' directory (made once): `secret` and `cam1.tif.ori`.
fn planted() -> &'static std::path::Path {
    static DIR: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().expect("a temporary directory");
        std::fs::write(dir.path().join("secret"), format!("{PLANTED_SECRET} 1 2\n")).unwrap();
        let ori = RECORDING_CAL[0]
            .1
            .replacen("80.9960491", &PLANTED_X0.to_string(), 1);
        assert!(ori.contains(&PLANTED_X0.to_string()));
        std::fs::write(dir.path().join("cam1.tif.ori"), ori).unwrap();
        std::fs::write(dir.path().join("mask.1"), PLANTED_SECRET).unwrap();
        dir
    })
    .path()
}

/// A path segment: plain, `.`, `..`, empty, unicode, NUL, long.
fn segment() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("..".to_owned()),
        Just(".".to_owned()),
        Just(String::new()),
        Just("cal".to_owned()),
        Just("cam1.tif.ori".to_owned()),
        Just("parameters".to_owned()),
        Just("ptv.par".to_owned()),
        Just("\0".to_owned()),
        Just("kamera-ü-相机".to_owned()),
        Just("x".repeat(300)),
        "[a-z0-9._-]{1,12}",
        "\\PC{1,6}",
    ]
}

/// A name an attacker writes where the experiment names a file.
fn hostile_name() -> impl Strategy<Value = String> {
    let planted = planted().display().to_string();
    prop_oneof![
        3 => prop_oneof![
            Just(format!("{planted}/secret")),
            Just(format!("{planted}/cam1.tif.ori")),
            Just(format!("{planted}/./cal/../cam1.tif.ori")),
            Just("/proc/self/environ".to_owned()),
            Just("/proc/self/cmdline".to_owned()),
            Just("/etc/passwd".to_owned()),
            Just(format!("{}{planted}/cam1.tif.ori", "../".repeat(12))),
            Just("cal/../../../../../../etc/passwd".to_owned()),
            Just("cal/cam1.tif.ori".to_owned()),
            Just("cal/cam9.tif.ori".to_owned()),
        ],
        3 => (any::<bool>(), prop::collection::vec(segment(), 1..7)).prop_map(|(absolute, parts)| {
            format!("{}{}", if absolute { "/" } else { "" }, parts.join("/"))
        }),
        1 => ".{0,40}",
        1 => Just("a/".repeat(400)),
    ]
}

/// A YAML single-quoted scalar.
fn yaml_quoted(text: &str) -> String {
    format!("'{}'", text.replace('\'', "''"))
}

/// Whether `name` is absolute or has a `..` component.
fn escapes(name: &str) -> bool {
    name.starts_with('/') || name.split('/').any(|part| part == "..")
}

/// One hostile case: which form, names written in the files, parts'
/// names, and mutations of one file.
#[derive(Clone, Debug)]
struct HostileUpload {
    yaml: bool,
    /// Per camera 0..4, a name replacing its `.ori`'s (none: kept).
    oris: Vec<Option<String>>,
    /// pyptv's masking on, with this `mask_base_name` (YAML form only).
    mask: Option<String>,
    /// Extra parts, named so, holding the planted `.ori`'s text.
    extra_parts: Vec<String>,
    /// Which file to mutate (an index into the upload) and how.
    mutated: Option<(usize, Vec<Mutation>)>,
}

fn hostile_upload() -> impl Strategy<Value = HostileUpload> {
    (
        any::<bool>(),
        prop::collection::vec(prop::option::weighted(0.4, hostile_name()), 4),
        prop::option::of(hostile_name()),
        prop::collection::vec(hostile_name(), 0..3),
        prop::option::weighted(0.4, (0usize..16, prop::collection::vec(mutation(), 1..8))),
    )
        .prop_map(|(yaml, oris, mask, extra_parts, mutated)| HostileUpload {
            yaml,
            oris,
            mask,
            extra_parts,
            mutated,
        })
}

impl HostileUpload {
    /// The parts (path, bytes) as a client would send them.
    fn parts(&self) -> Vec<(String, Vec<u8>)> {
        let mut parts: Vec<(String, Vec<u8>)> = Vec::new();
        if self.yaml {
            let mut yaml = RECORDING_YAML.to_owned();
            for (k, name) in self.oris.iter().enumerate() {
                if let Some(name) = name {
                    let line = format!("  - cal/cam{}.tif.ori\n", k + 1);
                    yaml = yaml.replacen(&line, &format!("  - {}\n", yaml_quoted(name)), 1);
                }
            }
            if let Some(mask) = &self.mask {
                yaml = yaml
                    .replacen("mask_flag: false", "mask_flag: true", 1)
                    .replacen(
                        "mask_base_name: ''",
                        &format!("mask_base_name: {}", yaml_quoted(mask)),
                        1,
                    );
            }
            parts.push(("parameters_Run1.yaml".to_owned(), yaml.into_bytes()));
        } else {
            for (path, text) in RECORDING {
                let mut text = (*text).to_owned();
                if *path == "parameters/cal_ori.par" {
                    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
                    for (k, name) in self.oris.iter().enumerate() {
                        if let Some(name) = name {
                            // A line holds one name: what follows a line
                            // break would be the next line's.
                            lines[2 + 2 * k] = name.replace(['\n', '\r'], " ");
                        }
                    }
                    text = lines.join("\n") + "\n";
                }
                parts.push(((*path).to_owned(), text.into_bytes()));
            }
        }
        for (path, text) in RECORDING_CAL {
            parts.push(((*path).to_owned(), text.as_bytes().to_vec()));
        }
        let planted_ori = std::fs::read(planted().join("cam1.tif.ori")).unwrap();
        for name in &self.extra_parts {
            parts.push((name.clone(), planted_ori.clone()));
        }
        if let Some((index, mutations)) = &self.mutated {
            let index = index % parts.len();
            parts[index].1 = mutate(&parts[index].1, mutations);
        }
        parts
    }
}

/// This process's environment as `NAME=value` texts worth finding (values
/// of 6 bytes or more).
fn environment() -> &'static [String] {
    static VARS: std::sync::OnceLock<Vec<String>> = std::sync::OnceLock::new();
    VARS.get_or_init(|| {
        std::env::vars()
            .filter(|(_, value)| value.len() >= 6)
            .map(|(name, value)| format!("{name}={value}"))
            .collect()
    })
}

proptest! {
    #[test]
    fn an_uploaded_experiment_reads_nothing_outside_its_files(upload in hostile_upload()) {
        let mut files = UploadedFiles::new();
        let parts = upload.parts();
        let extras_from = parts.len() - upload.extra_parts.len();
        let mut sent_planted = false;
        for (index, (name, bytes)) in parts.into_iter().enumerate() {
            // The service refuses such a part (400) before the importer runs.
            let added = files.insert_bytes(&name, bytes).unwrap_or(false);
            sent_planted |= added && index >= extras_from;
        }
        match experiment::read_experiment_from(&files, std::path::Path::new("")) {
            Ok(imported) => {
                for camera in &imported.cameras {
                    let x0 = camera.parameters().exterior.position.x;
                    // The planted camera may come only from a part sent.
                    prop_assert!(x0 != PLANTED_X0 || sent_planted, "the planted .ori was imported");
                }
                for mask in imported.masks.iter().flatten() {
                    prop_assert!(files.is_file(mask), "mask {} is not in the set", mask.display());
                }
            }
            Err(error) => {
                let message = error.to_string();
                prop_assert!(!message.contains(PLANTED_SECRET), "{message}");
                prop_assert!(!message.contains("root:x:0:0"), "{message}");
                prop_assert!(!message.contains(&planted().display().to_string()) || message.contains("names `"),
                    "a planted path shows other than as the name written: {message}");
                for var in environment() {
                    prop_assert!(!message.contains(var.as_str()), "the environment shows: {message}");
                }
                match &error {
                    ExperimentError::Refused { location, name, .. } => {
                        prop_assert!(location.starts_with("line "), "{message}");
                        prop_assert!(message.contains(&format!("`{}`", name.escape_debug())), "{message}");
                    }
                    ExperimentError::Missing { missing, .. } => {
                        let missing = missing.to_str().unwrap_or_default();
                        prop_assert!(!escapes(missing) && UploadedFiles::key(missing).is_ok(),
                            "an escaping name counted as missing: {message}");
                    }
                    _ => {}
                }
            }
        }
    }
}

#[test]
fn escaping_names_in_each_place_are_refused_with_file_line_and_name() {
    let planted = planted().display().to_string();
    for name in [
        "/proc/self/environ".to_owned(),
        format!("{planted}/cam1.tif.ori"),
        "../../etc/passwd".to_owned(),
        "cal/../cal/cam1.tif.ori".to_owned(),
    ] {
        for (yaml, mask) in [(false, false), (true, false), (true, true)] {
            let upload = HostileUpload {
                yaml,
                oris: vec![(!mask).then(|| name.clone()), None, None, None],
                mask: mask.then(|| name.clone()),
                extra_parts: Vec::new(),
                mutated: None,
            };
            let mut files = UploadedFiles::new();
            for (path, bytes) in upload.parts() {
                assert!(files.insert_bytes(&path, bytes).unwrap());
            }
            let error = experiment::read_experiment_from(&files, std::path::Path::new(""))
                .expect_err("refused");
            let message = error.to_string();
            assert!(
                matches!(error, ExperimentError::Refused { .. }),
                "{message}"
            );
            let (file, key) = match (yaml, mask) {
                (false, _) => (
                    "parameters/cal_ori.par: line 3, cal_ori.img_ori[0]",
                    name.clone(),
                ),
                (true, false) => (
                    "parameters_Run1.yaml: line 22, cal_ori.img_ori[0]",
                    name.clone(),
                ),
                (true, true) => (
                    "parameters_Run1.yaml: line 228, masking.mask_base_name",
                    format!("{name}.1"),
                ),
            };
            assert!(message.starts_with(file), "{message}");
            assert!(message.contains(&format!("`{key}`")), "{message}");
            assert!(!message.contains(PLANTED_SECRET));
        }
    }
}

#[test]
fn a_key_given_twice_where_the_sections_ignore_it_is_an_error_not_a_panic() {
    // The sections skip `plugins`; the whole value refuses the duplicate
    // (this was an `expect`: a panic, and a 500 from the service).
    let yaml = RECORDING_YAML.replacen(
        "  selected_tracking: default\n",
        "  selected_tracking: default\n  selected_tracking: other\n",
        1,
    );
    assert_ne!(yaml, RECORDING_YAML);
    let mut files = UploadedFiles::new();
    files
        .insert_bytes("parameters_Run1.yaml", yaml.into_bytes())
        .unwrap();
    for (path, text) in RECORDING_CAL {
        files.insert_bytes(path, text.as_bytes().to_vec()).unwrap();
    }
    let error = experiment::read_experiment_from(&files, std::path::Path::new(""))
        .unwrap_err()
        .to_string();
    assert!(
        error.starts_with("parameters_Run1.yaml: line ") && error.contains("duplicate"),
        "{error}"
    );
}

#[test]
fn yaml_aliases_expand_within_the_item_limit_or_are_refused() {
    let refused = |yaml: String| {
        let mut files = UploadedFiles::new();
        files
            .insert_bytes("parameters_Run1.yaml", yaml.into_bytes())
            .unwrap();
        let started = std::time::Instant::now();
        let error = experiment::read_experiment_from(&files, std::path::Path::new(""))
            .unwrap_err()
            .to_string();
        // Refused by the walk, not after expanding 25M items (seconds, GiB).
        assert!(started.elapsed() < std::time::Duration::from_secs(2));
        error
    };
    let bomb = format!(
        "a: &a [{}1]\nb: [{}*a]\n",
        "1,".repeat(5_000),
        "*a,".repeat(5_000)
    );
    let error = refused(bomb);
    assert!(error.contains("more than 32768 items"), "{error}");
    // Hidden in a tagged value, and in a section the importer ignores.
    let bomb = format!(
        "a: &a [{}1]\nplugins: !x [{}*a]\n",
        "1,".repeat(5_000),
        "*a,".repeat(5_000)
    );
    let error = refused(bomb);
    assert!(error.contains("more than 32768 items"), "{error}");
    // Within the limits the sections are read as ever.
    let small = RECORDING_YAML.replacen(
        "plugins:\n",
        "anchors: &a [1, 2]\nmore: [*a, *a]\nplugins:\n",
        1,
    );
    let error = refused(small);
    assert!(error.contains("cal/cam1.tif.ori"), "{error}");
}
