//! The inputs of a calibration: OpenPTV's calibration block (control
//! points, one `id X Y Z` per line, mm) and measured image coordinates of
//! control points (one `id x y` per line, pixels in the camera model's
//! convention), plus the report as JSON.
//!
//! Fields are separated by whitespace; blank lines and lines starting with
//! `#` are skipped. Ids are non-negative integers.

use super::openptv::finite_number;
use super::FormatError;
use crate::photogrammetry::calibrate::{
    CalibrationOptions, CalibrationReport, CheckPoints, ControlPoint, MarkObservation, Parameter,
};
use nalgebra::{Point2, Point3};

/// The data lines of a file: 1-based line number and fields.
fn records<'a>(
    text: &'a str,
    source: &'a str,
    fields: usize,
    layout: &'a str,
) -> impl Iterator<Item = Result<(usize, u64, Vec<&'a str>), FormatError>> + 'a {
    text.lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .filter(|(_, line)| !line.is_empty() && !line.starts_with('#'))
        .map(move |(line, text)| {
            let tokens: Vec<&str> = text.split_whitespace().collect();
            if tokens.len() != fields {
                return Err(FormatError::invalid(
                    source,
                    format!("line {line}"),
                    format!(
                        "expected {fields} fields `{layout}`, got {}: `{text}`",
                        tokens.len()
                    ),
                ));
            }
            let id = tokens[0].parse::<u64>().map_err(|_| {
                FormatError::invalid(
                    source,
                    format!("line {line}"),
                    format!("the id must be a non-negative integer, got `{}`", tokens[0]),
                )
            })?;
            Ok((line, id, tokens[1..].to_vec()))
        })
}

/// Reads a calibration block file: `id X Y Z` per line (mm). Ids must be
/// unique.
pub fn parse_control_points(text: &str, source: &str) -> Result<Vec<ControlPoint>, FormatError> {
    let mut points: Vec<ControlPoint> = Vec::new();
    let mut seen = std::collections::HashMap::new();
    for record in records(text, source, 4, "id X Y Z") {
        let (line, id, values) = record?;
        let x = finite_number(values[0], source, line, "X")?;
        let y = finite_number(values[1], source, line, "Y")?;
        let z = finite_number(values[2], source, line, "Z")?;
        if let Some(first) = seen.insert(id, line) {
            return Err(FormatError::invalid(
                source,
                format!("line {line}"),
                format!("control point {id} was already given on line {first}"),
            ));
        }
        points.push(ControlPoint {
            id,
            position: Point3::new(x, y, z),
        });
    }
    if points.is_empty() {
        return Err(FormatError::invalid(
            source,
            "line 1",
            "no control points: expected lines `id X Y Z`",
        ));
    }
    Ok(points)
}

/// Reads measured image coordinates of control points: `id x y` per line
/// (pixels). Ids must be unique; an empty file is an empty list (a camera
/// that sees nothing, which the calibration reports by name).
pub fn parse_mark_observations(
    text: &str,
    source: &str,
) -> Result<Vec<MarkObservation>, FormatError> {
    let mut marks = Vec::new();
    let mut seen = std::collections::HashMap::new();
    for record in records(text, source, 3, "id x y") {
        let (line, id, values) = record?;
        let x = finite_number(values[0], source, line, "x")?;
        let y = finite_number(values[1], source, line, "y")?;
        if let Some(first) = seen.insert(id, line) {
            return Err(FormatError::invalid(
                source,
                format!("line {line}"),
                format!("point {id} was already given on line {first}"),
            ));
        }
        marks.push(MarkObservation {
            id,
            pixel: Point2::new(x, y),
        });
    }
    Ok(marks)
}

/// A calibration option that is not valid: its name as the service's
/// `options` JSON spells it (`check_every`; the command line's flag is the
/// same with `--` and dashes) and what is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{option}: {reason}")]
pub struct OptionError {
    /// `fix`, `check_every` or `check_ids`.
    pub option: &'static str,
    /// What is wrong and what is expected.
    pub reason: String,
}

/// The parameters to hold, by OpenPTV's names (case-insensitive; blank
/// names are ignored), as `ptv calibrate --fix` and the service's `fix`
/// take them.
pub fn fixed_parameters(names: &[String]) -> Result<Vec<Parameter>, OptionError> {
    names
        .iter()
        .filter(|name| !name.trim().is_empty())
        .map(|name| {
            Parameter::from_name(name.trim()).ok_or_else(|| OptionError {
                option: "fix",
                reason: format!(
                    "unknown parameter `{name}`; the names are {}",
                    Parameter::ALL.map(Parameter::name).join(",")
                ),
            })
        })
        .collect()
}

/// The options of a calibration from what `ptv calibrate` and the service
/// take: parameters to hold ([`fixed_parameters`]), check points (every
/// K-th, K >= 2, or ids; not both) and the largest correlation of free
/// parameters.
pub fn calibration_options(
    fixed: Vec<Parameter>,
    check_every: Option<usize>,
    check_ids: Option<Vec<u64>>,
    max_correlation: f64,
) -> Result<CalibrationOptions, OptionError> {
    let invalid = |option, reason: String| OptionError { option, reason };
    let check_points = match (check_every, check_ids) {
        (Some(_), Some(_)) => {
            return Err(invalid(
                "check_every",
                "give either check_every or check_ids, not both".to_owned(),
            ))
        }
        (Some(k), None) if k < 2 => {
            return Err(invalid(
                "check_every",
                format!("K must be at least 2, got {k}"),
            ))
        }
        (Some(k), None) => CheckPoints::Every(k),
        (None, Some(ids)) => CheckPoints::Ids(ids),
        (None, None) => CheckPoints::None,
    };
    if !(max_correlation > 0.0 && max_correlation <= 1.0) {
        return Err(invalid(
            "max_correlation",
            format!("must be in (0, 1], got {max_correlation}"),
        ));
    }
    Ok(CalibrationOptions {
        fixed,
        check_points,
        max_correlation,
        ..CalibrationOptions::default()
    })
}

/// Reads check point ids: non-negative integers separated by whitespace.
pub fn parse_check_ids(text: &str, source: &str) -> Result<Vec<u64>, FormatError> {
    text.split_whitespace()
        .enumerate()
        .map(|(i, t)| {
            t.parse::<u64>().map_err(|_| {
                FormatError::invalid(
                    source,
                    format!("id {}", i + 1),
                    format!("`{t}` is not a point id (a non-negative integer)"),
                )
            })
        })
        .collect()
}

/// Writes image coordinates as `id x y` lines, numbers in their shortest
/// exact form.
pub fn format_mark_observations(marks: &[MarkObservation]) -> String {
    marks
        .iter()
        .map(|m| format!("{} {} {}\n", m.id, m.pixel.x, m.pixel.y))
        .collect()
}

/// Writes a calibration block file.
pub fn format_control_points(points: &[ControlPoint]) -> String {
    points
        .iter()
        .map(|p| {
            format!(
                "{} {} {} {}\n",
                p.id, p.position.x, p.position.y, p.position.z
            )
        })
        .collect()
}

/// The calibration report as pretty JSON (non-finite numbers, e.g. the RMSE
/// of zero check points, become `null`).
pub fn report_to_json(report: &CalibrationReport) -> String {
    let mut text = serde_json::to_string_pretty(report).unwrap_or_else(|e| {
        // Serialising plain numbers and strings cannot fail; keep the
        // signature total anyway.
        format!("{{\"error\": \"{e}\"}}")
    });
    text.push('\n');
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_test_cavity_calibration_block() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/data/openptv/test_cavity/cal/target_on_a_side.txt"
        );
        let text = std::fs::read_to_string(path).expect("the test_cavity calibration block");
        let points = parse_control_points(&text, path).unwrap();
        assert_eq!(
            points.len(),
            text.lines().filter(|l| !l.trim().is_empty()).count()
        );
        assert_eq!(points[0].id, 1);
        assert_eq!(points[0].position, Point3::new(-40.0, -25.0, 8.0));
        let round = parse_control_points(&format_control_points(&points), "x").unwrap();
        assert_eq!(round, points);
    }

    #[test]
    fn options_say_which_option_is_wrong() {
        let names = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let fixed = fixed_parameters(&names(&["k3", " C", ""])).unwrap();
        assert_eq!(fixed, vec![Parameter::K3, Parameter::C]);
        let options = calibration_options(fixed, Some(5), None, 0.95).unwrap();
        assert_eq!(options.fixed, vec![Parameter::K3, Parameter::C]);
        assert_eq!(options.check_points, CheckPoints::Every(5));
        assert_eq!(options.max_correlation, 0.95);
        let error = fixed_parameters(&names(&["k4"])).unwrap_err();
        assert_eq!(error.option, "fix");
        assert!(error.reason.contains("unknown parameter `k4`"), "{error}");
        let error = calibration_options(vec![], Some(1), None, 0.99).unwrap_err();
        assert_eq!(
            error.to_string(),
            "check_every: K must be at least 2, got 1"
        );
        assert!(calibration_options(vec![], Some(3), Some(vec![1]), 0.99).is_err());
        let error = calibration_options(vec![], None, None, 1.5).unwrap_err();
        assert_eq!(error.option, "max_correlation");
        assert_eq!(parse_check_ids("3 7\n12", "ids").unwrap(), vec![3, 7, 12]);
        let error = parse_check_ids("3 x", "ids.txt").unwrap_err();
        assert_eq!(
            error.to_string(),
            "ids.txt: id 2: `x` is not a point id (a non-negative integer)"
        );
    }

    #[test]
    fn errors_name_the_line_and_field() {
        let error = parse_control_points("1 0 0 0\n\n2 0 nan 0\n", "block.txt").unwrap_err();
        assert_eq!(
            error.to_string(),
            "block.txt: line 3: Y must be a finite number, got `nan`"
        );
        let error = parse_control_points("1 0 0\n", "block.txt").unwrap_err();
        assert!(
            error.to_string().contains("line 1: expected 4 fields"),
            "{error}"
        );
        let error = parse_control_points("1 0 0 0\n1 1 1 1\n", "b").unwrap_err();
        assert!(error
            .to_string()
            .contains("line 2: control point 1 was already given on line 1"));
        let error = parse_mark_observations("# id x y\n-3 1 2\n", "cam1.txt").unwrap_err();
        assert!(
            error.to_string().starts_with("cam1.txt: line 2: the id"),
            "{error}"
        );
        assert!(parse_control_points("", "empty").is_err());
        assert_eq!(parse_mark_observations("\n", "none").unwrap(), vec![]);
        let marks = parse_mark_observations("7 10.5 20.25\n", "m").unwrap();
        assert_eq!(
            parse_mark_observations(&format_mark_observations(&marks), "m").unwrap(),
            marks
        );
    }
}

