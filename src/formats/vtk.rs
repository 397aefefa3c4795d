//! ParaView's VTK XML files: particles and trajectories as `PolyData`
//! (`.vtp`) and a time series of them (`.pvd`), as described in VTK's
//! "VTK File Formats" (the XML formats: `VTKFile`, `PolyData`, `Piece`,
//! `Points`, `Verts`, `Lines`, `PointData`, `CellData`, `DataArray`;
//! `Collection` with `DataSet timestep=... file=...` for the series).
//!
//! Arrays are written inline in the `binary` encoding: per array, base64 of
//! a `UInt32` byte count followed by the values, little-endian
//! (`header_type="UInt32"`, `byte_order="LittleEndian"`). Binary rather than
//! ASCII keeps every value exactly and lets a missing value be NaN (an
//! acceleration where the fit window has two points), which VTK's ASCII
//! reader cannot parse.
//!
//! - [`particles_vtp`]: one frame's particles as vertices, with their
//!   position sigmas (`sigma`, mm), the cameras that saw them (`cameras`, 0
//!   where unknown) and the trajectory they belong to (`trajectory`, -1 for
//!   none).
//! - [`trajectories_vtp`]: trajectories as polylines (one cell each, points
//!   in frame order), with per point `frame`, `velocity` (mm per frame),
//!   `acceleration` (mm per frame², NaN where unknown), their sigmas
//!   (`velocity_sigma`, `acceleration_sigma`), the position's (`sigma`) and
//!   `cameras`; per cell `trajectory` (its number) and `length`.
//! - [`pvd`]: the `Collection` of per-frame files, `timestep` the frame.

use base64::Engine as _;
use nalgebra::{Point3, Vector3};

/// A particle of a frame, as exported.
#[derive(Clone, Debug, PartialEq)]
pub struct ParticleRecord {
    /// Position (mm).
    pub position: Point3<f64>,
    /// Its standard deviations (mm).
    pub sigma: Vector3<f64>,
    /// Cameras that saw it (0 where unknown).
    pub cameras: u32,
    /// Its trajectory, or -1.
    pub trajectory: i64,
}

/// A point of a trajectory, as exported.
#[derive(Clone, Debug, PartialEq)]
pub struct TrajectoryPointRecord {
    /// The frame.
    pub frame: i64,
    /// Position (mm).
    pub position: Point3<f64>,
    /// The position's standard deviations (mm).
    pub sigma: Vector3<f64>,
    /// Velocity (mm per frame).
    pub velocity: Vector3<f64>,
    /// Its standard deviations.
    pub velocity_sigma: Vector3<f64>,
    /// Acceleration (mm per frame²), where the fit gives one.
    pub acceleration: Option<Vector3<f64>>,
    /// Its standard deviations.
    pub acceleration_sigma: Option<Vector3<f64>>,
    /// Cameras that saw it (0 where unknown).
    pub cameras: u32,
}

/// A trajectory, as exported: its points in frame order.
#[derive(Clone, Debug, PartialEq)]
pub struct TrajectoryRecord {
    /// Its number.
    pub id: u64,
    /// Its points.
    pub points: Vec<TrajectoryPointRecord>,
}

/// Values of a `DataArray`.
enum Values<'a> {
    F64(Vec<f64>),
    I64(Vec<i64>),
    U32(&'a [u32]),
}

impl Values<'_> {
    fn type_name(&self) -> &'static str {
        match self {
            Values::F64(_) => "Float64",
            Values::I64(_) => "Int64",
            Values::U32(_) => "UInt32",
        }
    }

    fn bytes(&self) -> Vec<u8> {
        match self {
            Values::F64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            Values::I64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            Values::U32(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        }
    }
}

/// Appends one inline binary `DataArray`.
fn data_array(out: &mut String, name: &str, components: usize, values: Values) {
    let bytes = values.bytes();
    let mut block = Vec::with_capacity(4 + bytes.len());
    block.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
    block.extend_from_slice(&bytes);
    out.push_str(&format!(
        "        <DataArray type=\"{}\" Name=\"{name}\" NumberOfComponents=\"{components}\" \
         format=\"binary\">",
        values.type_name()
    ));
    out.push_str(&base64::engine::general_purpose::STANDARD.encode(&block));
    out.push_str("</DataArray>\n");
}

fn vectors<'a>(items: impl Iterator<Item = &'a Vector3<f64>>) -> Values<'static> {
    Values::F64(items.flat_map(|v| [v.x, v.y, v.z]).collect())
}

fn head(out: &mut String, points: usize, verts: usize, lines: usize) {
    out.push_str(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"PolyData\" version=\"1.0\" \
         byte_order=\"LittleEndian\" header_type=\"UInt32\">\n  <PolyData>\n",
    );
    out.push_str(&format!(
        "    <Piece NumberOfPoints=\"{points}\" NumberOfVerts=\"{verts}\" \
         NumberOfLines=\"{lines}\" NumberOfStrips=\"0\" NumberOfPolys=\"0\">\n"
    ));
}

fn tail(out: &mut String) {
    out.push_str("    </Piece>\n  </PolyData>\n</VTKFile>\n");
}

