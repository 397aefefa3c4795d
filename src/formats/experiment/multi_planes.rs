//! OpenPTV's multi-plane calibration files: the plate at several known
//! positions, each position's points already identified per camera.
//!
//! OpenPTV (liboptv's `jw_ptv` and pyptv's "multi-plane" orientation) uses
//! them when `examine.Combine_Flag` is 1. `multi_planes` names the planes
//! (`n_planes`, then one `plane_name` per plane); for plane `name` and
//! camera `n` (1-based, as liboptv numbers them) two files hold what one
//! calibration of that plane identified:
//!
//! - `<name><n>.tif.fix`: `pnr X Y Z` per line, the plate's points where it
//!   was (mm, the common frame);
//! - `<name><n>.tif.crd`: `pnr x y` per line, their image positions (OpenPTV
//!   pixels, which are `ptv`'s: `x_px = x / pix_x + imx / 2`); `-999` marks
//!   a point not detected, and such a line is skipped.
//!
//! pyptv writes both with `numpy.savetxt` (`%10.5f`, so `pnr` may be
//! `3.00000`) and numbers each camera's points from 0 in the order it
//! identified them: the same `pnr` may be another point in another camera.
//! So a plane's points are the distinct positions over all its cameras'
//! `.fix` files (numbered from 1 in the order first read: camera 1's file,
//! then camera 2's, ...), and each `.crd` line is the image of the position
//! its camera's `.fix` gives its `pnr`. Those planes go to
//! [`crate::photogrammetry::calibrate::calibrate_planes`].

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use nalgebra::{Point2, Point3};

use super::{ExperimentError, ExperimentFiles};
use crate::photogrammetry::calibrate::{ControlPoint, MarkObservation, Plane};

/// OpenPTV's marker of a point not detected in a `.crd` file.
const NOT_DETECTED: f64 = -999.0;

/// One plane of `multi_planes`: its name and, per camera, its `.fix` and
/// `.crd` files, resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaneFiles {
    /// The plane's name as `multi_planes` gives it.
    pub name: String,
    /// Per camera, its `.fix` and `.crd` files.
    pub cameras: Vec<(PathBuf, PathBuf)>,
}

/// The files of the planes `names` for `cameras` cameras, resolved from
/// `root` through `files` (an uploaded set resolves only to files sent);
/// `source` is the file that names them (for errors).
pub(super) fn plane_files(
    files: &dyn ExperimentFiles,
    source: &Path,
    root: &Path,
    names: &[String],
    cameras: usize,
) -> Result<Vec<PlaneFiles>, ExperimentError> {
    names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let cameras = (1..=cameras)
                .map(|n| {
                    let resolve = |extension: &str| {
                        let file = format!("{}{n}.tif.{extension}", name.trim());
                        files
                            .resolve(root, &file)
                            .map_err(|reason| ExperimentError::Refused {
                                file: source.to_owned(),
                                location: format!("multi_planes.plane_name[{k}], camera {n}"),
                                name: file,
                                reason,
                            })
                    };
                    Ok((resolve("fix")?, resolve("crd")?))
                })
                .collect::<Result<Vec<_>, ExperimentError>>()?;
            Ok(PlaneFiles {
                name: name.trim().to_owned(),
                cameras,
            })
        })
        .collect()
}

/// One numbered line of a `.fix` or `.crd` file: its line number, `pnr`
/// and the coordinates.
struct Row {
    line: usize,
    pnr: Option<u64>,
    values: Vec<f64>,
}

fn invalid(file: &Path, line: usize, reason: String) -> ExperimentError {
    ExperimentError::Invalid {
        file: file.to_owned(),
        location: format!("line {line}"),
        reason,
    }
}

