//! The service's domain types that the store's rows carry and every floor
//! above it reads: a sequence's parameters, its tracking settings, the
//! job kinds. Nothing here touches the database, the jobs or HTTP.

pub mod ids;
pub mod job_kind;
pub mod parameters;
pub mod raw_layout;
pub mod tracking_settings;
