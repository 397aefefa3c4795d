//! `POST /experiments/openptv`: an OpenPTV or pyptv experiment in one call
//! (issue 13). The request carries the experiment's files as multipart
//! parts `file` whose file names are their paths inside the experiment
//! directory (`parameters/ptv.par`, `parameters/criteria.par`, ...,
//! `cal/cam1.tif.ori`, `cal/cam1.tif.addpar`, or a pyptv
//! `parameters_Run1.yaml`, and masks where its masking is on: with curl,
//! `-F 'file=@parameters/ptv.par;filename=parameters/ptv.par'`); they are
//! written into a scratch directory under names of the service's own
//! (never the client's paths) and read by the same importer as `ptv
//! experiment import`, through the uploaded set
//! ([`crate::formats::experiment::UploadedFiles`]): a name inside the
//! experiment's files (`cal_ori`'s `.ori` files, pyptv's `img_ori` and
//! `mask_base_name`) resolves only to a file sent with it. An absolute
//! name, one with `..` or one that is no plain path is refused (400, the
//! file, line and name said); a clean name that was not sent is missing
//! (422). Nothing else on the server's disk is opened, and errors name the
//! files as the client sent them.
//! The calibration (with its splitter), a sequence with every detection and
//! matching setting the experiment has, and its masking images are stored
//! in one transaction. pyptv subtracts its masking images from the frames
//! (saturating), so they become the sequence's backgrounds, which are
//! subtracted the same way (not its masks, whose zero pixels are dropped).
//! The answer lists the settings `ptv` does not use and the image names
//! and frames the experiment records, for the uploader.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::extract::{Multipart, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::{Json, Router};
use serde::Serialize;
use tokio::io::AsyncWriteExt;
use utoipa::ToSchema;

use super::extract::Shared;
use super::problem::{ApiError, ApiMultipart};
use super::upload::{check_images, or_drain, persist_and_commit, text_part};
use crate::formats;
use crate::formats::experiment::{
    read_experiment_from, Experiment, ExperimentError, ExperimentFiles, UploadedFiles,
};
use crate::photogrammetry::{Cancel, StopOnDrop};
use crate::service::model::parameters::{experiment_settings, SequenceParameters};
use crate::service::ops::images::UploadedFile;
use crate::service::ops::jobs::pipelines::prepare_pipeline;
use crate::service::ops::links;
use crate::service::ops::state::AppState;
use crate::service::store::{CalibrationId, NewSequenceImage, SequenceId};

/// Files an experiment upload may have.
const MAX_FILES: usize = 128;

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new().route("/experiments/openptv", post(import))
}

/// The calibration and sequence an experiment became.
#[derive(Debug, Serialize, ToSchema)]
pub struct ImportedExperiment {
    /// The calibration.
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
    /// The sequence, processed with the experiment's settings.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// Where the calibration is.
    pub calibration: String,
    /// Where the sequence is; upload its frames to `{sequence}/frames`.
    pub sequence: String,
    /// The experiment's image names, per camera (one with a splitter), a
    /// printf-style `%d` for the frame number, relative to its directory.
    pub images: Vec<String>,
    /// Its first frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub first_frame: u64,
    /// Its last frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub last_frame: u64,
    /// The tracking run created with the experiment's `track.par` (pyptv's
    /// `track:`) settings: `max_velocity` from the `dv*` box,
    /// `max_acceleration` from `dacc`, `recovery` from `flagNewParticles`,
    /// from its first frame on; null where the experiment has none. Its
    /// trajectories grow as frames are uploaded and processed.
    #[schema(value_type = Option<i64>)]
    pub tracking_run_id: Option<crate::service::store::TrackingRunId>,
    /// Where its trajectories are (`{sequence}/trajectories`), where it has
    /// a tracking run.
    pub trajectories: Option<String>,
    /// The settings `ptv` does not use, and why.
    pub unmapped: Vec<UnmappedView>,
}