/// The rows of `text` (`pnr` and `columns - 1` numbers per line; blank
/// lines skipped). `pnr` is `None` for OpenPTV's -999.
fn rows(text: &str, file: &Path, columns: usize, what: &str) -> Result<Vec<Row>, ExperimentError> {
    let mut rows = Vec::new();
    let mut seen = BTreeMap::new();
    for (n, line) in text.lines().enumerate() {
        let line_number = n + 1;
        if line.trim().is_empty() {
            continue;
        }
        let values: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|_| invalid(file, line_number, format!("not `{what}` (numbers)")))?;
        if values.len() != columns || values.iter().any(|v| !v.is_finite()) {
            return Err(invalid(
                file,
                line_number,
                format!("not `{what}` ({columns} finite numbers)"),
            ));
        }
        let pnr = if values[0] == NOT_DETECTED {
            None
        } else if values[0] >= 0.0 && values[0].fract() == 0.0 && values[0] < 1e15 {
            Some(values[0] as u64)
        } else {
            return Err(invalid(
                file,
                line_number,
                format!("{} is not a point number (0, 1, 2, ...)", values[0]),
            ));
        };
        if let Some(pnr) = pnr {
            if let Some(first) = seen.insert(pnr, line_number) {
                return Err(invalid(
                    file,
                    line_number,
                    format!("point {pnr} again (first on line {first}); each point once"),
                ));
            }
        }
        rows.push(Row {
            line: line_number,
            pnr,
            values: values[1..].to_vec(),
        });
    }
    Ok(rows)
}

