//! The project's calibration JSON.
//!
//! ```json
//! {"cameras": [{"name": "cam1", "image_size": [1280, 1024], "pixel_size": [0.012, 0.012],
//!   "position": [X0, Y0, Z0], "angles": [omega, phi, kappa], "principal_distance": c,
//!   "principal_point": [xh, yh], "radial": [k1, k2, k3], "decentering": [p1, p2],
//!   "affine": [scx, shear],
//!   "media": {"n_air": 1.0, "walls": [{"n": 1.49, "thickness": 10.0}], "n_object": 1.33,
//!             "glass_vector": [0, 0, 100]}}]}
//! ```
//!
//! Lengths in mm, angles in rad, pixel coordinates as in [`crate::photogrammetry::camera`].
//! Walls are listed from the water outward, the first starting at the glass
//! vector's plane. Every camera needs its sensor (`image_size`,
//! `pixel_size`) and `media` (at least `n_object`). The orientation
//! (`position`, `angles`, `principal_distance`) is required in a
//! calibration ([`from_json`]) but may be left out of a setup
//! ([`setup_from_json`]: `ptv calibrate --calibration`, the `setup` part of
//! `/calibrations/solve`), whose orientation the calibration solves,
//! starting from the DLT. Optional fields and their defaults: `name` (`camN`),
//! `principal_point` (0, 0), `radial` (0, 0, 0), `decentering` (0, 0),
//! `affine` (1, 0), `media.n_air` (1), `media.walls` (none),
//! `media.glass_vector` (0, 0, 0; required when the media refract). Unknown
//! fields are errors, so that a typo never silently falls back to a default.
//!
//! An optional top-level `"splitter": {"layout": "quadrants"}` (or
//! `left_right`, `top_bottom`) says that the cameras are views of one
//! sensor ([`crate::photogrammetry::splitter`]): each camera's `image_size`
//! is its view's, and it has as many cameras as the layout has views.
//! Absent, every camera has its own sensor. [`from_json`] reads the cameras
//! alone; [`from_json_with_splitter`] also the splitter, checked.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::FormatError;
use crate::photogrammetry::calibrate::{setup_field, Parameter, ParameterSet};
use crate::photogrammetry::{
    check_camera_name, Camera, CameraParameters, Distortion, Exterior, Interior, Media, Sensor,
    Splitter, Wall,
};

/// The fewest cameras a calibration may have: a point needs two rays.
pub const MIN_CAMERAS: usize = 2;

/// The most cameras a calibration may have: 16, the core's
/// [`MAX_CAMERAS`](crate::photogrammetry::correspond::MAX_CAMERAS) (rigs
/// have 2..8 cameras; twice that leaves margin). The JSON list is cut off
/// while it is read, so a document of 10,000 cameras is refused after
/// the 17th, without holding the rest.
pub const MAX_CAMERAS: usize = crate::photogrammetry::correspond::MAX_CAMERAS;

/// The calibration JSON document (a calibration, or a calibration setup).
/// Its schema (utoipa) documents the format for the service's OpenAPI
/// document; the same structs parse it, so the two cannot disagree.
#[derive(Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(
    as = CalibrationDocument,
    description = "A rig's calibration JSON. As a calibration (POST /calibrations, stored calibrations) every camera gives its orientation (position, angles, principal_distance). As a setup (the `setup` part of POST /calibrations/solve, `ptv calibrate --calibration`) only the sensor (image_size, pixel_size) and media are needed: the orientation is solved from the control points, starting from the DLT; orientation values given are used for fixed parameters and, with images and no reference points, to identify the marks."
)]
pub struct CalibrationFile {
    /// The cameras, 2 to 16, in camera order.
    #[serde(deserialize_with = "bounded_cameras")]
    #[schema(min_items = 2, max_items = 16)]
    cameras: Vec<CameraJson>,
    /// Optional: the cameras are views of one sensor through an image
    /// splitter, `{"layout": "quadrants" | "left_right" | "top_bottom"}`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    splitter: Option<Splitter>,
}