/// A setting read but not used.
#[derive(Debug, Serialize, ToSchema)]
pub struct UnmappedView {
    /// The file it is in.
    pub file: String,
    /// Its key (`criteria.cn`).
    pub key: String,
    /// Its value as written.
    pub value: String,
    /// Why `ptv` does not use it.
    pub reason: String,
}

/// Creates a calibration and a sequence from an OpenPTV experiment's files.
#[utoipa::path(
    post, path = "/api/v1/experiments/openptv", tag = "experiments",
    request_body(content_type = "multipart/form-data", description = "One part `file` per file of the experiment, its file name the path inside the experiment directory: `parameters/ptv.par`, `parameters/criteria.par`, `parameters/targ_rec.par`, `parameters/sequence.par`, `parameters/cal_ori.par`, ... (or one pyptv `parameters_NAME.yaml`), the `.ori` and `.addpar` files the calibration names (`cal/cam1.tif.ori`, ...), and the masking images where masking is on (they become the sequence's backgrounds: pyptv subtracts them). Optional text parts `name` (the sequence's) and `keep_images` (`true`/`false`)."),
    responses(
        (status = 201, body = ImportedExperiment),
        (status = 400, description = "Malformed multipart, a path that leaves the directory, a file given twice, a name inside the experiment's files that is absolute, has `..` or is no plain relative path (the file, line and name said)", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "A file that does not parse (file, line and key named), a file the experiment names that was not sent, settings that do not work together", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn import(
    State(state): Shared,
    ApiMultipart(mut multipart): ApiMultipart,
) -> Result<Response, ApiError> {
    let scratch = Scratch::new(&state).await?;
    let read = read_files(&scratch.dir, &mut multipart).await;
    let (files, name, keep_images) = or_drain(read, &mut multipart).await?;
    let files = Arc::new(files);
    let uploaded = files.clone();
    let experiment =
        tokio::task::spawn_blocking(move || read_experiment_from(&*uploaded, Path::new("")))
            .await
            .map_err(ApiError::internal)?
            .map_err(experiment_error)?;
    // Its frames are uploaded as frame numbers, 0 to MAX_FRAME_NUMBER.
    if experiment.sequence.last > crate::service::store::MAX_FRAME_NUMBER as u64 {
        return Err(ApiError::unprocessable(format!(
            "sequence.last: {} is above the largest frame number, {}; number the frames from \
             0 to {}",
            experiment.sequence.last,
            crate::service::store::MAX_FRAME_NUMBER,
            crate::service::store::MAX_FRAME_NUMBER
        )));
    }
    let sequence_json = settings_json(&experiment)?;
    let masks = mask_files(&state, &experiment, &files).await?;

    // The same checks as `POST /sequences`: the parameters must work with
    // the cameras.
    let model =
        formats::calibration::to_json_with_splitter(&experiment.cameras, experiment.splitter);
    let parameters: SequenceParameters = serde_json::from_str(&sequence_json)?;
    let cancel = Cancel::new();
    let _stop = StopOnDrop(cancel.clone());
    let (pipeline, splitter) = prepare_pipeline(&state, &model, &parameters, &cancel).await?;

    // The tracking run's settings, checked before anything is stored.
    let tracking = match &experiment.tracking {
        Some(t) => {
            let p = &t.parameters;
            let settings = crate::service::model::tracking_settings::TrackingSettings {
                max_velocity: p.max_velocity,
                max_acceleration: Some(p.max_acceleration),
                max_gap: Some(p.max_gap),
                min_length: Some(p.min_length),
                fit_half_window: Some(p.fit_half_window),
                fit_order: Some(p.fit_order),
                first_frame: Some(crate::service::store::FrameNumber(
                    experiment.sequence.first as i64,
                )),
                recovery: Some(t.recovery),
                // The run's default (pyptv's tracking back is a step of
                // its own, and off here by default: docs/tracking.md).
                backward: None,
            }
            .with_defaults()?;
            if let Some(volume) = &experiment.matching.volume {
                settings.check_volume(volume)?;
            }
            Some(settings)
        }
        None => None,
    };
    let name = name.unwrap_or_else(|| "openptv".to_owned());
    let (files, rows): (Vec<UploadedFile>, Vec<_>) = masks.into_iter().unzip();
    let cameras = experiment.cameras.len() as i64;
    let (calibration, sequence) = persist_and_commit(&state, files, || {
        state
            .store
            .insert_experiment(&model, cameras, &name, &parameters, keep_images, &rows)
    })
    .await?;
    state.pipelines.insert(
        sequence.id,
        calibration.id,
        rows.len(),
        (Arc::new(pipeline), splitter),
    );
    drop(scratch);
    let mut tracking_run_id = None;
    if let Some(settings) = &tracking {
        let run = state
            .store
            .insert_tracking_run(sequence.id, settings)
            .await?
            .ok_or_else(|| ApiError::internal("the sequence just created is gone"))?;
        tracking_run_id = Some(run.id);
        crate::service::ops::tracking::kick(&state, sequence.id);
    }
    let body = ImportedExperiment {
        tracking_run_id,
        trajectories: tracking_run_id
            .map(|_| format!("{}/trajectories", links::sequence(sequence.id))),
        calibration_id: calibration.id,
        sequence_id: sequence.id,
        calibration: links::calibration(calibration.id),
        sequence: links::sequence(sequence.id),
        images: experiment
            .sequence
            .base_names
            .iter()
            .map(|p| p.as_str().to_owned())
            .collect(),
        first_frame: experiment.sequence.first,
        last_frame: experiment.sequence.last,
        unmapped: experiment
            .unmapped
            .into_iter()
            .map(|u| UnmappedView {
                file: u.file,
                key: u.key,
                value: u.value,
                reason: u.reason,
            })
            .collect(),
    };
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, links::sequence(sequence.id))],
        Json(body),
    )
        .into_response())
}

