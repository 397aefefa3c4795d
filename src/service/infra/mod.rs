//! The service's bottom floor: what knows nothing of the database, the
//! jobs or HTTP. Settings, connection handling, the memory budget, the
//! counters, file locks, the blob codec, process and error helpers.

pub mod budget;
pub mod codec;
pub mod config;
pub mod connections;
pub mod errors;
pub mod file_lock;
pub mod metrics;
pub mod process;
pub mod urls;