/// Reads the cameras' list, refusing it as soon as it holds more than
/// [`MAX_CAMERAS`].
fn bounded_cameras<'de, D>(deserializer: D) -> Result<Vec<CameraJson>, D::Error>
where
    D: serde::Deserializer<'de>,
{
    struct Bounded;
    impl<'de> serde::de::Visitor<'de> for Bounded {
        type Value = Vec<CameraJson>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            write!(f, "a list of {MIN_CAMERAS} to {MAX_CAMERAS} cameras")
        }
        fn visit_seq<A: serde::de::SeqAccess<'de>>(
            self,
            mut seq: A,
        ) -> Result<Self::Value, A::Error> {
            let mut cameras = Vec::new();
            while let Some(camera) = seq.next_element()? {
                if cameras.len() == MAX_CAMERAS {
                    return Err(serde::de::Error::custom(too_many_cameras(format!(
                        "more than {MAX_CAMERAS}"
                    ))));
                }
                cameras.push(camera);
            }
            Ok(cameras)
        }
    }
    deserializer.deserialize_seq(Bounded)
}

fn too_many_cameras(got: impl std::fmt::Display) -> String {
    format!(
        "a calibration has at most {MAX_CAMERAS} cameras (MAX_CAMERAS), got {got}; give one \
         entry per physical camera of the rig"
    )
}

/// One camera of the calibration JSON.
#[derive(Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = CalibrationCamera)]
pub struct CameraJson {
    /// Optional: the camera's name, 1 to 64 characters usable in a file
    /// name [default: camN, N from 1].
    #[serde(default)]
    name: Option<String>,
    // The sensor and the media are required; they are options here only so
    // that a missing one gets a message saying what a camera needs.
    /// Required: the sensor's size, [width, height] in pixels.
    #[serde(default)]
    #[schema(required = true, value_type = Vec<u32>, min_items = 2, max_items = 2)]
    image_size: Option<[u32; 2]>,
    /// Required: the pixel pitch, [x, y] in mm.
    #[serde(default)]
    #[schema(required = true, value_type = Vec<f64>, min_items = 2, max_items = 2)]
    pixel_size: Option<[f64; 2]>,
    // The orientation: required in a calibration, optional in a setup.
    /// Required in a calibration, optional in a setup: the projection
    /// centre [X0, Y0, Z0] (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 3, max_items = 3)]
    position: Option<[f64; 3]>,
    /// Required in a calibration, optional in a setup: [omega, phi, kappa]
    /// (rad).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 3, max_items = 3)]
    angles: Option<[f64; 3]>,
    /// Required in a calibration, optional in a setup: c (mm, positive).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    principal_distance: Option<f64>,
    /// Optional: [xh, yh] (mm) [default: 0, 0, the sensor's centre].
    #[serde(default)]
    #[schema(value_type = Vec<f64>, min_items = 2, max_items = 2)]
    principal_point: [f64; 2],
    /// Optional: radial distortion [k1, k2, k3] [default: 0, 0, 0].
    #[serde(default)]
    #[schema(value_type = Vec<f64>, min_items = 3, max_items = 3)]
    radial: [f64; 3],
    /// Optional: decentering distortion [p1, p2] [default: 0, 0].
    #[serde(default)]
    #[schema(value_type = Vec<f64>, min_items = 2, max_items = 2)]
    decentering: [f64; 2],
    /// Optional: [scx, shear] [default: 1, 0].
    #[serde(default = "identity_affine")]
    #[schema(value_type = Vec<f64>, min_items = 2, max_items = 2)]
    affine: [f64; 2],
    /// Required: the refracting media between the camera and the object.
    #[serde(default)]
    #[schema(required = true, value_type = MediaJson)]
    media: Option<MediaJson>,
}

fn identity_affine() -> [f64; 2] {
    [1.0, 0.0]
}

fn one() -> f64 {
    1.0
}

