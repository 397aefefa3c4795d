//! The workers' memory budget (issue 29): each job declares the memory it
//! will need from its pixels and settings ([`MemoryNeed`]) before its
//! work, and takes that many MiB from the process's [`MemoryBudget`] (a
//! semaphore of MiB) until the work is done, so two large jobs wait for
//! each other instead of both running and the process being killed for
//! memory.
//!
//! - The budget is `--memory-budget-mb` (`PTV_MEMORY_BUDGET_MB`), by
//!   default [`DEFAULT_SHARE_PERCENT`] % of the memory this process may use:
//!   `MemTotal` of `/proc/meminfo`, or the cgroup's `memory.max` when that
//!   is lower ([`default_budget_mib`]). It is the process's: `ptv serve`'s
//!   workers share one, and every `ptv worker` process has its own, so
//!   several processes on one machine are each given their share.
//! - A job whose need exceeds the whole budget can never run in this
//!   process: it fails at once with the reason ([`BudgetError::TooLarge`], the
//!   permanent failure; never retried into an out-of-memory crash loop).
//! - Waiting: the job waits for its MiB inside its attempt, after its
//!   claim, while the attempt's heartbeat renews its lease (every third of
//!   `--lease-secs`), so the wait never lets the lease run out and another
//!   worker take the job. The wait is first come, first served (tokio's
//!   semaphore is fair, `acquire_many` included): a large job at the head
//!   of the queue is not overtaken by smaller ones arriving after it, so
//!   it cannot starve; smaller jobs behind it wait until it got its share
//!   (head-of-line blocking, the price of no starvation). Every need is at
//!   most the budget, and every holder releases when its work ends
//!   (success, failure or panic: the grant is dropped), so every waiter
//!   is admitted eventually. A job takes at most one grant at a time (a
//!   frame that first computes its sequence's background releases that
//!   grant before taking its own), so grants cannot deadlock.
//! - The needs are estimates on the safe side, from figures measured on
//!   this code ([`DETECT_BYTES_PER_PIXEL`]); they bound the work's own
//!   allocations, not the process's baseline (the idle server, caches).
//! - Which work takes a grant, and its need: a frame ([`frame_need`]), a
//!   computed background ([`background_bytes`]), a calibration solve
//!   (`jobs::solve_need`), a self-calibration ([`selfcal_need`], from the
//!   stored target counts of its frames, before they are read), a
//!   reprocessing (one frame at a time, [`reprocess_need`]) and a tracking
//!   run (each frame it takes, [`tracking_need`], from the particles the
//!   tracker holds and the frame's). A tracking run holds no grant between
//!   frames, so a run waiting for frames never keeps their jobs waiting for
//!   memory.
//! - Grants of a quarter of the budget or more are logged when taken
//!   (with the wait) and released, numbered: when the large jobs ran.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::service::infra::metrics::Metrics;

/// One MiB.
pub const MIB: u64 = 1 << 20;

/// The default budget's share of the memory the process may use (%).
pub const DEFAULT_SHARE_PERCENT: u64 = 50;

/// The default budget where the machine's memory cannot be read (not
/// Linux): 4 GiB.
pub const FALLBACK_BUDGET_MIB: u64 = 4096;

/// Peak bytes per pixel of decoding and detecting one camera's image,
/// measured with `/usr/bin/time -v ptv detect` (maximum resident set size
/// less the process's baseline, over the image's pixels) on the worst
/// image found: an 8192x8192 16-bit 1-px checkerboard with threshold 1
/// and min_pixels 1 (every other pixel a target), 46 B/px; a real
/// 1280x1024 8-bit frame of `tests/data/openptv` takes far less. Rounded
/// up to 48.
pub const DETECT_BYTES_PER_PIXEL: u64 = 48;

/// Bytes a target takes through matching (the target, its encoding, its
/// epipolar candidates), per target a camera may have: a frame job's
/// targets are bounded by `correspond::max_targets` per camera.
pub const MATCH_BYTES_PER_TARGET: u64 = 256;

/// What a job will allocate, and what for (for the message of a job that
/// can never fit).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MemoryNeed {
    /// Bytes.
    pub bytes: u64,
    /// What needs them, e.g. `the median background of 2 cameras of
    /// 8192x8192 16-bit pixels over 32 frames`.
    pub what: String,
}

