//! `ptv track`: trajectories over a sequence of frames
//! ([`crate::photogrammetry::track`]), from the particle files of `ptv
//! match` (`--particles PATTERN`) or from the targets of every camera,
//! matched frame by frame first (`--calibration` and `--targets PATTERN`
//! per camera, with `ptv match`'s flags).
//!
//! The trajectory points go to standard output as the CSV
//! `trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras,t0,t1,...` (mm,
//! mm per frame, mm per frame²; `su,sv,sw` the velocity's standard
//! deviations; `cameras` and `tC` as `ptv match` writes them, empty where
//! the particle files have none; an acceleration is empty where the fit
//! window has two points). Rows come as points become final (their fit
//! window complete), so a long sequence streams; sort by
//! `trajectory,frame` for one trajectory's rows together. A summary goes to
//! standard error, with a progress bar where it is a terminal. A range
//! with frames whose files are missing is refused, naming them, unless
//! `--allow-gaps`: then such a frame is a gap, and the summary names them.
//!
//! `--ptv-is DIR` also writes OpenPTV's linkage files `DIR/ptv_is.<frame>`
//! (as liboptv's tracker writes them: the particle count, then per
//! particle of the frame, in its input order, `prev next x y z`, `prev`
//! and `next` the linked particle's row in the previous and next frame's
//! file, -1 and -2 for none). OpenPTV links adjacent frames only, so a
//! link across a bridged gap appears there as none.

use std::collections::VecDeque;
use std::fmt::Write as _;
use std::io::{IsTerminal, Write};
use std::path::PathBuf;

use clap::Args;
use nalgebra::Vector3;

use super::match_targets::MatchingFlags;
use super::{check_camera_count, read_calibration, write_stderr_line, write_stdout, CliError};
use crate::formats;
use crate::formats::csv::ParticleRow;
use crate::formats::frames::{FramePattern, FrameRange, WithoutNumber};
use crate::photogrammetry::correspond::Matcher;
use crate::photogrammetry::track::{
    BackwardSummary, FrameTargets, ImageSpaceRecovery, ParticlePosition, RecoveredParticles,
    TrackPoint, Tracker, TrackingParameters,
};

