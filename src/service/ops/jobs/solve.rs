//! The `solve_calibration` job: a calibration solved by resection from
//! the files of a `/calibrations/solve` request, kept in the image store
//! and listed in `job_files`.

use super::attempt::{JobError, JobRun};
use super::pool::CpuError;
use crate::formats::control::{self, OptionError};
use crate::formats::{self, FormatError};
use crate::photogrammetry::calibrate::{self, CalibrationError};
use crate::photogrammetry::InvalidDetectionParameters;
use crate::service::model::parameters::SolveOptions;
use crate::service::ops::images::remove_unused_images;
use crate::service::ops::state::AppState;
use crate::service::store::JobFile;
use serde::Deserialize;
use std::sync::Arc;

/// A solve_calibration job's payload: its options, checked when the
/// request was taken; its inputs are its `job_files`.
#[derive(Debug, Deserialize, serde::Serialize)]
pub struct SolvePayload {
    /// `options`, as given.
    pub options: SolveOptions,
}

/// How a part of a `/calibrations/solve` request is named in messages.
pub fn part_source(part: &str, camera: Option<usize>) -> String {
    match camera {
        Some(camera) => format!("part `{part}` of camera {camera}"),
        None => format!("part `{part}`"),
    }
}

/// Why a solve request's files do not give a calibration.
#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    /// A file does not parse.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A text part is not text (its source named).
    #[error("{0} is not UTF-8 text")]
    NotText(String),
    /// A part this job does not know.
    #[error("unknown input part `{0}`")]
    UnknownPart(String),
    /// A part that must be there is not.
    #[error("the `{0}` part is missing")]
    Missing(&'static str),
    /// An option is invalid.
    #[error("options.{0}")]
    Options(#[from] OptionError),
    /// The marks' detection parameters are invalid.
    #[error("options.detection")]
    Detection(#[from] InvalidDetectionParameters),
    /// A camera's image gave more marks than its limit.
    #[error("the image of camera {camera}: {error}")]
    Marks {
        /// The camera, from 0.
        camera: usize,
        /// Why.
        error: crate::photogrammetry::DetectError,
    },
    /// The calibration itself failed.
    #[error(transparent)]
    Calibration(#[from] CalibrationError),
    /// The work did not finish.
    #[error("the calibration {0}")]
    Cpu(#[from] CpuError),
}

/// Text of a part, or what is wrong with it.
pub fn part_text(bytes: Vec<u8>, source: &str) -> Result<String, SolveError> {
    String::from_utf8(bytes).map_err(|_| SolveError::NotText(source.to_owned()))
}

/// Calibrates from a solve request's files (part, camera, bytes; per-camera
/// parts in camera order): the calibration JSON, its camera count and the
/// report JSON. CPU work: run it on the pool.
pub fn solve(
    files: Vec<(JobFile, Vec<u8>)>,
    options: &SolveOptions,
) -> Result<(String, i64, String), SolveError> {
    let (mut setup, mut control_points) = (None, None);
    let (mut observations, mut references, mut images) = (Vec::new(), Vec::new(), Vec::new());
    for (file, bytes) in files {
        let source = part_source(&file.part, file.camera.map(|c| c as usize));
        match file.part.as_str() {
            "setup" => {
                let text = part_text(bytes, &source)?;
                setup = Some(formats::calibration::setup_from_json(&text, &source)?);
            }
            "control" => {
                let text = part_text(bytes, &source)?;
                control_points = Some(control::parse_control_points(&text, &source)?);
            }
            "observations" | "reference" => {
                let text = part_text(bytes, &source)?;
                let marks = control::parse_mark_observations(&text, &source)?;
                if file.part == "observations" {
                    observations.push(marks);
                } else {
                    references.push(marks);
                }
            }
            "image" => images.push(formats::image::decode_image(&bytes, &source)?),
            other => return Err(SolveError::UnknownPart(other.to_owned())),
        }
    }
    let formats::calibration::Setup {
        cameras: setup,
        unknown,
    } = setup.ok_or(SolveError::Missing("setup"))?;
    let control_points = control_points.ok_or(SolveError::Missing("control"))?;
    let calibration_options = calibrate::CalibrationOptions {
        unknown,
        ..options.calibration_options()?
    };
    let result = if images.is_empty() {
        calibrate::calibrate(&setup, &control_points, &observations, &calibration_options)
    } else {
        let parameters = options.mark_detection()?;
        let marks = images
            .iter()
            .enumerate()
            .map(|(camera, image)| {
                calibrate::detect_marks(image, &parameters)
                    .map_err(|error| SolveError::Marks { camera, error })
            })
            .collect::<Result<Vec<_>, _>>()?;
        if references.is_empty() {
            references = vec![Vec::new(); setup.len()];
        }
        calibrate::calibrate_from_marks(
            &setup,
            &control_points,
            &marks,
            &references,
            &calibration_options,
        )
    }?;
    let cameras = result.camera_models()?;
    let model = formats::calibration::to_json(&cameras);
    // Stored only if it reads back: a solve that ran out of the ranges
    // real cameras have (a diverged adjustment) fails, naming the value.
    formats::calibration::from_json(&model, "the solved calibration")?;
    Ok((
        model,
        cameras.len() as i64,
        control::report_to_json(&result.report),
    ))
}

/// What a solve_calibration job needs of the memory budget: its images
/// decoded all at once (2 bytes a sample at most) and the largest one's
/// marks detected ([`crate::service::infra::budget::DETECT_BYTES_PER_PIXEL`]), from the
/// images' headers; an image whose header does not read fails later in
/// [`solve`] with the reason.
fn solve_need(files: &[(JobFile, Vec<u8>)]) -> crate::service::infra::budget::MemoryNeed {
    let pixels: Vec<u64> = files
        .iter()
        .filter(|(file, _)| file.part == "image")
        .filter_map(|(_, bytes)| {
            formats::image::probe_image(std::io::Cursor::new(bytes), "an image").ok()
        })
        .map(|header| u64::from(header.width) * u64::from(header.height))
        .collect();
    let largest = pixels.iter().copied().max().unwrap_or(0);
    let bytes = pixels.iter().sum::<u64>().saturating_mul(2).saturating_add(
        largest.saturating_mul(crate::service::infra::budget::DETECT_BYTES_PER_PIXEL),
    );
    crate::service::infra::budget::MemoryNeed::new(
        bytes,
        format!(
            "solving a calibration from {} image(s) of {} pixels in all",
            pixels.len(),
            pixels.iter().sum::<u64>()
        ),
    )
}

/// The solve_calibration job: calibrates from the request's files and
/// stores the calibration with its report, completing the job in the same
/// transaction; with `keep_images: false` its files go afterwards.
pub async fn solve_calibration(state: Arc<AppState>, run: JobRun) -> Result<(), JobError> {
    let payload: SolvePayload = serde_json::from_str(&run.job.payload)
        .map_err(|e| JobError::Failed(format!("malformed payload: {e}")))?;
    let mut files = Vec::new();
    for file in state.store.job_files(run.job.id).await? {
        let bytes = state.images.read(&file.sha256).await.map_err(|e| {
            let part = part_source(&file.part, file.camera.map(|c| c as usize));
            JobError::image(&format!("the file of {part}"), e)
        })?;
        files.push((file, bytes));
    }
    let grant = state.budget.acquire(&solve_need(&files)).await?;
    let options = payload.options.clone();
    let (model, cameras, report) = state
        .cpu
        .try_run(move || solve(files, &options))
        .await
        .map_err(JobError::failed)?;
    drop(grant);
    let (_, released) = state
        .store
        .complete_calibration(
            &run.job,
            &model,
            cameras,
            &report,
            payload.options.keep_images.unwrap_or(true),
            run.elapsed_s(),
        )
        .await?;
    remove_unused_images(&state.store, &state.images, &released).await;
    Ok(())
}
