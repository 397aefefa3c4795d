//! `ptv`: 3D particle tracking velocimetry, the photogrammetric part, after
//! Maas, Gruen and Papantoniou (1993). Cameras (2 and up) film tracer
//! particles in water through glass walls; `ptv` calibrates them, finds the
//! particles' images in each frame, decides which images belong to one
//! particle, and gives its 3D position with its accuracy.
//!
//! The same core runs behind two doors, the command line (`ptv ...`) and
//! the HTTP service (`ptv serve`, the default), and the tests check it
//! against the simulator's truth and OpenPTV 0.3.2's results.
//!
//! # Layout
//!
//! From the inside out; each layer uses only the ones before it.
//!
//! [`photogrammetry`]: the pure core. Synchronous and deterministic: no I/O,
//! no async runtime, web framework or SQL; plain structs and nalgebra types
//! in, results or typed errors out. Section and equation numbers refer to
//! the paper.
//!
//! - [`camera`](photogrammetry::camera): the camera model, 16 parameters
//!   (exterior and interior orientation, distortion and affine terms, Eq.
//!   1-5); projection, its Jacobian, and the ray of a pixel.
//! - [`media`](photogrammetry::media): refraction through any number of
//!   plane walls, both directions (Eq. 6-17).
//! - [`intersect`](mod@photogrammetry::intersect): least-squares spatial
//!   intersection of a point's images (section 4.3, Eq. 21-23).
//! - [`volume`](photogrammetry::volume): the observation volume, a box.
//! - [`target`](photogrammetry::target): a particle image in one camera.
//! - [`image`](photogrammetry::image): greyscale images, 8 or 16 bits, and
//!   their check against a camera's sensor.
//! - [`detect`](mod@photogrammetry::detect): the particle images (targets)
//!   in one image (section 6.1).
//! - [`centroid`](photogrammetry::centroid): a target's sub-pixel position,
//!   the weighted centroid or a 3-point Gaussian fit per axis.
//! - [`correspond`](photogrammetry::correspond): which targets in 2..N
//!   cameras belong to one particle, by epipolar geometry through the walls
//!   (section 6.2), and the particles' 3D positions.
//! - [`pipeline`](photogrammetry::pipeline): one frame's images to
//!   particles, detection then correspondences, prepared once per
//!   calibration.
//! - [`cancel`](photogrammetry::cancel): a stop flag with a deadline that
//!   long work checks, so a job past its time limit or a request whose
//!   client left stops.
//! - [`calibrate`](mod@photogrammetry::calibrate): system calibration by
//!   resection on control points (section 5), from image coordinates or
//!   detected marks, with held parameters, gross-error detection, check
//!   points and a report.
//! - [`selfcal`](photogrammetry::selfcal): volume self-calibration from
//!   the particles (Wieneke 2008): wide-band matching, confident particles,
//!   a robust bundle adjustment through the walls with the gauge fixed from
//!   the input calibration, narrowing bands; disparity report; wand
//!   calibration on the same adjustment.
//! - [`track`](photogrammetry::track): tracking in time (Malik et al.
//!   1993): particles of successive frames linked into trajectories with
//!   velocities and accelerations, and particles recovered in image space.
//! - [`health`](photogrammetry::health): calibration health during a run:
//!   per camera the disparity of well-matched particles, and a drift alarm.
//! - [`background`](photogrammetry::background): a recording's background
//!   (median or minimum per pixel over frames).
//! - [`splitter`](photogrammetry::splitter): cameras that are views of one
//!   sensor.
//! - [`simulate`](photogrammetry::simulate): synthetic rigs, particles,
//!   flows, targets and images, the ground truth of tests and benchmarks.
//!
//! [`formats`]: files people already have, parsed into validated core
//! values; every error names the file, line or field.
//!
//! - [`calibration`](formats::calibration): the project's calibration JSON.
//! - [`control`](formats::control): calibration inputs (control points
//!   `id X Y Z`, image coordinates `id x y`) and the report.
//! - [`openptv`](formats::openptv): OpenPTV's `.ori`, `.addpar` and
//!   `ptv.par`, imported and exported without loss.
//! - [`csv`](formats::csv): the command line's point, observation, target,
//!   particle and trajectory tables.
//! - [`image`](formats::image): greyscale PNG, TIFF and raw buffers.
//! - [`vtk`](formats::vtk) and [`hdf5`](formats::hdf5): particles and
//!   trajectories for ParaView and HDF5 tools.
//!
//! [`plot`]: pictures of results as PNG or SVG, drawn once against one
//! drawing interface with a raster and an SVG backend: a calibration's
//! residuals, a self-calibration's disparity maps, a camera image with its
//! targets and reprojections, particles and trajectories in three views
//! (`ptv plot` and the service's `*.png` routes). Outside the core.
//!
//! [`cli`]: the `ptv` command line, one subcommand per task: `calibration`
//! (import and export), `calibrate`, `selfcalibrate`, `project`,
//! `intersect`, `detect`, `match`, `process`, `experiment`,
//! `process-sequence`, `track`, `simulate`, `plot`, `background`,
//! `upload`, `serve` and `worker`. It wires [`formats`] to
//! [`photogrammetry`] and has no numerics of its own.
//!
//! [`service`]: the HTTP service (`ptv serve`, `ptv worker`). The core
//! knows nothing of it. State and the job queue in SQLite (embedded, the
//! default) or PostgreSQL; images in the data directory or an
//! S3-compatible object store.
//!
//! - [`http`](service::http): the API under `/api/v1`, one router per
//!   resource; the one error type, problem+json; the one multipart upload
//!   path; the tower layers every request passes through.
//! - [`jobs`](service::jobs), [`tracking`](service::tracking),
//!   [`selfcal`](service::selfcal),
//!   [`preprocessing`](service::preprocessing): the workers (leased jobs
//!   on a CPU pool: frames, solves, self-calibration, reprocessing), the
//!   tracking runs, backgrounds and masks.
//! - [`store`](service::store): all SQL, one text per query for both
//!   engines, one file per table group, with the typed ids.
//! - [`images`](service::images): stored files, content-addressed, on disk
//!   or in S3.
//! - [`budget`](service::budget), [`connections`](service::connections),
//!   [`metrics`](service::metrics), [`events`](service::events): the memory
//!   budget, HTTP/1.1 within a connection limit, `/metrics`, the event log
//!   and its streams.
//! - [`config`](service::config) and [`app`](service::app): the flags, and
//!   start-up, serving and shutdown.
//!
//! `ARCHITECTURE.md` has the layering rule and the invariants.

pub mod cli;
pub mod formats;
pub mod photogrammetry;
pub mod plot;
pub mod service;
