//! Exports of a tracked sequence, from `ptv track --export FORMAT
//! --export-dir DIR` and `ptv process-sequence --track --export FORMAT`:
//! ParaView's VTK XML ([`crate::formats::vtk`]) or one HDF5 file
//! ([`crate::formats::hdf5`]).
//!
//! The tracking pass collects, as it lets each frame go, the frame's
//! particles (position, sigmas, cameras, trajectory) and every trajectory
//! point written (with the fit's velocity, acceleration and their sigmas);
//! the files are written at the end. Its memory is that collection: about
//! 200 bytes per trajectory point and 64 per particle (a 50-frame sequence
//! of 20,000 particles: some 260 MB), plus, for HDF5, the file's bytes.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use clap::ValueEnum;

use super::CliError;
use crate::formats::vtk::{ParticleRecord, TrajectoryPointRecord, TrajectoryRecord};
use crate::formats::{self, FormatError};

/// An export format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ExportFormat {
    /// ParaView's VTK XML: `particles.<frame>.vtp` per frame,
    /// `particles.pvd` (their time series) and `trajectories.vtp`
    /// (polylines).
    Vtk,
    /// One HDF5 file, `sequence.h5`: particles by frame, trajectories as a
    /// table, units in attributes.
    Hdf5,
}

/// What a tracking pass collects for the exports.
#[derive(Default)]
pub(super) struct Collector {
    /// Per frame (in order), its particles.
    pub frames: Vec<(i64, Vec<ParticleRecord>)>,
    /// Per trajectory, its points in frame order.
    pub trajectories: BTreeMap<u64, Vec<TrajectoryPointRecord>>,
}

impl Collector {
    /// The trajectories as records.
    fn trajectories(&self) -> Vec<TrajectoryRecord> {
        self.trajectories
            .iter()
            .map(|(&id, points)| TrajectoryRecord {
                id,
                points: points.clone(),
            })
            .collect()
    }

    /// Writes the files of `format` into `dir` (created if missing);
    /// returns their paths.
    pub(super) fn write(&self, format: ExportFormat, dir: &Path) -> Result<Vec<PathBuf>, CliError> {
        std::fs::create_dir_all(dir).map_err(|reason| FormatError::Io {
            path: dir.to_owned(),
            reason,
        })?;
        let trajectories = self.trajectories();
        let mut written = Vec::new();
        match format {
            ExportFormat::Vtk => {
                let mut series = Vec::new();
                for (frame, particles) in &self.frames {
                    let name = format!("particles.{frame}.vtp");
                    let path = dir.join(&name);
                    formats::write_text(&path, &formats::vtk::particles_vtp(particles))?;
                    series.push((*frame, name));
                    written.push(path);
                }
                let path = dir.join("particles.pvd");
                formats::write_text(&path, &formats::vtk::pvd(&series))?;
                written.push(path);
                let path = dir.join("trajectories.vtp");
                formats::write_text(&path, &formats::vtk::trajectories_vtp(&trajectories))?;
                written.push(path);
            }
            ExportFormat::Hdf5 => {
                let bytes =
                    formats::hdf5::sequence_file(&self.frames, &trajectories).map_err(|e| {
                        CliError::Flag {
                            flag: "--export",
                            reason: e.to_string(),
                        }
                    })?;
                let path = dir.join("sequence.h5");
                std::fs::write(&path, bytes).map_err(|reason| FormatError::Io {
                    path: path.clone(),
                    reason,
                })?;
                written.push(path);
            }
        }
        Ok(written)
    }
}