impl MemoryNeed {
    /// `bytes` for `what`.
    pub fn new(bytes: u64, what: impl Into<String>) -> MemoryNeed {
        MemoryNeed {
            bytes,
            what: what.into(),
        }
    }

    /// The need in whole MiB, rounded up.
    pub fn mib(&self) -> u64 {
        self.bytes.div_ceil(MIB)
    }
}

/// A frame job's need: its largest camera's pixels decoded and detected
/// (one camera at a time), with a splitter the whole image and its views
/// beside them, and the targets every camera may give through matching.
/// `cameras` are (width, height) of each camera's view; `image` the
/// frame's one image with a splitter; without `detect` (uploaded
/// targets) only the matching.
pub fn frame_need(cameras: &[(u32, u32)], image: Option<(u32, u32)>, detect: bool) -> MemoryNeed {
    let pixels = |(w, h): (u32, u32)| u64::from(w) * u64::from(h);
    let largest = if detect {
        cameras.iter().map(|&c| pixels(c)).max().unwrap_or(0)
    } else {
        0
    };
    let detect = largest.saturating_mul(DETECT_BYTES_PER_PIXEL);
    // The decoded image (at most 2 bytes a sample) and its views.
    let split = image.map_or(0, |i| pixels(i).saturating_mul(2 * 2));
    let targets: u64 = cameras
        .iter()
        .map(|&(w, h)| {
            // correspond::max_targets: one per 2x2 pixels, at most 2^20.
            let most = (u64::from(w.div_ceil(2)) * u64::from(h.div_ceil(2))).min(1 << 20);
            most.saturating_mul(MATCH_BYTES_PER_TARGET)
        })
        .sum();
    MemoryNeed::new(
        detect.saturating_add(split).saturating_add(targets),
        format!(
            "detecting and matching a frame of {} camera(s), the largest of {largest} pixels \
             ({DETECT_BYTES_PER_PIXEL} bytes per pixel for detection, \
             {MATCH_BYTES_PER_TARGET} per possible target for matching)",
            cameras.len()
        ),
    )
}

/// Bytes a computed background of one camera needs at most: `kept`
/// frames of `view` pixels at `sample_bytes` (1 or 2) each, the frame's
/// decoded image (`image` pixels: the whole image with a splitter, else
/// the view) and one view cut from it, the result, and its PNG encoding
/// (at most the result again); `compressed` is the largest stored file
/// read, held while it decodes. See
/// [`crate::photogrammetry::background`].
pub fn background_bytes(
    kept: u64,
    view: u64,
    image: u64,
    sample_bytes: u64,
    compressed: u64,
) -> u64 {
    let frame = view.saturating_mul(sample_bytes);
    kept.saturating_mul(frame)
        .saturating_add(image.saturating_mul(sample_bytes))
        .saturating_add(frame.saturating_mul(3))
        .saturating_add(compressed)
}

/// The fewest frames a median background may keep when the budget is too
/// small for more: the builder keeps between half its bound and its bound
/// ([`crate::photogrammetry::background`]), so a bound of 6 keeps at least
/// 3 frames, the fewest whose lower median rejects a particle that covers
/// a pixel in one of them.
pub const LEAST_MEDIAN_SAMPLE: u64 = 6;

/// The sample bound `K` a median background of `frames` frames may use
/// within `budget_bytes`: the largest even `K` of at most `most` whose
/// [`background_bytes`] (with `min(frames, K)` frames kept) fits, or
/// `None` when not even [`LEAST_MEDIAN_SAMPLE`] does. So a large sensor
/// on a small budget gets a median of fewer frames rather than a job that
/// can never run (issue 29: one camera at a time, `K` bounded by the
/// memory it would need).
pub fn median_sample_within(
    budget_bytes: u64,
    most: u64,
    frames: u64,
    view: u64,
    image: u64,
    sample_bytes: u64,
    compressed: u64,
) -> Option<u64> {
    let fits = |k: u64| {
        background_bytes(frames.min(k), view, image, sample_bytes, compressed) <= budget_bytes
    };
    let mut k = most - most % 2;
    while k >= LEAST_MEDIAN_SAMPLE {
        if fits(k) {
            return Some(k);
        }
        k -= 2;
    }
    None
}

