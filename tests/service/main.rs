//! The service, driven over HTTP: the real server on port 0 with a fresh
//! data directory (in process, or the `ptv` binary for the crash test).
//!
//! - `api`: the synthetic 4-camera experiment end to end, OpenPTV import
//!   and the project/intersect helpers, the API token, the committed
//!   OpenAPI document.
//! - `reliability`: a kill -9 while jobs run, and 32 concurrent uploaders.
//! - `bad_inputs`: every kind of bad request gets its 4xx and leaves the
//!   database consistent.
//! - `layers`: what every request passes through: request ids, gzip,
//!   header and body timeouts, the early 413, the bearer token.
//! - `recovery`: a full disk (SQLite's page limit as fault injection) is a
//!   507 and the service recovers without a restart; a failed frame is
//!   processed after `POST /jobs/{id}/retry`.

mod api;
mod bad_inputs;
mod helpers;
mod layers;
mod recovery;
mod reliability;
