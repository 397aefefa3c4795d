//! The API's exports (issue 34): ParaView's VTK XML and the one-file HDF5
//! of a sequence, the same files `ptv export` writes
//! ([`formats::vtk`], [`formats::hdf5`]), served by `?format=` on the
//! particles and trajectories routes.
//!
//! Bound: these files are built whole in memory (the HDF5 writer builds
//! its file at once; a `.vtp`'s arrays are columns), so a request loads at
//! most `--max-export-points` points (trajectory points plus the particles
//! of the frames it covers; default [`DEFAULT_MAX_EXPORT_POINTS`]) and is
//! refused with 413 above that, before the file is built: about 0.6 KB a
//! point between the records (~180 bytes), the stored rows and the file
//! (~170 bytes a point in HDF5, ~220 in base64 VTK), so ~120 MB a request
//! at the default (docs/service-limits.md has the measured peak).
//! `frames=FIRST..LAST` cuts a larger sequence into parts under the bound.
//!
//! What the store does not keep is written as unknown: the acceleration's
//! sigmas (NaN in VTK and HDF5), and the position sigma of a point the
//! tracker recovered from a frame's targets (not among the frame's
//! particles).

use std::collections::HashMap;

use axum::http::header;
use axum::response::{IntoResponse, Response};
use nalgebra::{Point3, Vector3};

use super::problem::ApiError;
use crate::formats;
use crate::formats::vtk::{ParticleRecord, TrajectoryPointRecord, TrajectoryRecord};
use crate::photogrammetry::correspond::Particle;
use crate::service::infra::codec;
use crate::service::ops::state::AppState;
use crate::service::store::{FrameNumber, PointRow, SequenceId, TrackingRunId};

/// Trajectories read from the store at a time (with their points) while an
/// export is collected: one page of `GET .../trajectories`.
const TRAJECTORIES_PER_READ: u32 = 500;

pub use crate::service::infra::config::DEFAULT_MAX_EXPORT_POINTS;

/// ParaView's VTK XML. `application/xml`: a `.vtp` is XML that any XML
/// tool reads, and VTK registered no media type of its own
/// (`model/vnd.vtk` is not in IANA's registry).
pub const VTK_CONTENT_TYPE: &str = "application/xml";

/// A zip (ParaView's time series: a `.pvd` names its frames' files).
pub const ZIP_CONTENT_TYPE: &str = "application/zip";

/// HDF5's media type as the HDF Group uses it.
pub const HDF5_CONTENT_TYPE: &str = "application/x-hdf5";

/// What the limit says when a request would go above it: the frames
/// asked for, and where the frames' particles alone passed the limit.
fn too_many(
    what: &str,
    limit: usize,
    frames: (FrameNumber, FrameNumber),
    passed_at: Option<i64>,
) -> ApiError {
    let at = passed_at.map_or_else(String::new, |frame| {
        format!(" (its particles alone pass it at frame {frame})")
    });
    ApiError::too_large(format!(
        "{what} has more than {limit} points (trajectory points and particles) within frames \
         {}..{}{at}, the most one export builds in memory (the service's \
         --max-export-points); ask for fewer frames with `frames=FIRST..LAST`, or for longer \
         trajectories only with `min_length`, or track the files with `ptv track --export`",
        frames.0 .0, frames.1 .0
    ))
}

/// A file as the response, named for saving.
pub fn attachment(content_type: &str, name: &str, body: Vec<u8>) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type.to_owned()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{name}\""),
            ),
        ],
        body,
    )
        .into_response()
}

/// A frame's particles as exported records.
pub fn particle_records(
    particles: &[Particle],
    trajectories: &[Option<i64>],
) -> Vec<ParticleRecord> {
    particles
        .iter()
        .enumerate()
        .map(|(i, p)| ParticleRecord {
            position: p.position,
            sigma: p.sigma,
            cameras: p.targets.iter().flatten().count() as u32,
            trajectory: trajectories.get(i).copied().flatten().unwrap_or(-1),
        })
        .collect()
}

/// A sequence's run, its trajectories and the particles of the frames
/// they cover (both within `frames`), under [`EXPORT_MAX_POINTS`].
pub struct Collected {
    /// Per processed frame, its particles.
    pub frames: Vec<(i64, Vec<ParticleRecord>)>,
    /// The trajectories of at least `min_length` points, by number.
    pub trajectories: Vec<TrajectoryRecord>,
}