/// The LPT challenge's calibration points (`CalibPoints.txt`): per line a
/// control point and its image in every camera, `X Y Z x1 y1 ... xN yN`
/// (mm, pixels), fields separated by whitespace (or commas); blank lines
/// and lines starting with `#` skipped. The points are numbered by data
/// line from 1. The image coordinates are taken in the camera model's
/// convention (the centre of the top-left pixel at 0.5, 0.5); a file that
/// counts pixel centres from 0 shifts every image by half a pixel, which the
/// resection takes into the principal point (xh, yh) when they are free.
/// Every point must be seen by every camera: `cameras` is the setup's.
pub fn parse_calib_points(
    text: &str,
    source: &str,
    cameras: usize,
) -> Result<(Vec<ControlPoint>, Vec<Vec<MarkObservation>>), FormatError> {
    let fields = 3 + 2 * cameras;
    let mut control = Vec::new();
    let mut observations = vec![Vec::new(); cameras];
    for (index, line) in text.lines().enumerate() {
        let number = index + 1;
        let trimmed = line.trim();
        if trimmed.is_empty() || trimmed.starts_with('#') {
            continue;
        }
        let tokens: Vec<&str> = trimmed
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty())
            .collect();
        if tokens.len() != fields {
            return Err(FormatError::invalid(
                source,
                format!("line {number}"),
                format!(
                    "expected {fields} numbers `X Y Z x1 y1 ... x{cameras} y{cameras}` (the setup \
                     has {cameras} cameras), got {}",
                    tokens.len()
                ),
            ));
        }
        let value = |k: usize, what: String| finite_number(tokens[k], source, number, &what);
        let id = control.len() as u64 + 1;
        control.push(ControlPoint {
            id,
            position: Point3::new(
                value(0, "X".into())?,
                value(1, "Y".into())?,
                value(2, "Z".into())?,
            ),
        });
        for (camera, marks) in observations.iter_mut().enumerate() {
            let x = value(3 + 2 * camera, format!("x{}", camera + 1))?;
            let y = value(4 + 2 * camera, format!("y{}", camera + 1))?;
            marks.push(MarkObservation {
                id,
                pixel: Point2::new(x, y),
            });
        }
    }
    if control.is_empty() {
        return Err(FormatError::invalid(
            source,
            "line 1",
            "no calibration points: expected lines `X Y Z x1 y1 ... xN yN`",
        ));
    }
    Ok((control, observations))
}