/// The media of a camera.
#[derive(Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = CalibrationMedia)]
pub struct MediaJson {
    /// Optional: the refractive index on the camera's side [default: 1].
    #[serde(default = "one")]
    n_air: f64,
    /// Optional: the walls, from the object outward [default: none].
    #[serde(default)]
    walls: Vec<WallJson>,
    /// Required: the refractive index of the object's medium (1 in air).
    n_object: f64,
    /// Optional: the vector from the origin to the nearest wall's plane,
    /// normal to it (mm) [default: 0, 0, 0; required when the media
    /// refract].
    #[serde(default)]
    #[schema(value_type = Vec<f64>, min_items = 3, max_items = 3)]
    glass_vector: [f64; 3],
}

/// A wall of the media.
#[derive(Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = CalibrationWall)]
pub struct WallJson {
    /// Required: its refractive index.
    n: f64,
    /// Required: its thickness (mm).
    thickness: f64,
}

impl CameraJson {
    /// The camera's parameters, with placeholders (zeros) for the
    /// orientation the document leaves out, and which parameters those are.
    fn into_parameters(
        self,
        index: usize,
        source: &str,
    ) -> Result<(CameraParameters, ParameterSet), FormatError> {
        let missing = |field: &str, what: &str| {
            FormatError::invalid(
                source,
                format!("cameras[{index}].{field}"),
                format!(
                    "missing: every camera needs its sensor and media ({what}); the \
                     orientation (position, angles, principal_distance) may be left out of a \
                     setup"
                ),
            )
        };
        let image_size = self
            .image_size
            .ok_or_else(|| missing("image_size", "image_size: [width, height] in pixels"))?;
        let pixel_size = self
            .pixel_size
            .ok_or_else(|| missing("pixel_size", "pixel_size: [x, y] in mm"))?;
        let media = self.media.ok_or_else(|| {
            missing(
                "media",
                "media: at least {\"n_object\": n}, with walls and glass_vector if they refract",
            )
        })?;
        let mut unknown = ParameterSet::empty();
        if self.position.is_none() {
            unknown = unknown | ParameterSet::position();
        }
        if self.angles.is_none() {
            unknown = unknown | ParameterSet::rotation();
        }
        if self.principal_distance.is_none() {
            unknown.insert(Parameter::C);
        }
        let position = self.position.unwrap_or_default();
        let angles = self.angles.unwrap_or_default();
        let parameters = CameraParameters {
            name: self.name.unwrap_or_else(|| format!("cam{}", index + 1)),
            sensor: Sensor {
                width: image_size[0],
                height: image_size[1],
                pixel_size_x: pixel_size[0],
                pixel_size_y: pixel_size[1],
            },
            exterior: Exterior {
                position: Vector3::from(position),
                omega: angles[0],
                phi: angles[1],
                kappa: angles[2],
            },
            interior: Interior {
                c: self.principal_distance.unwrap_or_default(),
                xh: self.principal_point[0],
                yh: self.principal_point[1],
            },
            distortion: Distortion {
                k1: self.radial[0],
                k2: self.radial[1],
                k3: self.radial[2],
                p1: self.decentering[0],
                p2: self.decentering[1],
                scx: self.affine[0],
                shear: self.affine[1],
            },
            media: Media {
                n_air: media.n_air,
                walls: media
                    .walls
                    .into_iter()
                    .map(|w| Wall {
                        n: w.n,
                        thickness: w.thickness,
                    })
                    .collect(),
                n_object: media.n_object,
                glass_vector: Vector3::from(media.glass_vector),
            },
        };
        Ok((parameters, unknown))
    }