/// Loads the records of an export (see [`Collected`]).
pub async fn collect(
    state: &AppState,
    id: SequenceId,
    run: TrackingRunId,
    cameras: usize,
    min_length: i64,
    frames: (FrameNumber, FrameNumber),
) -> Result<Collected, ApiError> {
    let what = format!("sequence {id}'s export");
    let limit = usize::try_from(state.config.max_export_points).unwrap_or(usize::MAX);
    let mut loaded = 0usize;
    // The frames' particles first: the trajectory points take their
    // sigmas from them.
    let mut particles: HashMap<i64, Vec<Particle>> = HashMap::new();
    let mut frame_list = Vec::new();
    for frame in state.store.processed_frames(id).await? {
        if frame.0 < frames.0 .0 || frame.0 > frames.1 .0 {
            continue;
        }
        let Some((count, blob, _)) = state.store.frame_particles(id, frame).await? else {
            continue;
        };
        loaded = loaded.saturating_add(usize::try_from(count).unwrap_or(usize::MAX));
        if loaded > limit {
            return Err(too_many(&what, limit, frames, Some(frame.0)));
        }
        particles.insert(frame.0, codec::decode_particles(&blob, cameras)?);
        frame_list.push(frame.0);
    }
    let mut trajectory_of: HashMap<(i64, usize), i64> = HashMap::new();
    let mut trajectories = Vec::new();
    let mut after = -1i64;
    loop {
        let list = state
            .store
            .trajectories(run, min_length, frames, after, TRAJECTORIES_PER_READ)
            .await?;
        let (Some(low), Some(high)) = (list.first(), list.last()) else {
            break;
        };
        let points = state
            .store
            .trajectory_points(run, (low.id, high.id), frames)
            .await?;
        let mut points = points.iter().peekable();
        for t in &list {
            // Trajectories below min_length in the id range are skipped.
            while points.peek().is_some_and(|p| p.trajectory < t.id) {
                points.next();
            }
            let mut record = TrajectoryRecord {
                id: u64::try_from(t.id).unwrap_or(0),
                points: Vec::new(),
            };
            while let Some(p) = points.next_if(|p| p.trajectory == t.id) {
                loaded += 1;
                if loaded > limit {
                    return Err(too_many(&what, limit, frames, None));
                }
                let particle = usize::try_from(p.particle).ok();
                let stored = particle.and_then(|i| particles.get(&p.frame.0)?.get(i));
                if let (Some(i), Some(_)) = (particle, stored) {
                    trajectory_of.insert((p.frame.0, i), t.id);
                }
                record.points.push(point_record(p, stored));
            }
            trajectories.push(record);
        }
        if list.len() < TRAJECTORIES_PER_READ as usize {
            break;
        }
        after = high.id;
    }
    let frames = frame_list
        .into_iter()
        .map(|frame| {
            let list = particles.remove(&frame).unwrap_or_default();
            let links: Vec<Option<i64>> = (0..list.len())
                .map(|i| trajectory_of.get(&(frame, i)).copied())
                .collect();
            (frame, particle_records(&list, &links))
        })
        .collect();
    Ok(Collected {
        frames,
        trajectories,
    })
}

/// A stored trajectory point as exported; its position sigma from the
/// frame's particle where it is one, NaN where it is unknown.
fn point_record(p: &PointRow, particle: Option<&Particle>) -> TrajectoryPointRecord {
    let vector = |v: Option<[f64; 3]>| v.map_or(Vector3::repeat(f64::NAN), Vector3::from);
    TrajectoryPointRecord {
        frame: p.frame.0,
        position: Point3::from(p.position),
        sigma: particle.map_or(Vector3::repeat(f64::NAN), |q| q.sigma),
        velocity: vector(p.velocity),
        velocity_sigma: vector(p.velocity_sigma),
        acceleration: p.acceleration.map(Vector3::from),
        acceleration_sigma: p.acceleration.map(|_| Vector3::repeat(f64::NAN)),
        cameras: p
            .targets
            .split(',')
            .filter(|t| t.parse::<i64>().is_ok_and(|t| t >= 0))
            .count() as u32,
    }
}

/// ParaView's time series of an export as one zip: `particles.pvd`, each
/// frame's `particles.<frame>.vtp`, and `trajectories.vtp`, as `ptv track
/// --export vtk` writes them into a directory. A `.pvd` names its
/// frames' files by path, which VTK's readers open from the disk only
/// (`vtkXMLReader` reads a file name or a string, no URL), so one
/// download has to carry them all. Entries are stored, not deflated: the
/// base64 arrays deflate to about three quarters only, and the HTTP layer
/// gzips the whole answer for a client that accepts it. Built whole in
/// memory: the files (about 220 bytes a point and particle), within the
/// export's bound.
pub fn paraview_zip(collected: &Collected) -> Result<Vec<u8>, ApiError> {
    use std::io::Write;
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let stored = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .large_file(false);
    let internal = |e: &dyn std::fmt::Display| ApiError::internal(format!("the zip: {e}"));
    let mut series = Vec::with_capacity(collected.frames.len());
    for (frame, particles) in &collected.frames {
        let name = format!("particles.{frame}.vtp");
        zip.start_file(name.as_str(), stored)
            .map_err(|e| internal(&e))?;
        zip.write_all(formats::vtk::particles_vtp(particles).as_bytes())
            .map_err(|e| internal(&e))?;
        series.push((*frame, name));
    }
    zip.start_file("particles.pvd", stored)
        .map_err(|e| internal(&e))?;
    zip.write_all(formats::vtk::pvd(&series).as_bytes())
        .map_err(|e| internal(&e))?;
    zip.start_file("trajectories.vtp", stored)
        .map_err(|e| internal(&e))?;
    zip.write_all(formats::vtk::trajectories_vtp(&collected.trajectories).as_bytes())
        .map_err(|e| internal(&e))?;
    Ok(zip.finish().map_err(|e| internal(&e))?.into_inner())
}

/// The HDF5 file of an export.
pub fn hdf5(collected: &Collected) -> Result<Vec<u8>, ApiError> {
    formats::hdf5::sequence_file(&collected.frames, &collected.trajectories)
        .map_err(|e| ApiError::internal(e.to_string()))
}
