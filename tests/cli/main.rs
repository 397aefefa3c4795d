//! The `ptv` command line, run as a real process in temporary directories,
//! in one test binary: OpenPTV's files in and out, project and intersect,
//! detect, match and process, calibrate, background, OpenPTV experiments,
//! simulated sequences, track, plot.
//!
//! One binary rather than one per file: each test binary links the whole
//! crate, service included, so fewer binaries make a cold CI run shorter.

#[path = "../common/mod.rs"]
mod common;

mod background;
mod between_tools;
mod calibrate;
mod detect;
mod experiment;
mod matching;
mod openptv_files;
mod plot;
mod reconstruct;
mod selfcalibrate;
mod simulate;
mod track;