    fn from_parameters(p: &CameraParameters) -> CameraJson {
        CameraJson {
            name: Some(p.name.clone()),
            image_size: Some([p.sensor.width, p.sensor.height]),
            pixel_size: Some([p.sensor.pixel_size_x, p.sensor.pixel_size_y]),
            position: Some(p.exterior.position.into()),
            angles: Some([p.exterior.omega, p.exterior.phi, p.exterior.kappa]),
            principal_distance: Some(p.interior.c),
            principal_point: [p.interior.xh, p.interior.yh],
            radial: [p.distortion.k1, p.distortion.k2, p.distortion.k3],
            decentering: [p.distortion.p1, p.distortion.p2],
            affine: [p.distortion.scx, p.distortion.shear],
            media: Some(MediaJson {
                n_air: p.media.n_air,
                walls: p
                    .media
                    .walls
                    .iter()
                    .map(|w| WallJson {
                        n: w.n,
                        thickness: w.thickness,
                    })
                    .collect(),
                n_object: p.media.n_object,
                glass_vector: p.media.glass_vector.into(),
            }),
        }
    }
}

/// Parses and validates a calibration JSON document: every camera's
/// orientation must be given.
pub fn from_json(text: &str, source: &str) -> Result<Vec<Camera>, FormatError> {
    from_parameters(oriented(setup_from_json(text, source)?, source)?, source)
}

/// A calibration setup: the cameras' parameters, and per camera which of
/// them the document leaves out (the orientation: `position`, `angles`,
/// `principal_distance`), whose values are placeholders (zeros). Pass
/// `unknown` as [`CalibrationOptions::unknown`](crate::photogrammetry::calibrate::CalibrationOptions::unknown).
#[derive(Clone, Debug, PartialEq)]
pub struct Setup {
    /// The cameras, in the document's order.
    pub cameras: Vec<CameraParameters>,
    /// Per camera, the parameters the document leaves out.
    pub unknown: Vec<ParameterSet>,
}

/// The cameras of a setup whose orientation is complete; else an error
/// naming the first missing field.
fn oriented(setup: Setup, source: &str) -> Result<Vec<CameraParameters>, FormatError> {
    for (i, unknown) in setup.unknown.iter().enumerate() {
        if let Some(parameter) = unknown.iter().next() {
            return Err(FormatError::invalid(
                source,
                format!("cameras[{i}].{}", setup_field(parameter)),
                "missing: a calibration gives every camera's orientation (position, angles, \
                 principal_distance); only a setup (`ptv calibrate --calibration`, the `setup` \
                 part of /calibrations/solve) may leave it out, to be solved"
                    .to_owned(),
            ));
        }
    }
    Ok(setup.cameras)
}

/// Parses and validates a calibration JSON document and its splitter, if
/// any: the splitter's views must be the cameras, all of one size.
pub fn from_json_with_splitter(
    text: &str,
    source: &str,
) -> Result<(Vec<Camera>, Option<Splitter>), FormatError> {
    with_splitter(text, source, Ranges::Physical)
}

/// [`from_json_with_splitter`] for a calibration the service stored
/// itself: checked as a rig (what the model needs to compute, the
/// splitter) but not against [`CameraParameters::check_physical`]'s
/// ranges, which are checked when a calibration comes in (a request, a
/// file, a solve): a calibration stored before those checks existed, or
/// before a range was narrowed, still loads, and its sequences keep
/// working. Stored data is never refused for a rule it was not stored
/// under.
pub fn stored_from_json_with_splitter(
    text: &str,
    source: &str,
) -> Result<(Vec<Camera>, Option<Splitter>), FormatError> {
    with_splitter(text, source, Ranges::Unchecked)
}

/// Whether a calibration's values are checked against the ranges real
/// cameras have.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Ranges {
    /// Input: [`CameraParameters::check_physical`].
    Physical,
    /// Stored by the service: only [`Camera::new`]'s checks.
    Unchecked,
}