/// Most parameters one camera may have adjusted in a self-calibration:
/// its exterior orientation (6) and every interior one OpenPTV names
/// (xh, yh, c, k1, k2, k3, p1, p2, scx, she: 10).
const SELFCAL_PARAMETERS_PER_CAMERA: u64 = 16;

/// A self-calibration's need: every frame's targets held at once
/// (`targets` of them, `size_of::<Target>()` each), each matched
/// ([`MATCH_BYTES_PER_TARGET`]: every frame's matches are kept for the
/// adjustment), and the bundle adjustment's share per target: a particle
/// has 3 unknowns and a normal-equation block of 3 x (3 + 16 per camera)
/// f64 against itself and the cameras' parameters, and at least two
/// targets, so half that per target. See
/// [`crate::photogrammetry::selfcal`].
pub fn selfcal_need(targets: u64, cameras: usize, frames: usize) -> MemoryNeed {
    let target = std::mem::size_of::<crate::photogrammetry::Target>() as u64;
    let adjust = 3 * (3 + SELFCAL_PARAMETERS_PER_CAMERA * cameras as u64) * 8 / 2;
    let per_target = target + MATCH_BYTES_PER_TARGET + adjust;
    MemoryNeed::new(
        targets.saturating_mul(per_target),
        format!(
            "self-calibrating {cameras} camera(s) from {targets} targets of {frames} frame(s) \
             ({per_target} bytes per target: the target, its matching, its share of the \
             adjustment)"
        ),
    )
}

/// Reprocessing one frame's need: its stored targets (`targets`, their
/// stored encoding `stored_bytes`) decoded and matched again
/// ([`MATCH_BYTES_PER_TARGET`] each), one frame at a time.
pub fn reprocess_need(frame: i64, targets: u64, stored_bytes: u64) -> MemoryNeed {
    let target = std::mem::size_of::<crate::photogrammetry::Target>() as u64;
    MemoryNeed::new(
        targets
            .saturating_mul(target + MATCH_BYTES_PER_TARGET)
            .saturating_add(stored_bytes),
        format!("matching frame {frame}'s {targets} stored targets again"),
    )
}

/// Bytes a particle takes in the tracker, per frame it is held: its
/// position and uncertainty, its place in a trajectory (the trajectory's
/// points and polynomial fits over the decision window), its spatial
/// index entry and its text of targets for the stored rows.
pub const TRACK_BYTES_PER_PARTICLE: u64 = 512;

/// Bytes of one candidate link the tracker weighs for a particle (the
/// pair, its cost, and its look-ahead partner).
pub const TRACK_BYTES_PER_LINK: u64 = 48;

/// A tracking step's need: the particles of the frames the tracker holds
/// (`held`, the frames within its report delay), the new frame's
/// `particles` with their candidate links (at most
/// [`crate::photogrammetry::track::MAX_CANDIDATES`] each), and with
/// image-space recovery the frame's `targets` matched
/// ([`MATCH_BYTES_PER_TARGET`]).
pub fn tracking_need(frame: i64, held: u64, particles: u64, targets: u64) -> MemoryNeed {
    let links = particles
        .saturating_mul(crate::photogrammetry::track::MAX_CANDIDATES as u64)
        .saturating_mul(TRACK_BYTES_PER_LINK);
    MemoryNeed::new(
        held.saturating_add(particles)
            .saturating_mul(TRACK_BYTES_PER_PARTICLE)
            .saturating_add(links)
            .saturating_add(targets.saturating_mul(MATCH_BYTES_PER_TARGET)),
        format!(
            "tracking frame {frame}: {particles} particles, {held} held from earlier frames, \
             {targets} targets for recovery"
        ),
    )
}

/// Bytes a particle of the run takes in its backward pass (module
/// `ops::tracking::backward`): its position, sigmas and camera count as
/// the pass reads them (56), the cameras that missed it and the
/// trajectory holding it (12), its spatial index entry while its frame is
/// searched (24), and its targets' text for a point it may become (about
/// 64).
pub const BACKWARD_BYTES_PER_PARTICLE: u64 = 160;