/// A request's scratch directory under the image store's `tmp/` (emptied
/// at every start), removed when dropped.
struct Scratch {
    dir: PathBuf,
}

impl Scratch {
    async fn new(state: &AppState) -> Result<Scratch, ApiError> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default();
        let dir = state
            .images
            .temp_dir()
            .join(format!("experiment-{}-{nanos}", std::process::id()));
        tokio::fs::create_dir_all(&dir).await?;
        Ok(Scratch { dir })
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if let Err(error) = std::fs::remove_dir_all(&self.dir) {
            tracing::warn!(%error, dir = %self.dir.display(), "cannot remove a scratch directory");
        }
    }
}

/// The file parts as an uploaded set, each written into `dir` under its
/// number (the client's path is only the set's key); the `name` and
/// `keep_images` text parts.
async fn read_files(
    dir: &Path,
    multipart: &mut Multipart,
) -> Result<(UploadedFiles, Option<String>, bool), ApiError> {
    let (mut name, mut keep_images, mut files) = (None, true, 0);
    let mut set = UploadedFiles::new();
    while let Some(mut field) = multipart.next_field().await? {
        let part = field.name().unwrap_or("").to_owned();
        match part.as_str() {
            "name" => {
                let text = text_part(&mut field, &part, 200).await?;
                super::sequences::check_name(&text)?;
                name = Some(text);
            }
            "keep_images" => {
                let text = text_part(&mut field, &part, 16).await?;
                keep_images = text.trim().parse().map_err(|_| {
                    ApiError::unprocessable(format!(
                        "part `keep_images` is `{}`; give true or false",
                        text.escape_debug()
                    ))
                })?;
            }
            "file" => {
                files += 1;
                if files > MAX_FILES {
                    return Err(ApiError::bad_request(format!(
                        "more than {MAX_FILES} files; an experiment needs its parameter files, \
                         the calibration's .ori/.addpar files and its masks"
                    )));
                }
                let name = field.file_name().unwrap_or("").to_owned();
                let path = dir.join(files.to_string());
                let added = set.insert_stored(&name, path.clone()).map_err(|why| {
                    ApiError::bad_request(format!(
                        "file `{}`: {}; give each `file` part its path inside the experiment \
                         directory as its file name, e.g. `parameters/ptv.par`",
                        name.escape_debug(),
                        why.0
                    ))
                })?;
                if !added {
                    return Err(ApiError::bad_request(format!(
                        "file `{}` is given twice",
                        name.escape_debug()
                    )));
                }
                let mut file = tokio::fs::File::create_new(&path).await?;
                while let Some(chunk) = field.chunk().await? {
                    file.write_all(&chunk).await?;
                }
                file.flush().await?;
            }
            _ => {
                return Err(ApiError::bad_request(format!(
                    "unknown part `{}`; send the experiment's files as parts `file` (their file \
                     names their paths inside the experiment), and optionally `name` and \
                     `keep_images`",
                    part.escape_debug()
                )))
            }
        }
    }
    if files == 0 {
        return Err(ApiError::bad_request(
            "no files; send the experiment's files as parts `file` whose file names are \
             their paths, e.g. `parameters/ptv.par` and `cal/cam1.tif.ori`",
        ));
    }
    Ok((set, name, keep_images))
}