fn with_splitter(
    text: &str,
    source: &str,
    ranges: Ranges,
) -> Result<(Vec<Camera>, Option<Splitter>), FormatError> {
    let file = parse_file(text, source)?;
    let splitter = file.splitter;
    let cameras = checked_parameters(
        oriented(camera_parameters(file, source)?, source)?,
        source,
        ranges,
    )?;
    if let Some(splitter) = splitter {
        if splitter.views() != cameras.len() {
            return Err(FormatError::invalid(
                source,
                "splitter.layout",
                format!(
                    "the {} layout has {} views but the calibration has {} cameras; give one \
                     camera per view, in the layout's order",
                    splitter.name(),
                    splitter.views(),
                    cameras.len()
                ),
            ));
        }
        let first = cameras[0].sensor();
        if let Some((i, other)) = cameras
            .iter()
            .enumerate()
            .find(|(_, c)| (c.sensor().width, c.sensor().height) != (first.width, first.height))
        {
            return Err(FormatError::invalid(
                source,
                format!("cameras[{i}].image_size"),
                format!(
                    "is {}x{} but camera 0's is {}x{}; a splitter's views are all of one size",
                    other.sensor().width,
                    other.sensor().height,
                    first.width,
                    first.height
                ),
            ));
        }
    }
    Ok((cameras, splitter))
}

/// Parses a calibration JSON document into plain parameters without
/// validating them as cameras: for a calibration setup, whose orientation
/// values are only optional starting values. Orientation the document
/// leaves out is zeros: use [`setup_from_json`] to know which.
pub fn parameters_from_json(
    text: &str,
    source: &str,
) -> Result<Vec<CameraParameters>, FormatError> {
    Ok(setup_from_json(text, source)?.cameras)
}

/// Parses a calibration setup: sensor and media required, orientation
/// optional (see [`Setup`]); not validated as cameras.
pub fn setup_from_json(text: &str, source: &str) -> Result<Setup, FormatError> {
    camera_parameters(parse_file(text, source)?, source)
}

fn parse_file(text: &str, source: &str) -> Result<CalibrationFile, FormatError> {
    let deserializer = &mut serde_json::Deserializer::from_str(text);
    let file: CalibrationFile = serde_path_to_error::deserialize(deserializer).map_err(|err| {
        let path = err.path().to_string();
        let location = if path == "." {
            "document".to_owned()
        } else {
            path
        };
        FormatError::invalid(source, location, err.into_inner().to_string())
    })?;
    Ok(file)
}

fn camera_parameters(file: CalibrationFile, source: &str) -> Result<Setup, FormatError> {
    let (parameters, unknown): (Vec<CameraParameters>, Vec<ParameterSet>) = file
        .cameras
        .into_iter()
        .enumerate()
        .map(|(i, camera)| camera.into_parameters(i, source))
        .collect::<Result<Vec<_>, _>>()?
        .into_iter()
        .unzip();
    // A setup's cameras are not validated as cameras (their orientation is
    // only a start), but their names become file names all the same.
    for (i, p) in parameters.iter().enumerate() {
        check_camera_name(&p.name).map_err(|e| {
            FormatError::invalid(source, format!("cameras[{i}].{}", e.field), e.reason)
        })?;
    }
    Ok(Setup {
        cameras: parameters,
        unknown,
    })
}

/// Validates a list of camera parameters as a calibration:
/// [`MIN_CAMERAS`]..=[`MAX_CAMERAS`] cameras, each one valid, its values
/// within the ranges real cameras have
/// ([`CameraParameters::check_physical`]; the error names the camera, the
/// field, the value and the range). Every calibration read from a file or
/// a request comes through here (the JSON, the OpenPTV import, an
/// experiment's), for the service and the command line alike.
pub fn from_parameters(
    parameters: Vec<CameraParameters>,
    source: &str,
) -> Result<Vec<Camera>, FormatError> {
    checked_parameters(parameters, source, Ranges::Physical)
}