/// Bytes a stored trajectory point takes in the run's backward pass: its
/// row as read (about 200 with its targets' text), the point in its
/// trajectory (about 190 with its sigmas), and its row as written back
/// (about 200), with room for the collections' growth.
pub const BACKWARD_BYTES_PER_POINT: u64 = 768;

/// A run's backward pass's need: every particle the tracker was given
/// over the run, and every point it stored (the pass needs the whole
/// run, as `ptv track` does).
pub fn backward_need(run: i64, particles: u64, points: u64) -> MemoryNeed {
    MemoryNeed::new(
        particles
            .saturating_mul(BACKWARD_BYTES_PER_PARTICLE)
            .saturating_add(points.saturating_mul(BACKWARD_BYTES_PER_POINT)),
        format!(
            "the backward pass of tracking run {run}: {particles} particles over its frames, \
             {points} trajectory points"
        ),
    )
}

/// Why memory could not be granted.
#[derive(Debug, thiserror::Error)]
pub enum BudgetError {
    /// The need is larger than the whole budget: it never fits (a job
    /// fails for good with this reason).
    #[error("{0}")]
    TooLarge(String),
    /// The budget was closed (it never is while the process runs; a job
    /// is tried again).
    #[error("the memory budget was closed")]
    Closed,
}

/// The process's memory budget: a semaphore of MiB (module doc).
#[derive(Debug)]
pub struct MemoryBudget {
    total_mib: u64,
    permits: Arc<Semaphore>,
    metrics: Option<Arc<Metrics>>,
    waiting: AtomicU64,
    granted: AtomicU64,
}

/// MiB held by a job until dropped.
#[derive(Debug)]
pub struct Grant {
    mib: u64,
    _permit: Option<OwnedSemaphorePermit>,
    metrics: Option<Arc<Metrics>>,
    /// The grant's number in this process and what it is for, when its
    /// taking was logged (a large share of the budget): its release is
    /// logged too.
    logged: Option<(u64, String)>,
}

impl Grant {
    /// The MiB held.
    pub fn mib(&self) -> u64 {
        self.mib
    }
}

impl Drop for Grant {
    fn drop(&mut self) {
        if let Some(metrics) = &self.metrics {
            metrics.memory_released(self.mib);
        }
        if let Some((number, what)) = &self.logged {
            tracing::info!(
                "memory released: grant {number}, {} MiB, for {what}",
                self.mib
            );
        }
    }
}

/// Grants of at least 1/this of the budget are logged (taken, released).
const LOGGED_SHARE: u64 = 4;

/// The largest budget a semaphore holds (MiB): tokio's limit on permits,
/// far above any machine's memory.
const MAX_BUDGET_MIB: u64 = u32::MAX as u64;

impl MemoryBudget {
    /// A budget of `total_mib` MiB (at least 1), reported to `metrics`.
    pub fn new(total_mib: u64, metrics: Option<Arc<Metrics>>) -> MemoryBudget {
        let total_mib = total_mib.clamp(1, MAX_BUDGET_MIB);
        if let Some(metrics) = &metrics {
            metrics.memory_budget(total_mib);
        }
        MemoryBudget {
            total_mib,
            permits: Arc::new(Semaphore::new(total_mib as usize)),
            metrics,
            waiting: AtomicU64::new(0),
            granted: AtomicU64::new(0),
        }
    }

    /// The budget (MiB).
    pub fn total_mib(&self) -> u64 {
        self.total_mib
    }

    /// MiB not held by any job now.
    pub fn available_mib(&self) -> u64 {
        self.permits.available_permits() as u64
    }

    /// Jobs waiting for their MiB now.
    pub fn waiting(&self) -> u64 {
        self.waiting.load(Ordering::Relaxed)
    }

    /// Whether `need` can ever be admitted, or why not.
    pub fn check(&self, need: &MemoryNeed) -> Result<(), String> {
        let mib = need.mib();
        if mib > self.total_mib {
            return Err(format!(
                "this job needs about {mib} MiB of memory for {}, more than this worker's whole \
                 memory budget of {} MiB (--memory-budget-mb), so it can never run here; give \
                 smaller images or settings that need less, or run the workers with a larger \
                 --memory-budget-mb (the machine must have that memory)",
                need.what, self.total_mib
            ));
        }
        Ok(())
    }