/// Arguments of `ptv track`.
#[derive(Debug, Args)]
pub struct TrackArgs {
    /// The particles of each frame, as `ptv match` writes them, with a
    /// printf-style frame number (`particles.%05d.csv`). Without
    /// `sx,sy,sz` columns, give --sigma.
    #[arg(long, value_name = "PATTERN", required_unless_present = "targets", conflicts_with_all = ["calibration", "targets"])]
    pub particles: Option<String>,
    /// The calibration JSON, to match --targets.
    #[arg(long, value_name = "CALIBRATION_JSON", requires = "targets")]
    pub calibration: Option<PathBuf>,
    /// One camera's target files, with a printf-style frame number
    /// (`cam1.%05d_targets`); once per camera, in camera order.
    #[arg(long = "targets", value_name = "PATTERN", requires = "calibration")]
    pub targets: Vec<String>,
    /// The frames, FIRST..LAST (inclusive).
    #[arg(long, value_name = "FIRST..LAST", value_parser = FrameRange::parse)]
    pub frames: FrameRange,
    /// The matching flags (with --targets).
    #[command(flatten)]
    pub matching: MatchingFlags,
    /// The largest displacement of a particle between frames (mm per
    /// frame): at most the diagonal of the observation volume (the
    /// matcher's with --targets, --volume where given) and 10^6 mm.
    #[arg(long, value_name = "MM_PER_FRAME")]
    pub max_velocity: f64,
    /// The largest change of velocity between frames (mm per frame²),
    /// at most twice the volume's diagonal [default: half of
    /// --max-velocity].
    #[arg(long, value_name = "MM_PER_FRAME2")]
    pub max_acceleration: Option<f64>,
    /// Frames a trajectory may miss and continue (0 to 2).
    #[arg(long, value_name = "FRAMES", default_value_t = 1)]
    pub max_gap: usize,
    /// The fewest points of a trajectory written.
    #[arg(long, value_name = "N", default_value_t = 3)]
    pub min_length: usize,
    /// Also write OpenPTV's linkage files ptv_is.<frame> into this
    /// directory (created if missing).
    #[arg(long, value_name = "DIR")]
    pub ptv_is: Option<PathBuf>,
    /// Do not look in the images for the particles the correspondences
    /// missed (with --targets, a trajectory whose prediction has no
    /// particle is continued from unused targets near its image in 2 or
    /// more cameras, intersected and accepted within --tolerance).
    #[arg(long)]
    pub no_recovery: bool,
    /// Do not extend the trajectories backwards in time after the forward
    /// pass. Backward tracking (on by default; docs/tracking.md) takes back
    /// the starts the forward pass found late and joins trajectories a
    /// loss broke, but holds the whole sequence until its end (about 200
    /// bytes a particle) and writes every row then; with --no-backward the
    /// rows stream in memory bounded by the fit window (for long
    /// sequences).
    #[arg(long, conflicts_with = "backward")]
    pub no_backward: bool,
    /// Backward tracking, the default (kept for scripts that ask for it).
    #[arg(long, hide = true)]
    pub backward: bool,
    /// Also export the particles and trajectories (repeatable): `vtk` for
    /// ParaView (`particles.<frame>.vtp`, `particles.pvd`,
    /// `trajectories.vtp`), `hdf5` (`sequence.h5`); into --export-dir.
    #[arg(long, value_enum, requires = "export_dir")]
    pub export: Vec<super::export::ExportFormat>,
    /// The directory of the exports (created if missing).
    #[arg(long, value_name = "DIR", requires = "export")]
    pub export_dir: Option<PathBuf>,
    /// Track across frames whose files are missing (as gaps: a trajectory
    /// bridges up to --max-gap of them) instead of refusing the range; the
    /// summary names the files.
    #[arg(long)]
    pub allow_gaps: bool,
    /// The particles' position uncertainty (mm) where the particle files
    /// have no sx,sy,sz columns.
    #[arg(long, value_name = "MM", allow_negative_numbers = true)]
    pub sigma: Option<f64>,
}

fn flag(flag: &'static str, reason: impl Into<String>) -> CliError {
    CliError::Flag {
        flag,
        reason: reason.into(),
    }
}

/// A frame as read.
struct FrameInput {
    /// Its particles.
    rows: Vec<ParticleRow>,
    /// With --targets, the targets per camera they were matched from, for
    /// the recovery ([`FrameTargets::of_particles`]).
    targets: Option<FrameTargets>,
}

/// Where the particles come from.
pub(super) enum Source {
    Particles(FramePattern),
    Targets {
        matcher: Matcher,
        patterns: Vec<FramePattern>,
    },
}