fn points_section(out: &mut String, positions: impl Iterator<Item = Point3<f64>>) {
    out.push_str("      <Points>\n");
    data_array(
        out,
        "position",
        3,
        Values::F64(positions.flat_map(|p| [p.x, p.y, p.z]).collect()),
    );
    out.push_str("      </Points>\n");
}

/// The cells' `connectivity` and `offsets` (cell `i` is points
/// `offsets[i-1]..offsets[i]`).
fn cells(out: &mut String, tag: &str, lengths: impl Iterator<Item = usize>) {
    let mut offsets = Vec::new();
    let mut end = 0i64;
    for n in lengths {
        end += n as i64;
        offsets.push(end);
    }
    out.push_str(&format!("      <{tag}>\n"));
    data_array(out, "connectivity", 1, Values::I64((0..end).collect()));
    data_array(out, "offsets", 1, Values::I64(offsets));
    out.push_str(&format!("      </{tag}>\n"));
}

/// One frame's particles as a `.vtp` file (see the module's docs).
pub fn particles_vtp(particles: &[ParticleRecord]) -> String {
    let n = particles.len();
    let mut out = String::new();
    head(&mut out, n, n, 0);
    out.push_str("      <PointData Vectors=\"sigma\">\n");
    data_array(
        &mut out,
        "sigma",
        3,
        vectors(particles.iter().map(|p| &p.sigma)),
    );
    let cameras: Vec<u32> = particles.iter().map(|p| p.cameras).collect();
    data_array(&mut out, "cameras", 1, Values::U32(&cameras));
    data_array(
        &mut out,
        "trajectory",
        1,
        Values::I64(particles.iter().map(|p| p.trajectory).collect()),
    );
    out.push_str("      </PointData>\n");
    points_section(&mut out, particles.iter().map(|p| p.position));
    cells(&mut out, "Verts", std::iter::repeat(1).take(n));
    tail(&mut out);
    out
}

/// Trajectories as polylines in one `.vtp` file (see the module's docs).
pub fn trajectories_vtp(trajectories: &[TrajectoryRecord]) -> String {
    let points: Vec<&TrajectoryPointRecord> = trajectories.iter().flat_map(|t| &t.points).collect();
    let nan = Vector3::repeat(f64::NAN);
    let mut out = String::new();
    head(&mut out, points.len(), 0, trajectories.len());
    out.push_str("      <PointData Vectors=\"velocity\">\n");
    data_array(
        &mut out,
        "frame",
        1,
        Values::I64(points.iter().map(|p| p.frame).collect()),
    );
    data_array(
        &mut out,
        "velocity",
        3,
        vectors(points.iter().map(|p| &p.velocity)),
    );
    data_array(
        &mut out,
        "acceleration",
        3,
        vectors(
            points
                .iter()
                .map(|p| p.acceleration.as_ref().unwrap_or(&nan)),
        ),
    );
    data_array(
        &mut out,
        "velocity_sigma",
        3,
        vectors(points.iter().map(|p| &p.velocity_sigma)),
    );
    data_array(
        &mut out,
        "acceleration_sigma",
        3,
        vectors(
            points
                .iter()
                .map(|p| p.acceleration_sigma.as_ref().unwrap_or(&nan)),
        ),
    );
    data_array(
        &mut out,
        "sigma",
        3,
        vectors(points.iter().map(|p| &p.sigma)),
    );
    let cameras: Vec<u32> = points.iter().map(|p| p.cameras).collect();
    data_array(&mut out, "cameras", 1, Values::U32(&cameras));
    out.push_str("      </PointData>\n      <CellData>\n");
    data_array(
        &mut out,
        "trajectory",
        1,
        Values::I64(trajectories.iter().map(|t| t.id as i64).collect()),
    );
    data_array(
        &mut out,
        "length",
        1,
        Values::I64(trajectories.iter().map(|t| t.points.len() as i64).collect()),
    );
    out.push_str("      </CellData>\n");
    points_section(&mut out, points.iter().map(|p| p.position));
    cells(
        &mut out,
        "Lines",
        trajectories.iter().map(|t| t.points.len()),
    );
    tail(&mut out);
    out
}

/// A ParaView time series: per frame, its file (relative to the `.pvd`).
pub fn pvd(files: &[(i64, String)]) -> String {
    let mut out = String::from(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"1.0\" \
         byte_order=\"LittleEndian\" header_type=\"UInt32\">\n  <Collection>\n",
    );
    for (frame, file) in files {
        out.push_str(&format!(
            "    <DataSet timestep=\"{frame}\" group=\"\" part=\"0\" file=\"{}\"/>\n",
            xml_escape(file)
        ));
    }
    out.push_str("  </Collection>\n</VTKFile>\n");
    out
}

fn xml_escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Reads back an inline binary `DataArray`'s payload (the text between
/// its tags): the values' bytes after the `UInt32` byte count, or `None`
/// where it is not base64 or the count disagrees. For the tests and any
/// reader of these files.
pub fn decode_binary(text: &str) -> Option<Vec<u8>> {
    let block = base64::engine::general_purpose::STANDARD
        .decode(text.trim())
        .ok()?;
    let (count, bytes) = block.split_first_chunk::<4>()?;
    (u32::from_le_bytes(*count) as usize == bytes.len()).then(|| bytes.to_vec())
}