fn checked_parameters(
    parameters: Vec<CameraParameters>,
    source: &str,
    ranges: Ranges,
) -> Result<Vec<Camera>, FormatError> {
    if parameters.len() > MAX_CAMERAS {
        return Err(FormatError::invalid(
            source,
            "cameras",
            too_many_cameras(parameters.len()),
        ));
    }
    if parameters.len() < MIN_CAMERAS {
        return Err(FormatError::invalid(
            source,
            "cameras",
            format!(
                "a calibration needs at least {MIN_CAMERAS} cameras, got {}",
                parameters.len()
            ),
        ));
    }
    parameters
        .into_iter()
        .enumerate()
        .map(|(i, p)| {
            // The camera's name in the message, where it is a name.
            let label = match check_camera_name(&p.name) {
                Ok(()) => format!("camera `{}`: ", p.name),
                Err(_) => String::new(),
            };
            Camera::new(p)
                .and_then(|camera| match ranges {
                    Ranges::Physical => camera.parameters().check_physical().map(|()| camera),
                    Ranges::Unchecked => Ok(camera),
                })
                .map_err(|e| {
                    FormatError::invalid(
                        source,
                        format!("cameras[{i}].{}", e.field),
                        format!("{label}{}", e.reason),
                    )
                })
        })
        .collect()
}

/// Serialises cameras as calibration JSON (pretty-printed, every field
/// written, numbers in their shortest exact form).
pub fn to_json(cameras: &[Camera]) -> String {
    to_json_with_splitter(cameras, None)
}