impl Source {
    fn flag(&self) -> &'static str {
        match self {
            Source::Particles(_) => "--particles",
            Source::Targets { .. } => "--targets",
        }
    }

    fn patterns(&self) -> Vec<&FramePattern> {
        match self {
            Source::Particles(p) => vec![p],
            Source::Targets { patterns, .. } => patterns.iter().collect(),
        }
    }

    /// Frame `frame`; `None` where a file is missing (a gap).
    fn read(&self, frame: u64) -> Result<Option<FrameInput>, CliError> {
        if self.patterns().iter().any(|p| !p.path(frame).is_file()) {
            return Ok(None);
        }
        Ok(Some(match self {
            Source::Particles(pattern) => {
                let path = pattern.path(frame);
                let rows = formats::csv::parse_particles(
                    &formats::read_text(&path)?,
                    &path.display().to_string(),
                )?;
                FrameInput {
                    rows,
                    targets: None,
                }
            }
            Source::Targets { matcher, patterns } => {
                let targets = patterns
                    .iter()
                    .map(|p| {
                        let path = p.path(frame);
                        formats::parse_targets(
                            &formats::read_text(&path)?,
                            &path.display().to_string(),
                        )
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                let particles = matcher.match_frame(&targets)?;
                let targets = FrameTargets::of_particles(&targets, &particles)
                    .map_err(|e| flag("--targets", format!("frame {frame}: {e}")))?;
                let rows = particles
                    .into_iter()
                    .map(|p| ParticleRow {
                        position: p.position,
                        sigma: Some(p.sigma),
                        targets: p.targets,
                    })
                    .collect();
                FrameInput {
                    rows,
                    targets: Some(targets),
                }
            }
        }))
    }
}

/// Tracks, writing the trajectory points to standard output.
pub(super) fn run(
    args: &TrackArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let parameters = TrackingParameters {
        max_acceleration: args.max_acceleration.unwrap_or(args.max_velocity / 2.0),
        max_gap: args.max_gap,
        min_length: args.min_length,
        ..TrackingParameters::new(args.max_velocity)
    };
    if let Some(sigma) = args.sigma {
        if !(sigma.is_finite() && sigma > 0.0) {
            return Err(flag(
                "--sigma",
                format!("must be a positive number of mm, got {sigma}"),
            ));
        }
    }
    let mut tracker = Tracker::new(parameters.clone())?;
    let source = match (&args.particles, &args.calibration) {
        (Some(pattern), _) => {
            // The limits against the volume, where one is given (as the
            // service checks them against its sequence's).
            if let Some(volume) = args.matching.parameters()?.volume {
                parameters.check_volume(&volume)?;
            }
            Source::Particles(
                FramePattern::parse(pattern, WithoutNumber::Refuse)
                    .map_err(|e| flag("--particles", e))?,
            )
        }
        (None, Some(calibration)) => {
            let cameras = read_calibration(calibration)?;
            check_camera_count(
                calibration,
                cameras.len(),
                args.targets.len(),
                ("--targets", "target pattern"),
            )?;
            if !args.no_recovery {
                let recovery = ImageSpaceRecovery::new(cameras.clone(), args.matching.tolerance)
                    .map_err(|e| flag("--tolerance", e.to_string()))?;
                tracker = Tracker::with_recovery(parameters.clone(), recovery)?;
            }
            let matcher = Matcher::new(&cameras, &args.matching.parameters()?)?;
            // The limits against the volume the particles are found in.
            parameters.check_volume(matcher.volume())?;
            Source::Targets {
                matcher,
                patterns: args
                    .targets
                    .iter()
                    .map(|t| {
                        FramePattern::parse(t, WithoutNumber::Refuse)
                            .map_err(|e| flag("--targets", e))
                    })
                    .collect::<Result<_, _>>()?,
            }
        }
        (None, None) => {
            return Err(flag(
                "--particles",
                "give --particles PATTERN, or --calibration and --targets PATTERN per camera",
            ))
        }
    };
    if !args.no_backward {
        tracker = tracker.extending_backward();
    }
    let counts = track_source(
        &parameters,
        tracker,
        &source,
        args.frames,
        args.allow_gaps,
        args.sigma,
        args.ptv_is.as_deref(),
        !args.export.is_empty(),
        stdout,
    )?;
    if let (Some(collector), Some(dir)) = (&counts.export, &args.export_dir) {
        for format in &args.export {
            collector.write(*format, dir)?;
        }
    }
    write_stderr_line(stderr, &counts.summary(&parameters))
}

/// What a tracking pass counted.
pub(super) struct TrackCounts {
    /// Frames in the range.
    pub frames: u64,
    /// Of those, frames without files (tracked as gaps).
    pub gaps: u64,
    /// The missing files' description (empty for none).
    pub missing: String,
    /// Particles read.
    pub particles: usize,
    /// Particles recovered from the images.
    pub recovered: usize,
    /// Trajectories written.
    pub trajectories: u64,
    /// Points written.
    pub points: usize,
    /// What the exports need, where asked.
    pub export: Option<super::export::Collector>,
    /// What backward tracking added, where it ran.
    pub backward: Option<BackwardSummary>,
}

impl TrackCounts {
    /// `ptv track`'s summary line.
    pub(super) fn summary(&self, parameters: &TrackingParameters) -> String {
        format!(
            "{} frames ({} without files, tracked as gaps{}), {} particles and {} recovered from the images; {} trajectories of at least {} points hold {} of them",
            self.frames - self.gaps,
            self.gaps,
            self.missing,
            self.particles,
            self.recovered,
            self.trajectories,
            parameters.min_length,
            self.points
        ) + &match self.backward {
            Some(b) => format!(
                "; backward tracking added {} points before trajectories' starts ({} trajectories lengthened, {} joined to the one ending before them)",
                b.points, b.lengthened, b.joined
            ),
            None => "; backward tracking off (--no-backward)".into(),
        }
    }
}

impl Source {
    /// The particle files of `pattern` (as `ptv match` writes them).
    pub(super) fn particles(pattern: FramePattern) -> Source {
        Source::Particles(pattern)
    }

    /// Every camera's target files, matched frame by frame by `matcher`.
    pub(super) fn targets(matcher: Matcher, patterns: Vec<FramePattern>) -> Source {
        Source::Targets { matcher, patterns }
    }
}

/// Tracks the frames of `range` from `source`, writing the CSV to
/// `stdout` (and `ptv_is` files where given).
#[allow(clippy::too_many_arguments)]
pub(super) fn track_source(
    parameters: &TrackingParameters,
    mut tracker: Tracker,
    source: &Source,
    range: FrameRange,
    allow_gaps: bool,
    sigma: Option<f64>,
    ptv_is: Option<&std::path::Path>,
    collect: bool,
    stdout: &mut dyn Write,
) -> Result<TrackCounts, CliError> {
    for pattern in source.patterns() {
        if !(range.first..=range.last).any(|f| pattern.path(f).is_file()) {
            return Err(flag(
                source.flag(),
                format!(
                    "the pattern `{}` matches no file for frames {}..{}; check the pattern and --frames",
                    pattern.as_str(),
                    range.first,
                    range.last
                ),
            ));
        }
    }

    // Frames missing a file: refused unless --allow-gaps, and named.
    let mut missing: Vec<(u64, PathBuf)> = Vec::new();
    for frame in range.first..=range.last {
        for pattern in source.patterns() {
            let path = pattern.path(frame);
            if !path.is_file() {
                missing.push((frame, path));
            }
        }
    }
    if !missing.is_empty() && !allow_gaps {
        return Err(flag(
            "--frames",
            format!(
                "the range {}..{} is not contiguous: {}; give a range whose files all exist, or --allow-gaps to track across the missing frames as gaps",
                range.first,
                range.last,
                describe_missing(&missing)
            ),
        ));
    }

    let bar = indicatif::ProgressBar::with_draw_target(
        Some(range.last - range.first + 1),
        if std::io::stderr().is_terminal() {
            indicatif::ProgressDrawTarget::stderr()
        } else {
            indicatif::ProgressDrawTarget::hidden()
        },
    );
    // A frame's particles are needed until its points are handed out:
    // with backward tracking, all of them at the end.
    let keep = parameters.report_delay() as u64;
    let hold_all = tracker.is_extending_backward();
    if let Some(dir) = ptv_is {
        std::fs::create_dir_all(dir).map_err(|e| {
            flag(
                "--ptv-is",
                format!("cannot create the directory {}: {e}", dir.display()),
            )
        })?;
    }
    let mut window: VecDeque<Held> = VecDeque::new();
    let mut writer = Rows {
        export: collect.then(super::export::Collector::default),
        ..Rows::default()
    };
    let mut gaps = 0u64;
    let mut particles = 0usize;
    let mut recovered = 0usize;
    for frame in range.first..=range.last {
        bar.set_position(frame - range.first);
        let Some(FrameInput { rows, targets }) = source.read(frame)? else {
            gaps += 1;
            continue;
        };
        writer.cameras(&rows, source.flag())?;
        let positions = rows
            .iter()
            .enumerate()
            .map(|(i, row)| {
                let sigma = match (row.sigma, sigma) {
                    (Some(s), _) => s,
                    (None, Some(s)) => Vector3::repeat(s),
                    (None, None) => {
                        return Err(flag(
                            "--sigma",
                            format!(
                                "the particles of frame {frame} have no sx,sy,sz columns; give \
                                 --sigma MM, their position uncertainty (particle {i})"
                            ),
                        ))
                    }
                };
                // The files' target columns say how many cameras saw
                // it; without them it is unknown (0).
                Ok(ParticlePosition::seen_by(
                    row.position,
                    sigma,
                    row.targets.iter().flatten().count(),
                ))
            })
            .collect::<Result<Vec<_>, _>>()?;
        particles += rows.len();
        let sigmas = positions.iter().map(|p| p.sigma).collect();
        window.push_back(Held::new(frame, rows, sigmas));
        while !hold_all && window.front().is_some_and(|h| h.frame + keep < frame) {
            let held = window.pop_front().expect("a frame");
            held.write_ptv_is(ptv_is)?;
            writer.release(held);
        }
        let points = match targets {
            Some(targets) => tracker.push_with_targets(frame as i64, positions, targets)?,
            None => tracker.push(frame as i64, positions)?,
        };
        recovered += hold_recovered(tracker.take_recovered(), &mut window)?;
        writer.write(&points, &mut window, stdout)?;
    }
    let finished = tracker.finish_all();
    recovered += hold_recovered(finished.recovered, &mut window)?;
    writer.write(&finished.points, &mut window, stdout)?;
    for held in window {
        held.write_ptv_is(ptv_is)?;
        writer.release(held);
    }
    bar.finish_and_clear();
    Ok(TrackCounts {
        frames: range.last - range.first + 1,
        gaps,
        missing: if missing.is_empty() {
            String::new()
        } else {
            format!(" ({})", describe_missing(&missing))
        },
        particles,
        recovered,
        trajectories: writer.trajectories,
        points: writer.points,
        export: writer.export,
        backward: finished.backward,
    })
}

/// Adds the particles the tracker recovered from the images to their
/// frames' rows (they are numbered after the frame's own); returns how
/// many.
fn hold_recovered(
    recovered: Vec<RecoveredParticles>,
    window: &mut VecDeque<Held>,
) -> Result<usize, CliError> {
    let mut count = 0;
    for frame in recovered {
        let held = window
            .iter_mut()
            .find(|h| h.frame as i64 == frame.frame)
            .filter(|h| h.rows.len() == frame.first)
            .ok_or_else(|| {
                flag(
                    "--targets",
                    format!(
                        "internal: frame {}'s recovered particles came after the frame was let go; please report this",
                        frame.frame
                    ),
                )
            })?;
        for particle in frame.particles {
            held.rows.push(ParticleRow {
                position: particle.position,
                sigma: Some(particle.sigma),
                targets: particle.targets,
            });
            held.prev.push(-1);
            held.next.push(-2);
            held.sigma.push(particle.sigma);
            held.trajectory.push(-1);
            count += 1;
        }
    }
    Ok(count)
}

/// The frames that miss files, as runs (`5, 9..11`), and the first few
/// files missing, with how many in all.
fn describe_missing(missing: &[(u64, PathBuf)]) -> String {
    const NAMED: usize = 5;
    let mut frames: Vec<u64> = missing.iter().map(|(f, _)| *f).collect();
    frames.dedup();
    let mut runs: Vec<String> = Vec::new();
    let mut i = 0;
    while i < frames.len() {
        let mut j = i;
        while j + 1 < frames.len() && frames[j + 1] == frames[j] + 1 {
            j += 1;
        }
        runs.push(if i == j {
            frames[i].to_string()
        } else {
            format!("{}..{}", frames[i], frames[j])
        });
        i = j + 1;
    }
    let named: Vec<String> = missing
        .iter()
        .take(NAMED)
        .map(|(_, p)| p.display().to_string())
        .collect();
    let more = if missing.len() > NAMED {
        format!(" and {} more", missing.len() - NAMED)
    } else {
        String::new()
    };
    format!(
        "frame{} {} miss{} {}{more}",
        if frames.len() == 1 { "" } else { "s" },
        runs.join(", "),
        if frames.len() == 1 { "es" } else { "" },
        named.join(", ")
    )
}

/// A frame's particles while its points may still come, with the links
/// to its neighbours for `ptv_is`.
struct Held {
    frame: u64,
    rows: Vec<ParticleRow>,
    /// Per particle, its row in the previous frame (-1 for none).
    prev: Vec<i64>,
    /// Per particle, its row in the next frame (-2 for none).
    next: Vec<i64>,
    /// Per particle, the position sigmas tracking took (the files' or
    /// --sigma).
    sigma: Vec<Vector3<f64>>,
    /// Per particle, its trajectory (-1 for none).
    trajectory: Vec<i64>,
}

impl Held {
    fn new(frame: u64, rows: Vec<ParticleRow>, sigma: Vec<Vector3<f64>>) -> Held {
        Held {
            frame,
            prev: vec![-1; rows.len()],
            next: vec![-2; rows.len()],
            trajectory: vec![-1; rows.len()],
            sigma,
            rows,
        }
    }

    fn write_ptv_is(&self, dir: Option<&std::path::Path>) -> Result<(), CliError> {
        let Some(dir) = dir else {
            return Ok(());
        };
        let mut text = format!("{}\n", self.rows.len());
        for (i, row) in self.rows.iter().enumerate() {
            let p = row.position;
            let _ = writeln!(
                text,
                "{:4} {:4} {:10.3} {:10.3} {:10.3}",
                self.prev[i], self.next[i], p.x, p.y, p.z
            );
        }
        formats::write_text(&dir.join(format!("ptv_is.{}", self.frame)), &text)?;
        Ok(())
    }
}

/// The hash of [`Rows::last`]'s keys, trajectory numbers (dense, chosen
/// by the tracker, not by the input): a multiply and a rotate (as rustc's
/// FxHash) instead of SipHash's rounds, which guard against keys chosen
/// to collide.
#[derive(Clone, Copy, Default)]
struct TrajectoryHash;

impl std::hash::BuildHasher for TrajectoryHash {
    type Hasher = TrajectoryHasher;

    fn build_hasher(&self) -> TrajectoryHasher {
        TrajectoryHasher(0)
    }
}

/// [`TrajectoryHash`]'s hasher.
struct TrajectoryHasher(u64);

impl std::hash::Hasher for TrajectoryHasher {
    fn finish(&self) -> u64 {
        // hashbrown takes the top 7 bits as a tag and the low ones as the
        // bucket: the rotate brings the product's well-mixed high bits down.
        self.0.rotate_left(26)
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u64(&mut self, value: u64) {
        self.0 = (self.0.rotate_left(5) ^ value).wrapping_mul(0xf135_7aea_2e62_a9c5);
    }
}

/// The CSV writer and its counts.
#[derive(Default)]
struct Rows {
    /// Cameras of the `tC` columns, from the first frame with particles.
    camera_count: Option<usize>,
    header_written: bool,
    trajectories: u64,
    points: usize,
    /// Per trajectory, its last point written (frame, particle).
    last: std::collections::HashMap<u64, (i64, usize), TrajectoryHash>,
    /// What the exports need, where asked.
    export: Option<super::export::Collector>,
}

impl Rows {
    /// A frame let go: its particles to the exports.
    fn release(&mut self, held: Held) {
        let Some(export) = &mut self.export else {
            return;
        };
        let particles = held
            .rows
            .iter()
            .enumerate()
            .map(|(i, row)| crate::formats::vtk::ParticleRecord {
                position: row.position,
                sigma: held.sigma[i],
                cameras: row.targets.iter().flatten().count() as u32,
                trajectory: held.trajectory[i],
            })
            .collect();
        export.frames.push((held.frame as i64, particles));
    }

    fn cameras(&mut self, rows: &[ParticleRow], source: &'static str) -> Result<(), CliError> {
        for row in rows {
            match self.camera_count {
                None => self.camera_count = Some(row.targets.len()),
                Some(n) if n != row.targets.len() => {
                    return Err(flag(
                        source,
                        format!(
                            "the particle files name targets of {n} cameras in one frame and of {} in another; give one recording",
                            row.targets.len()
                        ),
                    ))
                }
                Some(_) => {}
            }
        }
        Ok(())
    }

    fn write(
        &mut self,
        points: &[TrackPoint],
        window: &mut VecDeque<Held>,
        stdout: &mut dyn Write,
    ) -> Result<(), CliError> {
        let cameras = self.camera_count.unwrap_or(0);
        let mut text = String::new();
        if !self.header_written {
            text.push_str(&formats::csv::trajectory_header(cameras));
            self.header_written = true;
        }
        for p in points {
            self.points += 1;
            self.trajectories = self.trajectories.max(p.trajectory + 1);
            // Its frame in the window (held in frame order).
            let here = window
                .binary_search_by_key(&p.frame, |h| h.frame as i64)
                .ok();
            // Adjacent-frame links for ptv_is.
            if let Some((frame, particle)) = self.last.insert(p.trajectory, (p.frame, p.particle)) {
                if frame + 1 == p.frame {
                    if let Some(before) = here
                        .and_then(|i| i.checked_sub(1))
                        .and_then(|i| window.get_mut(i))
                        .filter(|h| h.frame as i64 == frame)
                    {
                        before.next[particle] = p.particle as i64;
                    }
                    if let Some(this) = here.map(|i| &mut window[i]) {
                        this.prev[p.particle] = particle as i64;
                    }
                }
            }
            let Some((row, sigma)) = here.map(|i| &mut window[i]).and_then(|held| {
                *held.trajectory.get_mut(p.particle)? = p.trajectory as i64;
                let held = &*held;
                Some((held.rows.get(p.particle)?, *held.sigma.get(p.particle)?))
            }) else {
                return Err(flag(
                    "--max-gap",
                    format!(
                        "internal: frame {}'s particles were let go before trajectory {} was written; please report this",
                        p.frame, p.trajectory
                    ),
                ));
            };
            let d = &p.derivatives;
            if let Some(export) = &mut self.export {
                export.trajectories.entry(p.trajectory).or_default().push(
                    crate::formats::vtk::TrajectoryPointRecord {
                        frame: p.frame,
                        position: p.position,
                        sigma,
                        velocity: d.velocity,
                        velocity_sigma: d.velocity_sigma,
                        acceleration: d.acceleration,
                        acceleration_sigma: d.acceleration_sigma,
                        cameras: row.targets.iter().flatten().count() as u32,
                    },
                );
            }
            let point = formats::csv::TrajectoryPointLine {
                trajectory: p.trajectory as i64,
                frame: p.frame,
                position: [p.position.x, p.position.y, p.position.z],
                velocity: Some([d.velocity.x, d.velocity.y, d.velocity.z]),
                acceleration: d.acceleration.map(|a| [a.x, a.y, a.z]),
                velocity_sigma: Some([d.velocity_sigma.x, d.velocity_sigma.y, d.velocity_sigma.z]),
                targets: (cameras > 0).then_some(&row.targets[..]),
            };
            formats::csv::write_trajectory_point(&mut text, &point, cameras);
        }
        // A trajectory whose last point is before every held frame (and
        // not just before the oldest, whose point may still link back) has
        // ended: its entry can go, so the map stays as small as the window.
        if let Some(oldest) = window.front().map(|h| h.frame as i64) {
            self.last.retain(|_, (frame, _)| *frame + 1 >= oldest);
        }
        write_stdout(stdout, &text)
    }
}
