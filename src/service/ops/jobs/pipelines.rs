//! A sequence's frame pipeline: its stored parameters and calibration
//! read, the pipeline prepared on the CPU pool with its stored
//! backgrounds and masks, or taken from the cache.

use std::sync::Arc;

use crate::formats::{self, FormatError};
use crate::photogrammetry::{Cancel, FramePipeline, PipelineError, Splitter};
use crate::service::model::parameters::SequenceParameters;
use crate::service::ops::jobs::attempt::JobError;
use crate::service::ops::jobs::cache::Prepared;
use crate::service::ops::jobs::pool::CpuError;
use crate::service::ops::state::AppState;
use crate::service::store::{CalibrationId, SequenceId};

/// Why a frame pipeline could not be prepared.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    /// The stored calibration does not read.
    #[error(transparent)]
    Calibration(#[from] FormatError),
    /// The parameters do not work with the calibration.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// The preparation did not finish.
    #[error("preparing the frame pipeline {0}")]
    Cpu(#[from] CpuError),
}

/// Prepares the frame pipeline of a calibration and parameters, on the CPU
/// pool; not started if `cancel` fired while it waited for a thread (a
/// request whose client has gone). The preparation itself is bounded by
/// the cameras a calibration may have. Also the calibration's splitter.
pub async fn prepare_pipeline(
    state: &AppState,
    calibration_model: &str,
    parameters: &SequenceParameters,
    cancel: &Cancel,
) -> Result<(FramePipeline, Option<Splitter>), PrepareError> {
    let (cameras, splitter) = formats::calibration::stored_from_json_with_splitter(
        calibration_model,
        "the stored calibration",
    )?;
    let detection = parameters.detection();
    let matching = parameters.matching();
    let cancel = cancel.clone();
    state
        .cpu
        .try_run(move || {
            cancel.check().map_err(PipelineError::from)?;
            Ok((
                FramePipeline::new(&cameras, &detection, &matching)?,
                splitter,
            ))
        })
        .await
}

/// A sequence's stored parameters.
pub async fn sequence_parameters(
    state: &AppState,
    sequence_id: SequenceId,
) -> Result<SequenceParameters, JobError> {
    let sequence = state
        .store
        .sequence(sequence_id)
        .await?
        .ok_or_else(|| JobError::Failed(format!("sequence {sequence_id} does not exist")))?;
    Ok(sequence.parameters)
}

/// The sequence's pipeline, from the cache or prepared now, with its
/// backgrounds and masks.
pub async fn pipeline_of(
    state: &AppState,
    sequence_id: SequenceId,
    calibration_id: CalibrationId,
) -> Result<Prepared, JobError> {
    let images = state.store.sequence_images(sequence_id).await?;
    if let Some(prepared) = state
        .pipelines
        .get(sequence_id, calibration_id, images.len())
    {
        return Ok(prepared);
    }
    let count = images.len();
    let parameters = sequence_parameters(state, sequence_id).await?;
    let calibration = state
        .store
        .calibration(calibration_id)
        .await?
        .ok_or_else(|| JobError::Failed(format!("calibration {calibration_id} does not exist")))?;
    let (pipeline, splitter) =
        prepare_pipeline(state, &calibration.model, &parameters, &Cancel::new())
            .await
            .map_err(JobError::failed)?;
    let pipeline = Arc::new(
        crate::service::ops::preprocessing::with_stored_images(state, images, pipeline).await?,
    );
    let prepared = (pipeline, splitter);
    state
        .pipelines
        .insert(sequence_id, calibration_id, count, prepared.clone());
    Ok(prepared)
}
