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
//! vector's plane. Optional fields and their defaults: `name` (`camN`),
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

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CalibrationFile {
    #[serde(deserialize_with = "bounded_cameras")]
    cameras: Vec<CameraJson>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
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

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraJson {
    #[serde(default)]
    name: Option<String>,
    image_size: [u32; 2],
    pixel_size: [f64; 2],
    position: [f64; 3],
    angles: [f64; 3],
    principal_distance: f64,
    #[serde(default)]
    principal_point: [f64; 2],
    #[serde(default)]
    radial: [f64; 3],
    #[serde(default)]
    decentering: [f64; 2],
    #[serde(default = "identity_affine")]
    affine: [f64; 2],
    media: MediaJson,
}

fn identity_affine() -> [f64; 2] {
    [1.0, 0.0]
}

fn one() -> f64 {
    1.0
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct MediaJson {
    #[serde(default = "one")]
    n_air: f64,
    #[serde(default)]
    walls: Vec<WallJson>,
    n_object: f64,
    #[serde(default)]
    glass_vector: [f64; 3],
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct WallJson {
    n: f64,
    thickness: f64,
}

impl CameraJson {
    fn into_parameters(self, index: usize) -> CameraParameters {
        CameraParameters {
            name: self.name.unwrap_or_else(|| format!("cam{}", index + 1)),
            sensor: Sensor {
                width: self.image_size[0],
                height: self.image_size[1],
                pixel_size_x: self.pixel_size[0],
                pixel_size_y: self.pixel_size[1],
            },
            exterior: Exterior {
                position: Vector3::from(self.position),
                omega: self.angles[0],
                phi: self.angles[1],
                kappa: self.angles[2],
            },
            interior: Interior {
                c: self.principal_distance,
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
                n_air: self.media.n_air,
                walls: self
                    .media
                    .walls
                    .into_iter()
                    .map(|w| Wall {
                        n: w.n,
                        thickness: w.thickness,
                    })
                    .collect(),
                n_object: self.media.n_object,
                glass_vector: Vector3::from(self.media.glass_vector),
            },
        }
    }

    fn from_parameters(p: &CameraParameters) -> CameraJson {
        CameraJson {
            name: Some(p.name.clone()),
            image_size: [p.sensor.width, p.sensor.height],
            pixel_size: [p.sensor.pixel_size_x, p.sensor.pixel_size_y],
            position: p.exterior.position.into(),
            angles: [p.exterior.omega, p.exterior.phi, p.exterior.kappa],
            principal_distance: p.interior.c,
            principal_point: [p.interior.xh, p.interior.yh],
            radial: [p.distortion.k1, p.distortion.k2, p.distortion.k3],
            decentering: [p.distortion.p1, p.distortion.p2],
            affine: [p.distortion.scx, p.distortion.shear],
            media: MediaJson {
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
            },
        }
    }
}

/// Parses and validates a calibration JSON document.
pub fn from_json(text: &str, source: &str) -> Result<Vec<Camera>, FormatError> {
    from_parameters(parameters_from_json(text, source)?, source)
}

/// Parses and validates a calibration JSON document and its splitter, if
/// any: the splitter's views must be the cameras, all of one size.
pub fn from_json_with_splitter(
    text: &str,
    source: &str,
) -> Result<(Vec<Camera>, Option<Splitter>), FormatError> {
    let file = parse_file(text, source)?;
    let splitter = file.splitter;
    let cameras = from_parameters(camera_parameters(file, source)?, source)?;
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
/// values are only optional starting values.
pub fn parameters_from_json(
    text: &str,
    source: &str,
) -> Result<Vec<CameraParameters>, FormatError> {
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

fn camera_parameters(
    file: CalibrationFile,
    source: &str,
) -> Result<Vec<CameraParameters>, FormatError> {
    let parameters: Vec<CameraParameters> = file
        .cameras
        .into_iter()
        .enumerate()
        .map(|(i, camera)| camera.into_parameters(i))
        .collect();
    // A setup's cameras are not validated as cameras (their orientation is
    // only a start), but their names become file names all the same.
    for (i, p) in parameters.iter().enumerate() {
        check_camera_name(&p.name).map_err(|e| {
            FormatError::invalid(source, format!("cameras[{i}].{}", e.field), e.reason)
        })?;
    }
    Ok(parameters)
}

/// Validates a list of camera parameters as a calibration:
/// [`MIN_CAMERAS`]..=[`MAX_CAMERAS`] cameras, each one valid.
pub fn from_parameters(
    parameters: Vec<CameraParameters>,
    source: &str,
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
            Camera::new(p).map_err(|e| {
                FormatError::invalid(source, format!("cameras[{i}].{}", e.field), e.reason)
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
}
