//! Prepared frame pipelines by sequence, kept between frames.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use crate::photogrammetry::{FramePipeline, Splitter};
use crate::service::store::{CalibrationId, SequenceId};

/// Prepared frame pipelines by sequence (preparing one builds the
/// matcher's refraction tables, far more work than a frame), each with the
/// number of the sequence's stored backgrounds and masks it was made with:
/// a sequence's images are only ever added, so a pipeline made with fewer
/// than there are now is stale, whoever added them and when; and with the
/// calibration it was made with (reprocessing switches a sequence's).
#[derive(Debug, Default)]
pub struct PipelineCache {
    pipelines: Mutex<HashMap<SequenceId, (CalibrationId, usize, Prepared)>>,
}

/// A sequence's prepared frame pipeline and its calibration's splitter
/// (whether a frame is one image of several views).
pub type Prepared = (Arc<FramePipeline>, Option<Splitter>);

/// Pipelines kept at most; beyond, the cache starts afresh.
const CACHED_PIPELINES: usize = 32;

impl PipelineCache {
    /// The sequence's pipeline, if prepared with `calibration_id` and
    /// `images` stored backgrounds and masks.
    pub fn get(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
        images: usize,
    ) -> Option<Prepared> {
        let map = self.pipelines.lock().unwrap_or_else(|e| e.into_inner());
        map.get(&sequence_id)
            .filter(|(calibration, made_with, _)| {
                *calibration == calibration_id && *made_with == images
            })
            .map(|(_, _, prepared)| prepared.clone())
    }

    /// Keeps a pipeline prepared with `calibration_id` and `images` stored
    /// backgrounds and masks.
    pub fn insert(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
        images: usize,
        prepared: Prepared,
    ) {
        let mut map = self.pipelines.lock().unwrap_or_else(|e| e.into_inner());
        if map.len() >= CACHED_PIPELINES {
            map.clear();
        }
        map.insert(sequence_id, (calibration_id, images, prepared));
    }
}
