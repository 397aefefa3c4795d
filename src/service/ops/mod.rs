//! The service's operations: what HTTP handlers and workers both call.
//! The shared state ([`state::AppState`]), the image files, the job
//! runtime and its kinds (frame, solve, self-calibration, reprocessing,
//! preprocessing), the live tracking, the event streams, the calibration
//! health.

pub mod computing;
pub mod events;
pub mod health;
pub mod images;
pub mod jobs;
pub mod links;
pub mod preprocessing;
pub mod selfcal;
pub mod state;
pub mod tracking;