    /// Waits for `need`'s MiB, first come first served; a need larger than
    /// the whole budget fails at once ([`MemoryBudget::check`]).
    pub async fn acquire(&self, need: &MemoryNeed) -> Result<Grant, BudgetError> {
        self.check(need).map_err(BudgetError::TooLarge)?;
        let mib = need.mib();
        let asked = std::time::Instant::now();
        let permit = if mib == 0 {
            None
        } else {
            // Counted as waiting until the permit comes or the wait is
            // dropped (a job cancelled while it waits).
            let _waiting = Waiting::count(&self.waiting);
            let permit = Arc::clone(&self.permits)
                .acquire_many_owned(mib as u32)
                .await;
            // The semaphore is never closed.
            Some(permit.map_err(|_| BudgetError::Closed)?)
        };
        if let Some(metrics) = &self.metrics {
            metrics.memory_reserved(mib);
        }
        // The grants that make others wait (a quarter of the budget or
        // more) are logged when taken and when released: when the large
        // jobs ran, and for how long they waited.
        let logged = (mib > 0 && mib.saturating_mul(LOGGED_SHARE) >= self.total_mib).then(|| {
            let number = self.granted.fetch_add(1, Ordering::Relaxed);
            tracing::info!(
                "memory granted: grant {number}, {mib} MiB of {} MiB, after {:.1} s waiting, \
                 for {}",
                self.total_mib,
                asked.elapsed().as_secs_f64(),
                need.what
            );
            (number, need.what.clone())
        });
        Ok(Grant {
            mib,
            _permit: permit,
            metrics: self.metrics.clone(),
            logged,
        })
    }
}

/// One job in the budget's `waiting` count, for as long as it lives.
struct Waiting<'a>(&'a AtomicU64);

