//! The core against its ground truth, in one test binary: the camera model
//! and intersection against OpenPTV 0.3.2's golden values, correspondences
//! on test_cavity's real frames against OpenPTV's, calibration on simulated
//! rigs and on test_cavity's block, and detection against the renderer's
//! truth. The data are in `tests/data/openptv/` (see its README).
//!
//! One binary rather than one per file: each test binary links the whole
//! crate, service included, so fewer binaries make a cold CI run shorter.

#[path = "../common/mod.rs"]
mod common;

mod calibrate;
mod detect_accuracy;
mod detect_properties;
mod health;
mod ipr;
mod openptv_frames;
mod openptv_golden;
mod real_recording;
mod selfcal;
mod structured_background;
mod wand;
