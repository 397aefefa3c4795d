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