/// Reads the planes' `.fix` and `.crd` files through `files`, as the
/// module's documentation says; `source` is the file that names them.
/// Errors name the file and line: a file missing, a line that is not
/// `pnr X Y Z` / `pnr x y`, a point number twice in one file, a `.crd`
/// point its `.fix` does not have.
pub fn read_planes(
    files: &dyn ExperimentFiles,
    source: &Path,
    planes: &[PlaneFiles],
) -> Result<Vec<Plane>, ExperimentError> {
    planes
        .iter()
        .enumerate()
        .map(|(k, plane)| {
            let mut control: Vec<ControlPoint> = Vec::new();
            let mut ids: HashMap<[u64; 3], u64> = HashMap::new();
            let mut observations = Vec::with_capacity(plane.cameras.len());
            for (camera, (fix, crd)) in plane.cameras.iter().enumerate() {
                let read = |path: &Path| {
                    if !files.is_file(path) {
                        return Err(ExperimentError::Missing {
                            file: source.to_owned(),
                            location: format!(
                                "multi_planes.plane_name[{k}] ({}), camera {}",
                                plane.name,
                                camera + 1
                            ),
                            missing: path.to_owned(),
                        });
                    }
                    Ok(files.read_text(path)?)
                };
                let known = rows(&read(fix)?, fix, 4, "pnr X Y Z")?;
                let detected = rows(&read(crd)?, crd, 3, "pnr x y")?;
                // This camera's pnr -> the plane's id of its position.
                let mut local = BTreeMap::new();
                for row in &known {
                    let Some(pnr) = row.pnr else {
                        return Err(invalid(
                            fix,
                            row.line,
                            "-999 is not a point number here (it marks an undetected point in a \
                             .crd file)"
                                .into(),
                        ));
                    };
                    let position = Point3::new(row.values[0], row.values[1], row.values[2]);
                    let key = [
                        position.x.to_bits(),
                        position.y.to_bits(),
                        position.z.to_bits(),
                    ];
                    let next = control.len() as u64 + 1;
                    let id = *ids.entry(key).or_insert_with(|| {
                        control.push(ControlPoint { id: next, position });
                        next
                    });
                    local.insert(pnr, id);
                }
                let mut seen = Vec::with_capacity(detected.len());
                for row in &detected {
                    let (Some(pnr), [x, y]) = (row.pnr, row.values.as_slice()) else {
                        continue;
                    };
                    if *x == NOT_DETECTED || *y == NOT_DETECTED {
                        continue;
                    }
                    let id = local.get(&pnr).ok_or_else(|| {
                        invalid(
                            crd,
                            row.line,
                            format!(
                                "point {pnr} is not in {} (the plane's points this camera \
                                 identified); the two files must number the same points",
                                fix.display()
                            ),
                        )
                    })?;
                    seen.push(MarkObservation {
                        id: *id,
                        pixel: Point2::new(*x, *y),
                    });
                }
                observations.push(seen);
            }
            Ok(Plane {
                control,
                observations,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::experiment::UploadedFiles;

    fn one_plane(
        fix: &[(&str, &str)],
        crd: &[(&str, &str)],
    ) -> Result<Vec<Plane>, ExperimentError> {
        let mut files = UploadedFiles::new();
        for (name, text) in fix.iter().chain(crd) {
            files.insert_bytes(name, text.as_bytes().to_vec()).unwrap();
        }
        let planes = plane_files(
            &files,
            Path::new("parameters/multi_planes.par"),
            Path::new(""),
            &["img/a_cam".to_owned()],
            fix.len(),
        )
        .unwrap();
        read_planes(&files, Path::new("parameters/multi_planes.par"), &planes)
    }

    #[test]
    fn cameras_numbering_the_same_points_differently_share_the_plane() {
        let planes = one_plane(
            &[
                (
                    "img/a_cam1.tif.fix",
                    "0.00000 1.0 2.0 3.0\n1.00000 4.0 5.0 3.0\n",
                ),
                ("img/a_cam2.tif.fix", "0 4.0 5.0 3.0\n1 7.0 8.0 3.0\n"),
            ],
            &[
                ("img/a_cam1.tif.crd", "0 10.5 20.5\n1 -999 -999\n"),
                ("img/a_cam2.tif.crd", "1 30.0 40.0\n0 50.0 60.0\n"),
            ],
        )
        .unwrap();
        let plane = &planes[0];
        assert_eq!(
            plane.control.iter().map(|p| p.id).collect::<Vec<_>>(),
            [1, 2, 3]
        );
        assert_eq!(plane.control[2].position, Point3::new(7.0, 8.0, 3.0));
        assert_eq!(plane.observations[0].len(), 1);
        assert_eq!(plane.observations[0][0].id, 1);
        // Camera 2's pnr 0 is camera 1's pnr 1: the same position, id 2.
        assert_eq!(
            plane.observations[1]
                .iter()
                .map(|o| o.id)
                .collect::<Vec<_>>(),
            [3, 2]
        );
    }

    #[test]
    fn unknown_and_repeated_points_and_missing_files_are_named() {
        let error = one_plane(
            &[("img/a_cam1.tif.fix", "0 1 2 3\n")],
            &[("img/a_cam1.tif.crd", "0 1 1\n7 2 2\n")],
        )
        .unwrap_err()
        .to_string();
        assert!(
            error.contains("img/a_cam1.tif.crd: line 2: point 7 is not in img/a_cam1.tif.fix"),
            "{error}"
        );
        let error = one_plane(
            &[("img/a_cam1.tif.fix", "0 1 2 3\n0 4 5 6\n")],
            &[("img/a_cam1.tif.crd", "0 1 1\n")],
        )
        .unwrap_err()
        .to_string();
        assert!(
            error.contains("line 2: point 0 again (first on line 1)"),
            "{error}"
        );
        let error = one_plane(&[("img/a_cam1.tif.fix", "0 1 2 3\n")], &[])
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("camera 1")
                && error.contains("img/a_cam1.tif.crd, which does not exist"),
            "{error}"
        );
        let error = one_plane(
            &[("img/a_cam1.tif.fix", "0 1 2\n")],
            &[("img/a_cam1.tif.crd", "0 1 1\n")],
        )
        .unwrap_err()
        .to_string();
        assert!(error.contains("not `pnr X Y Z`"), "{error}");
    }
}
