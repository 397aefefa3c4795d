//! The service, driven over HTTP: the real server on port 0 with a fresh
//! data directory (in process, or the `ptv` binary for the crash test).
//!
//! - `api`: the synthetic 4-camera experiment end to end, OpenPTV import
//!   and the project/intersect helpers, the API token, the committed
//!   OpenAPI document.
//! - `reliability`: a kill -9 while jobs run, and 32 concurrent uploaders;
//!   `ptv serve --workers 0` with two `ptv worker` processes, one killed
//!   in the middle of a job, which the other takes over once its lease
//!   has run out and completes exactly once.
//! - `calibration_health`: a simulated run whose camera 2 turns by 0.5
//!   mrad over 200 frames raises its drift alarm at the frame the core's
//!   monitor gives (event, gauges, picture); a steady rig none; bad
//!   requests' 4xx.
//! - `bad_inputs`: every kind of bad request gets its 4xx and leaves the
//!   database consistent.
//! - `hostile`: issue 29's probe of hostile requests, each held to its
//!   bound (status, the server's peak memory, time).
//! - `job_bounds`: projections per request bounded, a frame past its time
//!   limit failed and its worker freed, corrupt images refused at upload.
//! - `layers`: what every request passes through: request ids, gzip,
//!   header and body timeouts, the early 413, the bearer token before
//!   routing, bounded metrics labels.
//! - `leases`: the store's lease rules (claims, renewals, fences, the
//!   attempt limit, the reaper, a tracking run's one holder) on the engine
//!   under test.
//! - `live`: a sequence's events (server-sent events) in order as its
//!   frames are uploaded and processed, 404 and the token before a stream,
//!   the stream's end at shutdown; the lists newest first, a page at a
//!   time.
//! - `page`: the web page in a real headless Chromium (`browser`: the
//!   DevTools protocol over a pipe) on a simulated experiment: what each
//!   view shows, live progress, the camera switch, the 3D view's rotation,
//!   the token, no console errors; screenshots in `target/tmp/screenshots`.
//! - `fuzz`: multipart uploads to every multipart route, fuzzed (seeded;
//!   `PTV_FUZZ_CASES` for longer runs), and the 10,000-camera calibration.
//! - `connections`: the connection limit under idle and slowloris
//!   connections, and refused uploads drained before the close.
//! - `experiments`: the real test_cavity recording imported in one call
//!   from its `.par` files and from its YAML, a frame of it processed;
//!   bad experiments refused by file and line; a splitter's one image cut
//!   into its cameras' views.
//! - `plots`: the pictures: marks where the data are (target rings on
//!   the targets, particles in their views, residual arrows from where
//!   their points were measured; disparity and trajectory pictures checked
//!   from the `selfcal` and `tracking` tests), and their 404, 400 and 409.
//! - `preprocessing`: a sequence's uploaded or computed background
//!   removes static structure, a mask keeps targets out, and bad
//!   backgrounds and masks change nothing.
//! - `recovery`: a full disk (SQLite's page limit as fault injection) is a
//!   507 and the service recovers without a restart; a failed frame is
//!   processed after `POST /jobs/{id}/retry`.
//! - `selfcal`: a simulated sequence with a disturbed calibration
//!   self-calibrated from its stored targets (the new calibration linked
//!   to its origin and closer to the truth), its frames reprocessed and
//!   their particles naming the calibration; bad requests' 4xx.
//! - `tracking`: a simulated sequence of moving particles uploaded out of
//!   order by 4 clients is tracked exactly as the core's tracker tracks
//!   its particles in order, also across a kill -9 and a restart, and by
//!   two `ptv worker` processes, the run's holder killed; a re-run
//!   with other settings is a new run next to the old one; bad settings
//!   and queries refused.
//! - `upload`: `ptv upload` against the service and a flaky stand-in:
//!   concurrent, resumable, retried uploads and their summary.
//! - `postgres`: with `PTV_TEST_DATABASE=postgres` every server above runs
//!   against a fresh database on a real PostgreSQL this process starts
//!   (the SQLite-only fault tests skip themselves; the outage test, in
//!   `reliability`, runs only then).

mod api;
mod bad_inputs;
mod browser;
mod calibration_health;
mod connections;
mod experiments;
mod fuzz;
mod helpers;
mod hostile;
mod job_bounds;
mod layers;
mod leases;
mod live;
mod page;
mod plots;
mod postgres;
mod preprocessing;
mod recovery;
mod reliability;
mod selfcal;
mod tracking;
mod upload;
