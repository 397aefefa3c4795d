//! `ptv`: 3D particle tracking velocimetry photogrammetry.
//!
//! Layers, from the inside out:
//! - [`photogrammetry`]: the pure core: camera model, multimedia refraction,
//!   spatial intersection, simulator. No I/O, no async, no SQL.
//! - [`formats`]: files people already have: the calibration JSON, OpenPTV's
//!   `.ori`/`.addpar`/`ptv.par`, CSV. Parsers name the file, line and field
//!   of every error.
//! - [`cli`]: the `ptv` command line.
//! - [`service`]: the HTTP service (`ptv serve`): API, job queue, workers,
//!   SQLite.

pub mod cli;
pub mod formats;
pub mod photogrammetry;
pub mod service;
