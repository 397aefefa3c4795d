//! Issue 29's probe, kept: every hostile request it found, replayed
//! against the `ptv` binary as a child process ([`ServiceProcess`]), each
//! asserting its bound: the status, the server's peak memory (`VmHWM`,
//! [`ServiceProcess::peak_memory_mib`]) and, where it matters, the time.
//!
//! - `import`: names inside an experiment's files never reach the
//!   server's disk; YAML size and depth limits.
//! - `decoders`: PNG ancillary-chunk bombs, detection's early target
//!   limit, targets CSV streamed with its per-camera limit, one status for
//!   undecodable images.
//! - `budget`: the computed background streamed, jobs admitted within the
//!   memory budget.
//! - `edges`: slow bodies, aborted uploads, framing, start-up.
//! - `settings`: bounds on every setting that scales work.
//!
//! [`ServiceProcess`]: super::helpers::ServiceProcess
//! [`ServiceProcess::peak_memory_mib`]: super::helpers::ServiceProcess::peak_memory_mib

mod budget;
mod decoders;
mod edges;
mod import;
mod settings;
