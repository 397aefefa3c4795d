//! The particles a round adjusts: every frame matched with the round's band
//! (or voted where the band is wide), only confident particles kept
//! (uncrowded targets, enough cameras), spread evenly over the volume
//! (module docs of [`super`]).

use nalgebra::Point2;

use super::bundle::Track;
use super::report;
use super::{SelfCalibrationError, SelfCalibrationOptions};
use crate::photogrammetry::camera::{Camera, CameraParameters};
use crate::photogrammetry::cancel::Cancel;
use crate::photogrammetry::correspond::{MatchError, Matcher, MatchingParameters, Particle};
use crate::photogrammetry::target::Target;
use crate::photogrammetry::volume::Volume;

/// Bands wider than this (px) vote ([`vote`]) rather than match: in them
/// the matcher's best-fitting groups are mostly ghosts.
pub(super) const VOTE_ABOVE_PX: f64 = 1.0;

pub(super) type Matched = (Vec<Track>, Vec<usize>, usize);

/// The confident particles of every frame matched with `band`, as tracks;
/// the particles matched by camera count; the confident ones.
#[allow(clippy::too_many_arguments)]
pub(super) fn matched_tracks(
    frames: &[Vec<Vec<Target>>],
    models: &[Camera],
    band: f64,
    min_cameras: usize,
    volume: &Volume,
    options: &SelfCalibrationOptions,
    cancel: &Cancel,
    progress: &mut dyn FnMut(usize),
) -> Result<Matched, SelfCalibrationError> {
    let matcher = Matcher::new(models, &matching(band, options)).map_err(|source| {
        SelfCalibrationError::Matching {
            band_px: band,
            source,
        }
    })?;
    let mut matched_by_cameras = vec![0; models.len() + 1];
    let mut candidates: Vec<Candidate> = Vec::new();
    for (f, frame) in frames.iter().enumerate() {
        cancel.check()?;
        let particles = matcher
            .match_frame_until(frame, cancel)
            .map_err(|e| match e {
                MatchError::Cancelled(c) => SelfCalibrationError::Cancelled(c),
                source => SelfCalibrationError::Matching {
                    band_px: band,
                    source,
                },
            })?;
        let crowded = crowded_targets(frame, options.isolation_px);
        for p in &particles {
            matched_by_cameras[p.camera_count()] += 1;
            if confident(p, &crowded, min_cameras) {
                candidates.push(Candidate {
                    frame: f,
                    particle: p.clone(),
                });
            }
        }
        progress(f + 1);
    }
    let candidate_count = candidates.len();
    let selected = select(candidates, volume, options);
    let tracks = selected
        .iter()
        .map(|c| Track {
            observations: c
                .particle
                .targets
                .iter()
                .enumerate()
                .filter_map(|(cam, t)| {
                    t.map(|t| {
                        let target = &frames[c.frame][cam][t];
                        (cam, Point2::new(target.x, target.y), 1.0)
                    })
                })
                .collect(),
            point: c.particle.position,
        })
        .collect();
    Ok((tracks, matched_by_cameras, candidate_count))
}

/// A matched particle of one frame.
pub(super) struct Candidate {
    frame: usize,
    pub(super) particle: Particle,
}

pub(super) fn matching(band: f64, options: &SelfCalibrationOptions) -> MatchingParameters {
    MatchingParameters {
        tolerance: band,
        volume: options.volume,
        min_cameras: 2,
        similarity: None,
    }
}

pub(super) fn models(cameras: &[CameraParameters]) -> Result<Vec<Camera>, SelfCalibrationError> {
    cameras
        .iter()
        .enumerate()
        .map(|(camera, p)| {
            Camera::new(p.clone())
                .map_err(|source| SelfCalibrationError::InvalidCamera { camera, source })
        })
        .collect()
}

pub(super) fn models_or_diverged(cameras: &[CameraParameters]) -> Option<Vec<Camera>> {
    cameras
        .iter()
        .map(|p| Camera::new(p.clone()).ok())
        .collect()
}

/// Per camera of a frame, which targets have another within `radius` px.
pub(super) fn crowded_targets(frame: &[Vec<Target>], radius: f64) -> Vec<Vec<bool>> {
    frame
        .iter()
        .map(|targets| {
            let mut order: Vec<usize> = (0..targets.len()).collect();
            order.sort_by(|&a, &b| targets[a].x.total_cmp(&targets[b].x));
            let mut crowded = vec![false; targets.len()];
            for (k, &i) in order.iter().enumerate() {
                for &j in &order[k + 1..] {
                    if targets[j].x - targets[i].x > radius {
                        break;
                    }
                    let d = (targets[j].x - targets[i].x).hypot(targets[j].y - targets[i].y);
                    if d <= radius {
                        crowded[i] = true;
                        crowded[j] = true;
                    }
                }
            }
            crowded
        })
        .collect()
}

pub(super) fn confident(p: &Particle, crowded: &[Vec<bool>], min_cameras: usize) -> bool {
    p.camera_count() >= min_cameras
        && p.targets
            .iter()
            .enumerate()
            .all(|(c, t)| t.map_or(true, |t| !crowded[c][t]))
}

/// At most `max_particles / cells` per sub-volume, the most cameras and
/// then the best fitting first.
pub(super) fn select(
    mut candidates: Vec<Candidate>,
    volume: &Volume,
    options: &SelfCalibrationOptions,
) -> Vec<Candidate> {
    let grid = options.grid;
    let cells = grid[0] * grid[1] * grid[2];
    let cap = options.max_particles.div_ceil(cells).max(1);
    candidates.sort_by(|a, b| {
        b.particle
            .camera_count()
            .cmp(&a.particle.camera_count())
            .then(a.particle.rms_px.total_cmp(&b.particle.rms_px))
    });
    let mut filled = vec![0usize; cells];
    candidates
        .into_iter()
        .filter(|c| {
            let cell = report::flat(grid, report::cell_of(volume, grid, &c.particle.position));
            filled[cell] += 1;
            filled[cell] <= cap
        })
        .take(options.max_particles)
        .collect()
}