#[cfg(test)]
mod calib_points_tests {
    use super::*;

    #[test]
    fn reads_points_and_their_images_and_names_bad_lines() {
        let text = "# X Y Z x1 y1 x2 y2\n1 2 3 10.5 20.5 30 40\n\n4,5,6,11,21,31,41\n";
        let (control, observations) = parse_calib_points(text, "CalibPoints.txt", 2).unwrap();
        assert_eq!(control.len(), 2);
        assert_eq!(control[1].position, Point3::new(4.0, 5.0, 6.0));
        assert_eq!(observations[1][0].pixel, Point2::new(30.0, 40.0));
        assert_eq!(observations[0][1].id, 2);
        for (bad, expected) in [
            ("1 2 3 4 5 6\n", "line 1: expected 7 numbers"),
            (
                "1 2 3 4 5 6 7\n1 2 NaN 4 5 6 7\n",
                "line 2: Z must be a finite number, got `NaN`",
            ),
            ("1 2 3 4 5 6 y\n", "line 1: y2 must be a finite number"),
            ("# nothing\n", "no calibration points"),
        ] {
            let message = parse_calib_points(bad, "CalibPoints.txt", 2)
                .unwrap_err()
                .to_string();
            assert!(message.starts_with("CalibPoints.txt: "), "{message}");
            assert!(message.contains(expected), "{expected}: {message}");
        }
    }
}