/// Serialises cameras and their splitter, if any, as calibration JSON.
pub fn to_json_with_splitter(cameras: &[Camera], splitter: Option<Splitter>) -> String {
    let file = CalibrationFile {
        cameras: cameras
            .iter()
            .map(|c| CameraJson::from_parameters(c.parameters()))
            .collect(),
        splitter,
    };
    serde_json::to_string_pretty(&file).expect("plain data serialises") + "\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    const TWO_CAMERAS: &str = r#"{"cameras": [
        {"name": "a", "image_size": [1280, 1024], "pixel_size": [0.012, 0.012],
         "position": [0, 0, 600], "angles": [0, 0, 0], "principal_distance": 50,
         "media": {"walls": [{"n": 1.5, "thickness": 10}], "n_object": 1.33, "glass_vector": [0, 0, 100]}},
        {"image_size": [1280, 1024], "pixel_size": [0.012, 0.012],
         "position": [300, 0, 520], "angles": [0, 0.5, 0], "principal_distance": 50,
         "radial": [1e-4, 0, 0], "affine": [1.001, 0.001],
         "media": {"walls": [{"n": 1.5, "thickness": 10}], "n_object": 1.33, "glass_vector": [0, 0, 100]}}
    ]}"#;

    fn error_of(text: &str) -> String {
        from_json(text, "cal.json").unwrap_err().to_string()
    }

    /// Issue 29: the physical ranges are checked on input only. A
    /// calibration the service stored before they existed (here a
    /// principal distance of 20 m, past the 10 m the range allows, which
    /// the model computes with) must still load from the store, or every
    /// sequence on it would fail; the same document as input is refused.
    #[test]
    fn stored_calibrations_load_without_the_input_ranges() {
        let old = TWO_CAMERAS.replacen(
            "\"principal_distance\": 50",
            "\"principal_distance\": 20000",
            1,
        );
        assert_ne!(old, TWO_CAMERAS);
        let error = from_json_with_splitter(&old, "the body")
            .unwrap_err()
            .to_string();
        assert!(error.contains("principal_distance"), "{error}");
        let (cameras, splitter) = stored_from_json_with_splitter(&old, "the stored calibration")
            .expect("a stored calibration loads");
        assert_eq!(cameras.len(), 2);
        assert_eq!(cameras[0].parameters().interior.c, 20000.0);
        assert!(splitter.is_none());
        // What the model cannot compute with is refused even when stored.
        let broken =
            TWO_CAMERAS.replacen("\"principal_distance\": 50", "\"principal_distance\": 0", 1);
        assert!(stored_from_json_with_splitter(&broken, "the stored calibration").is_err());
    }

    #[test]
    fn reads_defaults_and_round_trips_exactly() {
        let cameras = from_json(TWO_CAMERAS, "cal.json").unwrap();
        assert_eq!(cameras[1].name(), "cam2");
        assert_eq!(cameras[0].parameters().distortion, Distortion::default());
        assert_eq!(cameras[0].parameters().media.n_air, 1.0);
        let again = from_json(&to_json(&cameras), "again").unwrap();
        assert_eq!(again, cameras);
    }

    #[test]
    fn unknown_field_is_named_with_its_path() {
        let text = TWO_CAMERAS.replace(
            "\"principal_distance\": 50,\n         \"radial\"",
            "\"principal_distanse\": 50, \"radial\"",
        );
        let message = error_of(&text);
        assert!(
            message.contains("cameras[1]") && message.contains("principal_distanse"),
            "{message}"
        );
    }

    #[test]
    fn missing_field_is_named() {
        let text = TWO_CAMERAS.replacen("\"pixel_size\": [0.012, 0.012],", "", 1);
        let message = error_of(&text);
        assert!(
            message.contains("cameras[0]") && message.contains("pixel_size"),
            "{message}"
        );
    }

    #[test]
    fn bad_values_are_named() {
        for (from, to, field) in [
            (
                "[0.012, 0.012]",
                "[0.012, -0.012]",
                "cameras[0].pixel_size[1]",
            ),
            ("\"n\": 1.5", "\"n\": 0", "cameras[0].media.walls[0].n"),
            (
                "\"principal_distance\": 50",
                "\"principal_distance\": 0",
                "cameras[0].principal_distance",
            ),
            ("[1280, 1024]", "[0, 1024]", "cameras[0].image_size[0]"),
            (
                "\"n_object\": 1.33",
                "\"n_object\": -1.33",
                "cameras[0].media.n_object",
            ),
            ("[0, 0, 600]", "[0, 0, 1e999]", "cameras[0].position"),
        ] {
            let message = error_of(&TWO_CAMERAS.replacen(from, to, 1));
            assert!(message.contains(field), "{field}: {message}");
        }
    }

    #[test]
    fn one_camera_is_not_a_calibration() {
        let one: serde_json::Value = serde_json::from_str(TWO_CAMERAS).unwrap();
        let text = serde_json::json!({"cameras": [one["cameras"][0].clone()]}).to_string();
        assert!(error_of(&text).contains("at least 2 cameras"));
    }

    /// A calibration of `count` copies of the first camera.
    fn cameras_json(count: usize) -> String {
        let two: serde_json::Value = serde_json::from_str(TWO_CAMERAS).unwrap();
        serde_json::json!({"cameras": vec![two["cameras"][0].clone(); count]}).to_string()
    }

    #[test]
    fn at_most_max_cameras() {
        assert_eq!(
            from_json(&cameras_json(MAX_CAMERAS), "x").unwrap().len(),
            16
        );
        for count in [MAX_CAMERAS + 1, 10_000] {
            let message = error_of(&cameras_json(count));
            assert!(
                message.starts_with(
                    "cal.json: cameras: a calibration has at most 16 cameras \
                                     (MAX_CAMERAS), got more than 16"
                ),
                "{message}"
            );
            let setup = parameters_from_json(&cameras_json(count), "setup.json").unwrap_err();
            assert!(setup.to_string().contains("MAX_CAMERAS"), "{setup}");
        }
        // Built in memory, the count is checked before the cameras.
        let parameters = parameters_from_json(&cameras_json(MAX_CAMERAS), "x").unwrap();
        let mut many = parameters.clone();
        many.push(parameters[0].clone());
        let message = from_parameters(many, "rig").unwrap_err().to_string();
        assert!(
            message.contains("at most 16 cameras (MAX_CAMERAS), got 17"),
            "{message}"
        );
    }

    #[test]
    fn hostile_camera_names_are_refused_at_parse_time() {
        for name in ["../../etc/passwd", "a/b", "cam\u{0}1", ".ori", ""] {
            let text = TWO_CAMERAS.replacen(
                "\"name\": \"a\"",
                &format!("\"name\": {}", serde_json::to_string(name).unwrap()),
                1,
            );
            let message = error_of(&text);
            assert!(
                message.starts_with("cal.json: cameras[0].name: the camera name")
                    && message.contains("1 to 64 characters"),
                "{name:?}: {message}"
            );
            // Setups too: their names name files just the same.
            let setup = parameters_from_json(&text, "setup.json").unwrap_err();
            assert!(setup.to_string().contains("cameras[0].name"), "{setup}");
        }
        let long = "n".repeat(1 << 20);
        let text = TWO_CAMERAS.replacen("\"name\": \"a\"", &format!("\"name\": {long:?}"), 1);
        assert!(error_of(&text).contains("1048576 bytes long, more than the limit of 64"));
    }

    #[test]
    fn not_json_is_an_error_not_a_panic() {
        for text in [
            "",
            "[]",
            "{\"cameras\": 3}",
            "NaN",
            "{\"cameras\": [{\"position\": [NaN, 0, 0]}]}",
        ] {
            assert!(from_json(text, "x").is_err(), "{text}");
        }
    }

    #[test]
    fn a_splitter_round_trips_and_must_have_one_view_per_camera() {
        let cameras = from_json(TWO_CAMERAS, "x").unwrap();
        let halves = Splitter {
            layout: crate::photogrammetry::SplitterLayout::LeftRight,
        };
        let text = to_json_with_splitter(&cameras, Some(halves));
        assert!(text.contains(r#""layout": "left_right""#), "{text}");
        let (again, splitter) = from_json_with_splitter(&text, "x").unwrap();
        assert_eq!((again, splitter), (cameras.clone(), Some(halves)));
        // Without one, none is written, and none is read.
        assert!(!to_json(&cameras).contains("splitter"));
        assert_eq!(from_json_with_splitter(TWO_CAMERAS, "x").unwrap().1, None);
        // Four views for two cameras.
        let text = to_json_with_splitter(&cameras, Some(Splitter::quadrants()));
        let error = from_json_with_splitter(&text, "cal.json")
            .unwrap_err()
            .to_string();
        assert!(
            error.starts_with("cal.json: splitter.layout: the quadrants layout has 4 views")
                && error.contains("has 2 cameras"),
            "{error}"
        );
    }

    /// The schema's required fields of a camera are exactly those a setup
    /// cannot leave out, and its optional ones can be left out of a setup.
    #[test]
    fn the_schema_says_which_setup_fields_are_required() {
        let schema = serde_json::to_value(<CameraJson as utoipa::PartialSchema>::schema()).unwrap();
        let required: Vec<&str> = schema["required"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        assert_eq!(required, ["image_size", "pixel_size", "media"]);
        let two: serde_json::Value = serde_json::from_str(TWO_CAMERAS).unwrap();
        for field in schema["properties"].as_object().unwrap().keys() {
            let mut setup = two.clone();
            setup["cameras"][0].as_object_mut().unwrap().remove(field);
            let parsed = setup_from_json(&setup.to_string(), "setup.json");
            if required.contains(&field.as_str()) {
                let message = parsed.unwrap_err().to_string();
                assert!(
                    message.starts_with(&format!("setup.json: cameras[0].{field}: missing")),
                    "{message}"
                );
            } else {
                let parsed = parsed.unwrap_or_else(|e| panic!("{field}: {e}"));
                let orientation = ["position", "angles", "principal_distance"];
                assert_eq!(
                    parsed.unknown[0].is_empty(),
                    !orientation.contains(&field.as_str()),
                    "{field}"
                );
                assert!(parsed.unknown[1].is_empty());
            }
        }
        // Without its orientation, a camera is a setup's, not a calibration's.
        let mut bare = two.clone();
        for field in ["position", "angles", "principal_distance"] {
            bare["cameras"][1].as_object_mut().unwrap().remove(field);
        }
        let setup = setup_from_json(&bare.to_string(), "setup.json").unwrap();
        assert_eq!(
            setup.unknown[1],
            ParameterSet::exterior() | ParameterSet::of(&[Parameter::C])
        );
        let message = error_of(&bare.to_string());
        assert!(
            message.starts_with("cal.json: cameras[1].position: missing: a calibration gives"),
            "{message}"
        );
    }
}
