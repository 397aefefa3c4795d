//! One HDF5 file per sequence: its particles by frame and its trajectories
//! as tables, with units in attributes, readable by h5py (and pandas
//! through it: `pandas.DataFrame({k: g[k][()] for k in g})` for a table
//! group `g`).
//!
//! Written with `hdf5-pure`, a pure-Rust writer (no libhdf5, no build
//! script); the file is built in memory and written at once, so its memory
//! is the file's size (about 170 bytes per trajectory point and 64 per
//! particle) plus the records.
//!
//! Layout:
//!
//! - `/` attributes `creator` (`ptv <version>`), `length_unit` (`mm`),
//!   `time_unit` (`frame`).
//! - `/particles/frames`: the frame numbers, in order; per frame a group
//!   `/particles/frame_<N>` (attribute `frame`) of equal-length columns
//!   `x, y, z, sigma_x, sigma_y, sigma_z` (mm), `cameras` (cameras that saw
//!   the particle, 0 where unknown) and `trajectory` (-1 for none).
//! - `/trajectories`: one table of points by trajectory and frame, columns
//!   `trajectory, frame, x, y, z, sigma_x, sigma_y, sigma_z, u, v, w,
//!   sigma_u, sigma_v, sigma_w, ax, ay, az, sigma_ax, sigma_ay, sigma_az,
//!   cameras`: velocities in mm per frame, accelerations in mm per frame²
//!   (NaN where the fit window has two points).
//!
//! Every column has the attributes `units` and `description`.

use hdf5_pure::{AttrValue, FileBuilder, GroupBuilder};

use super::vtk::{ParticleRecord, TrajectoryRecord};

/// A column of a table.
enum Column {
    F64(Vec<f64>),
    I64(Vec<i64>),
    U32(Vec<u32>),
}

fn put(group: &mut GroupBuilder, name: &str, units: &str, description: &str, column: Column) {
    let dataset = group.create_dataset(name);
    let dataset = match &column {
        Column::F64(v) => dataset.with_f64_data(v),
        Column::I64(v) => dataset.with_i64_data(v),
        Column::U32(v) => dataset.with_u32_data(v),
    };
    dataset
        .set_attr("units", AttrValue::String(units.into()))
        .set_attr("description", AttrValue::String(description.into()));
}

/// Why the file could not be built.
#[derive(Debug, thiserror::Error)]
#[error("the HDF5 writer failed: {0}")]
pub struct Hdf5Error(String);

/// The sequence's particles (per frame) and trajectories as one HDF5
/// file's bytes (see the module's docs).
pub fn sequence_file(
    frames: &[(i64, Vec<ParticleRecord>)],
    trajectories: &[TrajectoryRecord],
) -> Result<Vec<u8>, Hdf5Error> {
    let mut file = FileBuilder::new();
    file.set_attr(
        "creator",
        AttrValue::String(format!("ptv {}", env!("CARGO_PKG_VERSION"))),
    );
    file.set_attr("length_unit", AttrValue::String("mm".into()));
    file.set_attr("time_unit", AttrValue::String("frame".into()));

    let mut particles = file.create_group("particles");
    put(
        &mut particles,
        "frames",
        "frame",
        "the frames, each a group frame_<N>",
        Column::I64(frames.iter().map(|(f, _)| *f).collect()),
    );
    for (frame, list) in frames {
        let mut group = particles.create_group(&format!("frame_{frame}"));
        group.set_attr("frame", AttrValue::I64(*frame));
        for (axis, name) in ["x", "y", "z"].iter().enumerate() {
            put(
                &mut group,
                name,
                "mm",
                "position",
                Column::F64(list.iter().map(|p| p.position[axis]).collect()),
            );
        }
        for (axis, name) in ["sigma_x", "sigma_y", "sigma_z"].iter().enumerate() {
            put(
                &mut group,
                name,
                "mm",
                "the position's standard deviation",
                Column::F64(list.iter().map(|p| p.sigma[axis]).collect()),
            );
        }
        put(
            &mut group,
            "cameras",
            "1",
            "cameras that saw the particle (0: unknown)",
            Column::U32(list.iter().map(|p| p.cameras).collect()),
        );
        put(
            &mut group,
            "trajectory",
            "1",
            "the particle's trajectory (-1: none)",
            Column::I64(list.iter().map(|p| p.trajectory).collect()),
        );
        particles.add_group(group.finish());
    }
    file.add_group(particles.finish());

    let mut table = file.create_group("trajectories");
    table.set_attr(
        "description",
        AttrValue::String("trajectory points by trajectory and frame".into()),
    );
    let points: Vec<_> = trajectories
        .iter()
        .flat_map(|t| t.points.iter().map(move |p| (t.id, p)))
        .collect();
    put(
        &mut table,
        "trajectory",
        "1",
        "the trajectory's number",
        Column::I64(points.iter().map(|(id, _)| *id as i64).collect()),
    );
    put(
        &mut table,
        "frame",
        "frame",
        "the frame",
        Column::I64(points.iter().map(|(_, p)| p.frame).collect()),
    );
    type Pick = fn(&super::vtk::TrajectoryPointRecord, usize) -> f64;
    let vectors: [([&str; 3], &str, &str, Pick); 6] = [
        (["x", "y", "z"], "mm", "position", |p, a| p.position[a]),
        (
            ["sigma_x", "sigma_y", "sigma_z"],
            "mm",
            "the position's standard deviation",
            |p, a| p.sigma[a],
        ),
        (
            ["u", "v", "w"],
            "mm/frame",
            "velocity, from the local polynomial fit",
            |p, a| p.velocity[a],
        ),
        (
            ["sigma_u", "sigma_v", "sigma_w"],
            "mm/frame",
            "the velocity's standard deviation",
            |p, a| p.velocity_sigma[a],
        ),
        (
            ["ax", "ay", "az"],
            "mm/frame^2",
            "acceleration, from the local polynomial fit (NaN: the window has two points)",
            |p, a| p.acceleration.map_or(f64::NAN, |v| v[a]),
        ),
        (
            ["sigma_ax", "sigma_ay", "sigma_az"],
            "mm/frame^2",
            "the acceleration's standard deviation (NaN: none)",
            |p, a| p.acceleration_sigma.map_or(f64::NAN, |v| v[a]),
        ),
    ];
    for (names, units, description, pick) in vectors {
        for (axis, name) in names.iter().enumerate() {
            put(
                &mut table,
                name,
                units,
                description,
                Column::F64(points.iter().map(|(_, p)| pick(p, axis)).collect()),
            );
        }
    }
    put(
        &mut table,
        "cameras",
        "1",
        "cameras that saw the particle (0: unknown)",
        Column::U32(points.iter().map(|(_, p)| p.cameras).collect()),
    );
    file.add_group(table.finish());
    file.finish().map_err(|e| Hdf5Error(e.to_string()))
}