/// An importer's error as a 400 (a name the upload may not follow) or a
/// 422, naming the files as sent.
fn experiment_error(error: ExperimentError) -> ApiError {
    match error {
        ExperimentError::Refused { .. } => ApiError::bad_request(error.to_string()),
        ExperimentError::Missing {
            file,
            location,
            missing,
        } => ApiError::unprocessable(format!(
            "{}: {location}: names `{}`, which was not sent; send it as a part `file` with that \
             file name, or correct the name",
            file.display(),
            missing.display().to_string().escape_debug()
        )),
        ExperimentError::NotAnExperiment { reason, .. } => {
            ApiError::unprocessable(format!("the files sent: {reason}"))
        }
        error => ApiError::unprocessable(crate::service::infra::errors::error_chain(&error)),
    }
}

/// The sequence's parameters, defaults filled in, as stored JSON.
fn settings_json(experiment: &Experiment) -> Result<String, ApiError> {
    let (detection, matching) = experiment_settings(experiment);
    let parameters = SequenceParameters::with_defaults(detection, matching);
    Ok(serde_json::to_string(&parameters)?)
}

/// The experiment's masking images as files for the image store, with their
/// rows, each checked against its camera's
/// sensor: the sequence's backgrounds, as pyptv subtracts them.
async fn mask_files(
    state: &AppState,
    experiment: &Experiment,
    uploaded: &Arc<UploadedFiles>,
) -> Result<Vec<(UploadedFile, NewSequenceImage)>, ApiError> {
    let Some(masks) = &experiment.masks else {
        return Ok(Vec::new());
    };
    let mut files = Vec::with_capacity(masks.len());
    for path in masks {
        let (set, key) = (uploaded.clone(), path.clone());
        let bytes = tokio::task::spawn_blocking(move || set.read(&key))
            .await
            .map_err(ApiError::internal)??;
        let mut upload = state.images.create_upload().await?;
        upload.write(&bytes).await?;
        files.push(upload.finish().await?);
    }
    let sensors: Vec<_> = experiment
        .cameras
        .iter()
        .map(|c| c.sensor().clone())
        .collect();
    let names: Vec<String> = masks.iter().map(|p| p.display().to_string()).collect();
    let headers = check_images(&files, &sensors, None, move |c| {
        format!("mask `{}`", names[c])
    })
    .await?;
    Ok(files
        .into_iter()
        .zip(headers)
        .enumerate()
        .map(|(camera, (file, header))| {
            let row = NewSequenceImage {
                camera: camera as i64,
                sha256: file.sha256.clone(),
                size: file.size as i64,
                bits: i64::from(header.bit_depth.bits()),
            };
            (file, row)
        })
        .collect())
}