impl<'a> Waiting<'a> {
    fn count(waiting: &'a AtomicU64) -> Waiting<'a> {
        waiting.fetch_add(1, Ordering::Relaxed);
        Waiting(waiting)
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// The default budget (MiB): [`DEFAULT_SHARE_PERCENT`] % of the memory
/// this process may use ([`memory_limit_bytes`]), or
/// [`FALLBACK_BUDGET_MIB`] where that cannot be read.
pub fn default_budget_mib() -> u64 {
    match memory_limit_bytes() {
        Some(bytes) => (bytes / 100 * DEFAULT_SHARE_PERCENT / MIB).max(1),
        None => FALLBACK_BUDGET_MIB,
    }
}

/// The memory this process may use: `MemTotal` of `/proc/meminfo`, or its
/// cgroup's `memory.max` (v2; `memory.limit_in_bytes` in v1) when lower.
pub fn memory_limit_bytes() -> Option<u64> {
    let total = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| mem_total_bytes(&text));
    let cgroup = cgroup_limit_bytes();
    match (total, cgroup) {
        (Some(total), Some(cgroup)) => Some(total.min(cgroup)),
        (total, cgroup) => total.or(cgroup),
    }
}

/// `MemTotal` of `/proc/meminfo`'s text, in bytes.
fn mem_total_bytes(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let mut words = line["MemTotal:".len()..].split_whitespace();
    let value: u64 = words.next()?.parse().ok()?;
    match words.next() {
        Some("kB") | None => value.checked_mul(1024),
        Some(_) => None,
    }
}

/// A cgroup limit file's value: bytes, or `max` (no limit).
fn cgroup_value(text: &str) -> Option<u64> {
    let text = text.trim();
    // cgroup v1 says "no limit" with a huge number (about i64::MAX).
    text.parse::<u64>().ok().filter(|&v| v < (1 << 60))
}

/// The memory limit of this process's cgroup, if it has one.
fn cgroup_limit_bytes() -> Option<u64> {
    let own = std::fs::read_to_string("/proc/self/cgroup").unwrap_or_default();
    let mut candidates = Vec::new();
    for line in own.lines() {
        // v2: "0::/path"; v1: "N:memory:/path".
        let mut parts = line.splitn(3, ':');
        let (_, controllers, path) = (parts.next(), parts.next(), parts.next());
        let Some(path) = path else { continue };
        match controllers {
            Some("") => candidates.push(format!("/sys/fs/cgroup{path}/memory.max")),
            Some(c) if c.split(',').any(|c| c == "memory") => {
                candidates.push(format!("/sys/fs/cgroup/memory{path}/memory.limit_in_bytes"))
            }
            _ => {}
        }
    }
    candidates.push("/sys/fs/cgroup/memory.max".to_owned());
    candidates.push("/sys/fs/cgroup/memory/memory.limit_in_bytes".to_owned());
    candidates
        .iter()
        .filter_map(|path| std::fs::read_to_string(path).ok())
        .filter_map(|text| cgroup_value(&text))
        .min()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn mem_total_and_cgroup_values_parse() {
        let meminfo = "MemTotal:       24684092 kB\nMemFree:        21123136 kB\n";
        assert_eq!(mem_total_bytes(meminfo), Some(24_684_092 * 1024));
        assert_eq!(mem_total_bytes("MemFree: 1 kB\n"), None);
        assert_eq!(cgroup_value("max\n"), None);
        assert_eq!(cgroup_value("6442450944\n"), Some(6 << 30));
        assert_eq!(cgroup_value("9223372036854771712\n"), None);
        // Wherever the tests run, the default is a positive share.
        assert!(default_budget_mib() >= 1);
    }

    #[test]
    fn needs_round_up_to_whole_mib() {
        assert_eq!(MemoryNeed::new(0, "x").mib(), 0);
        assert_eq!(MemoryNeed::new(1, "x").mib(), 1);
        assert_eq!(MemoryNeed::new(MIB, "x").mib(), 1);
        assert_eq!(MemoryNeed::new(MIB + 1, "x").mib(), 2);
    }

    #[test]
    fn a_frame_needs_its_largest_camera_detected_and_every_cameras_targets() {
        let need = frame_need(&[(1280, 1024), (8192, 8192)], None, true);
        let targets = (640 * 512 + (1 << 20)) * MATCH_BYTES_PER_TARGET;
        assert_eq!(need.bytes, 8192 * 8192 * DETECT_BYTES_PER_PIXEL + targets);
        // Uploaded targets are only matched.
        let matched = frame_need(&[(1280, 1024), (8192, 8192)], None, false);
        assert_eq!(matched.bytes, targets);
        // With a splitter the whole image and its views come on top.
        let split = frame_need(&[(100, 100); 4], Some((200, 200)), true);
        let plain = frame_need(&[(100, 100); 4], None, true);
        assert_eq!(split.bytes - plain.bytes, 200 * 200 * 4);
    }

    #[test]
    fn a_background_needs_its_kept_frames_and_one_decoded_image() {
        // 32 frames of one 8192x8192 16-bit camera: 4 GiB of samples, the
        // decoded frame, the view, the median and its PNG.
        let px = 8192 * 8192;
        assert_eq!(
            background_bytes(32, px, px, 2, 300_000),
            32 * px * 2 + px * 2 + 3 * px * 2 + 300_000
        );
    }

    #[test]
    fn a_median_background_keeps_fewer_frames_on_a_small_budget() {
        let px = 8192 * 8192;
        let need = |k| background_bytes(k, px, px, 2, 0);
        // The whole sample fits a large budget; a short recording keeps
        // all its frames whatever the bound.
        assert_eq!(
            median_sample_within(need(32), 32, 100, px, px, 2, 0),
            Some(32)
        );
        assert_eq!(
            median_sample_within(need(10), 32, 10, px, px, 2, 0),
            Some(32)
        );
        // One byte short of 32 frames: the next even bound, 30.
        assert_eq!(
            median_sample_within(need(32) - 1, 32, 100, px, px, 2, 0),
            Some(30)
        );
        // 2 GiB holds 12 frames of 128 MiB beside the 4 images of 128 MiB.
        assert_eq!(
            median_sample_within(2 << 30, 32, 100, px, px, 2, 0),
            Some(12)
        );
        // Less than the least sample: no median at all.
        let least = need(LEAST_MEDIAN_SAMPLE);
        assert_eq!(median_sample_within(least, 32, 100, px, px, 2, 0), Some(6));
        assert_eq!(median_sample_within(least - 1, 32, 100, px, px, 2, 0), None);
    }

    #[tokio::test]
    async fn jobs_wait_for_each_other_within_the_budget() {
        let budget = Arc::new(MemoryBudget::new(100, None));
        let first = budget
            .acquire(&MemoryNeed::new(60 * MIB, "a"))
            .await
            .unwrap();
        assert_eq!(budget.available_mib(), 40);
        // A second 60 MiB job waits until the first is done.
        let waiter = {
            let budget = budget.clone();
            tokio::spawn(async move { budget.acquire(&MemoryNeed::new(60 * MIB, "b")).await })
        };
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(!waiter.is_finished());
        assert_eq!(budget.waiting(), 1);
        drop(first);
        let second = tokio::time::timeout(Duration::from_secs(5), waiter)
            .await
            .unwrap()
            .unwrap()
            .unwrap();
        assert_eq!(second.mib(), 60);
        assert_eq!(budget.available_mib(), 40);
        drop(second);
        assert_eq!(budget.available_mib(), 100);
    }

    #[tokio::test]
    async fn a_wait_given_up_is_no_longer_counted_as_waiting() {
        let budget = MemoryBudget::new(100, None);
        let _held = budget
            .acquire(&MemoryNeed::new(60 * MIB, "a"))
            .await
            .unwrap();
        // A job cancelled while it waits (its future dropped at the timeout).
        let gave_up = tokio::time::timeout(
            Duration::from_millis(50),
            budget.acquire(&MemoryNeed::new(60 * MIB, "b")),
        )
        .await;
        assert!(gave_up.is_err());
        assert_eq!(budget.waiting(), 0);
    }

    #[tokio::test]
    async fn a_large_waiting_job_is_not_overtaken_by_smaller_ones() {
        let budget = Arc::new(MemoryBudget::new(100, None));
        let small = budget
            .acquire(&MemoryNeed::new(30 * MIB, "a"))
            .await
            .unwrap();
        let large = {
            let budget = budget.clone();
            tokio::spawn(async move { budget.acquire(&MemoryNeed::new(100 * MIB, "b")).await })
        };
        tokio::time::sleep(Duration::from_millis(50)).await;
        // 70 MiB are free, but a 10 MiB job arriving later queues behind
        // the large one instead of starving it.
        let later = {
            let budget = budget.clone();
            tokio::spawn(async move { budget.acquire(&MemoryNeed::new(10 * MIB, "c")).await })
        };
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(!large.is_finished());
        assert!(!later.is_finished());
        drop(small);
        let large = large.await.unwrap().unwrap();
        assert_eq!(large.mib(), 100);
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(!later.is_finished());
        drop(large);
        assert_eq!(later.await.unwrap().unwrap().mib(), 10);
    }

    #[tokio::test]
    async fn a_job_larger_than_the_budget_fails_for_good_with_the_reason() {
        let budget = MemoryBudget::new(100, None);
        let error = budget
            .acquire(&MemoryNeed::new(101 * MIB, "the median of something"))
            .await
            .unwrap_err();
        let BudgetError::TooLarge(message) = error else {
            panic!("{error:?} is not a permanent failure");
        };
        assert!(message.contains("about 101 MiB"), "{message}");
        assert!(message.contains("the median of something"), "{message}");
        assert!(message.contains("budget of 100 MiB"), "{message}");
        // Nothing was taken; a job of exactly the budget fits.
        assert_eq!(budget.available_mib(), 100);
        let all = budget
            .acquire(&MemoryNeed::new(100 * MIB, "x"))
            .await
            .unwrap();
        assert_eq!(budget.available_mib(), 0);
        drop(all);
        // A job that needs nothing does not wait.
        let none = budget.acquire(&MemoryNeed::new(0, "x")).await.unwrap();
        assert_eq!(none.mib(), 0);
    }

    #[test]
    fn metrics_show_the_budget_and_what_is_held() {
        let metrics = Arc::new(Metrics::default());
        let budget = MemoryBudget::new(100, Some(metrics.clone()));
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let grant = runtime
            .block_on(budget.acquire(&MemoryNeed::new(30 * MIB, "x")))
            .unwrap();
        let text = metrics.render(&[]);
        assert!(text.contains("ptv_memory_budget_mib 100\n"), "{text}");
        assert!(text.contains("ptv_memory_reserved_mib 30\n"), "{text}");
        drop(grant);
        let text = metrics.render(&[]);
        assert!(text.contains("ptv_memory_reserved_mib 0\n"), "{text}");
    }
}
