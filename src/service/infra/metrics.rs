//! Counters for `/metrics`, rendered in Prometheus' text format by hand:
//! HTTP requests by method, route and status, job durations and particles
//! per frame as histograms. Queue depth and jobs by state are read from the
//! database at scrape time, so they are right across restarts.
//!
//! Written by hand rather than with the `metrics` crate and its Prometheus
//! exporter: that exporter's recorder is one per process, where these
//! counters belong to one service (several run in one test process, each
//! asserting its own counts), and without the macros its per-instance use is
//! no shorter than this file; it would also bring about fifteen crates
//! (evmap, quanta, sketches, ...) to replace some 170 lines.
//!
//! Every label takes its values from a set fixed here or by the code, never
//! from what a client sends, so the series cannot grow without bound
//! (a client could otherwise make one per invented method name): methods
//! outside RFC 9110's eight and PATCH count as `OTHER`, routes are the
//! router's patterns (`unmatched` for the rest), and a status outside
//! [`STATUSES`] counts as its class (`4xx`).

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

/// A cumulative histogram.
#[derive(Clone, Debug)]
struct Histogram {
    bounds: &'static [f64],
    counts: Vec<u64>,
    sum: f64,
    count: u64,
}

impl Histogram {
    fn new(bounds: &'static [f64]) -> Histogram {
        Histogram {
            bounds,
            counts: vec![0; bounds.len()],
            sum: 0.0,
            count: 0,
        }
    }

    fn observe(&mut self, value: f64) {
        for (bound, count) in self.bounds.iter().zip(&mut self.counts) {
            if value <= *bound {
                *count += 1;
            }
        }
        self.sum += value;
        self.count += 1;
    }

    fn render(&self, out: &mut String, name: &str, labels: &str) {
        let sep = if labels.is_empty() { "" } else { "," };
        for (bound, count) in self.bounds.iter().zip(&self.counts) {
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{bound}\"}} {count}");
        }
        let _ = writeln!(
            out,
            "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {}",
            self.count
        );
        let braces = if labels.is_empty() {
            String::new()
        } else {
            format!("{{{labels}}}")
        };
        let _ = writeln!(out, "{name}_sum{braces} {}", self.sum);
        let _ = writeln!(out, "{name}_count{braces} {}", self.count);
    }
}

const DURATION_BOUNDS: &[f64] = &[0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0];
const PARTICLE_BOUNDS: &[f64] = &[0.0, 10.0, 100.0, 500.0, 1000.0, 2000.0, 5000.0, 10000.0];

/// The statuses counted by their own code; any other counts as its class.
pub const STATUSES: &[u16] = &[
    100, 101, 200, 201, 202, 204, 206, 301, 302, 303, 304, 307, 308, 400, 401, 403, 404, 405, 406,
    408, 409, 410, 411, 412, 413, 414, 415, 416, 417, 422, 426, 428, 429, 431, 499, 500, 501, 502,
    503, 504, 505, 507,
];

/// The method's label: its name if it is one of the standard ones, else
/// `OTHER`.
fn method_label(method: &str) -> &'static str {
    const METHODS: [&str; 9] = [
        "GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH",
    ];
    METHODS
        .into_iter()
        .find(|known| *known == method)
        .unwrap_or("OTHER")
}

/// A status label: the code itself if it is in [`STATUSES`], else its
/// class (`4xx`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum StatusLabel {
    Code(u16),
    Class(u16),
}

impl StatusLabel {
    fn of(status: u16) -> StatusLabel {
        if STATUSES.contains(&status) {
            StatusLabel::Code(status)
        } else {
            StatusLabel::Class((status / 100).min(9))
        }
    }
}

impl std::fmt::Display for StatusLabel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StatusLabel::Code(code) => write!(f, "{code}"),
            StatusLabel::Class(class) => write!(f, "{class}xx"),
        }
    }
}

#[derive(Debug, Default)]
struct Inner {
    /// (method, route, status) -> count, each label from a bounded set.
    requests: BTreeMap<(&'static str, String, StatusLabel), u64>,
    /// (kind, outcome) -> durations.
    job_seconds: BTreeMap<(String, &'static str), Histogram>,
    particles: Option<Histogram>,
}

/// The service's counters.
#[derive(Debug, Default)]
pub struct Metrics {
    inner: Mutex<Inner>,
    /// Open connections, the limit, and connections closed to make room.
    connections: AtomicU64,
    connection_limit: AtomicU64,
    evicted: AtomicU64,
    /// The workers' memory budget and the MiB its jobs hold now
    /// (`service::budget`).
    memory_budget: AtomicU64,
    memory_reserved: AtomicU64,
    /// Requests whose body arrived too slowly, ended at the limit to let a
    /// new connection in.
    slow_evicted: AtomicU64,
    /// Calibration drift alarms this process announced.
    calibration_alarms: AtomicU64,
}

/// One camera's calibration health in a sequence whose monitor advanced
/// lately, for [`render_health`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraDrift {
    /// The sequence's id.
    pub sequence: i64,
    /// The camera, from 0.
    pub camera: usize,
    /// The windowed mean disparity's drift from the baseline (px; 0 before
    /// the baseline is complete).
    pub drift_px: f64,
    /// Whether the camera's alarm fired.
    pub alarm: bool,
}

/// The calibration health gauges: per sequence whose drift monitor advanced
/// within the last hour (at most 100 sequences, the newest; the caller
/// reads them) and camera (at most 16), its drift and whether its alarm
/// fired; so at most 1,600 series of each, and they go away an hour after
/// a run stops.
pub fn render_health(cameras: &[CameraDrift]) -> String {
    let mut out = String::new();
    out.push_str(
        "# HELP ptv_calibration_drift_px A camera's mean disparity drift from the run's first \
         frames (px), per sequence advanced in the last hour.\n",
    );
    out.push_str("# TYPE ptv_calibration_drift_px gauge\n");
    for c in cameras {
        let _ = writeln!(
            out,
            "ptv_calibration_drift_px{{sequence=\"{}\",camera=\"{}\"}} {}",
            c.sequence, c.camera, c.drift_px
        );
    }
    out.push_str(
        "# HELP ptv_calibration_drift_alarm 1 when a camera's drift passed the sequence's \
         threshold (self-calibrate), per sequence advanced in the last hour.\n",
    );
    out.push_str("# TYPE ptv_calibration_drift_alarm gauge\n");
    for c in cameras {
        let _ = writeln!(
            out,
            "ptv_calibration_drift_alarm{{sequence=\"{}\",camera=\"{}\"}} {}",
            c.sequence,
            c.camera,
            u8::from(c.alarm)
        );
    }
    out
}

impl Metrics {
    fn with<T>(&self, f: impl FnOnce(&mut Inner) -> T) -> T {
        let mut inner = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut inner)
    }

    /// Counts a request to `route` (the matched path pattern, or
    /// `unmatched`: never the path a client sent); the method and status
    /// are folded into bounded labels here.
    pub fn request(&self, method: &str, route: &str, status: u16) {
        let key = (
            method_label(method),
            route.to_owned(),
            StatusLabel::of(status),
        );
        self.with(|i| *i.requests.entry(key).or_default() += 1);
    }

    /// The connection limit (`--max-connections`).
    pub fn connection_limit(&self, max: usize) {
        self.connection_limit.store(max as u64, Ordering::Relaxed);
    }

    /// The connections open now.
    pub fn connections_open(&self, open: usize) {
        self.connections.store(open as u64, Ordering::Relaxed);
    }

    /// An idle connection closed to make room for a new one; `open` now.
    pub fn connection_evicted(&self, open: usize) {
        self.evicted.fetch_add(1, Ordering::Relaxed);
        self.connections_open(open);
    }

    /// The workers' memory budget (MiB, `--memory-budget-mb`).
    pub fn memory_budget(&self, mib: u64) {
        self.memory_budget.store(mib, Ordering::Relaxed);
    }

    /// A job took `mib` of the memory budget.
    pub fn memory_reserved(&self, mib: u64) {
        self.memory_reserved.fetch_add(mib, Ordering::Relaxed);
    }

    /// A job gave back `mib` of the memory budget.
    pub fn memory_released(&self, mib: u64) {
        self.memory_reserved.fetch_sub(mib, Ordering::Relaxed);
    }

    /// Records a finished job attempt.
    pub fn job(&self, kind: &str, outcome: &'static str, seconds: f64) {
        self.with(|i| {
            i.job_seconds
                .entry((kind.to_owned(), outcome))
                .or_insert_with(|| Histogram::new(DURATION_BOUNDS))
                .observe(seconds);
        });
    }

    /// Records a processed frame's particle count.
    pub fn particles(&self, count: usize) {
        self.with(|i| {
            i.particles
                .get_or_insert_with(|| Histogram::new(PARTICLE_BOUNDS))
                .observe(count as f64);
        });
    }

    /// A request whose body arrived below `--min-body-rate` ended (408) to
    /// make room for a new connection.
    pub fn slow_body_evicted(&self) {
        self.slow_evicted.fetch_add(1, Ordering::Relaxed);
    }

    /// A calibration drift alarm announced.
    pub fn calibration_alarm(&self) {
        self.calibration_alarms.fetch_add(1, Ordering::Relaxed);
    }

    /// The text exposition; `jobs` are (kind, state, count) from the store.
    pub fn render(&self, jobs: &[(String, String, i64)]) -> String {
        let mut out = String::new();
        out.push_str("# HELP ptv_http_requests_total HTTP requests by route and status.\n");
        out.push_str("# TYPE ptv_http_requests_total counter\n");
        self.with(|i| {
            for ((method, route, status), count) in &i.requests {
                let _ = writeln!(
                    out,
                    "ptv_http_requests_total{{method=\"{method}\",route=\"{}\",status=\"{status}\"}} {count}",
                    escape(route)
                );
            }
        });
        let connections = [
            (
                "ptv_http_connections",
                "gauge",
                "Open HTTP connections.",
                &self.connections,
            ),
            (
                "ptv_http_connections_max",
                "gauge",
                "The connection limit (--max-connections).",
                &self.connection_limit,
            ),
            (
                "ptv_http_connections_evicted_total",
                "counter",
                "Idle connections closed at the limit to let a new one in.",
                &self.evicted,
            ),
            (
                "ptv_memory_budget_mib",
                "gauge",
                "The workers' memory budget (--memory-budget-mb).",
                &self.memory_budget,
            ),
            (
                "ptv_memory_reserved_mib",
                "gauge",
                "MiB of the memory budget held by running jobs.",
                &self.memory_reserved,
            ),
            (
                "ptv_http_slow_bodies_evicted_total",
                "counter",
                "Requests whose body arrived below --min-body-rate, ended with 408 at the \
                 limit to let a new connection in.",
                &self.slow_evicted,
            ),
            (
                "ptv_calibration_drift_alarms_total",
                "counter",
                "Calibration drift alarms this process announced (calibration_drift events).",
                &self.calibration_alarms,
            ),
        ];
        for (name, kind, help, value) in connections {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} {kind}");
            let _ = writeln!(out, "{name} {}", value.load(Ordering::Relaxed));
        }
        out.push_str("# HELP ptv_queue_depth Jobs waiting for a worker.\n");
        out.push_str("# TYPE ptv_queue_depth gauge\n");
        let queued: i64 = jobs
            .iter()
            .filter(|(_, state, _)| state == "queued")
            .map(|(_, _, n)| n)
            .sum();
        let _ = writeln!(out, "ptv_queue_depth {queued}");
        out.push_str("# HELP ptv_jobs Jobs by kind and state.\n");
        out.push_str("# TYPE ptv_jobs gauge\n");
        for (kind, state, count) in jobs {
            let _ = writeln!(
                out,
                "ptv_jobs{{kind=\"{}\",state=\"{}\"}} {count}",
                escape(kind),
                escape(state)
            );
        }
        out.push_str("# HELP ptv_job_duration_seconds Job attempts by kind and outcome.\n");
        out.push_str("# TYPE ptv_job_duration_seconds histogram\n");
        self.with(|i| {
            for ((kind, outcome), histogram) in &i.job_seconds {
                let labels = format!("kind=\"{}\",outcome=\"{outcome}\"", escape(kind));
                histogram.render(&mut out, "ptv_job_duration_seconds", &labels);
            }
            out.push_str("# HELP ptv_frame_particles Particles found per processed frame.\n");
            out.push_str("# TYPE ptv_frame_particles histogram\n");
            i.particles
                .clone()
                .unwrap_or_else(|| Histogram::new(PARTICLE_BOUNDS))
                .render(&mut out, "ptv_frame_particles", "");
        });
        out
    }
}

/// Escapes a label value.
fn escape(value: &str) -> String {
    value
        .replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request_lines(metrics: &Metrics) -> Vec<String> {
        metrics
            .render(&[])
            .lines()
            .filter(|l| l.starts_with("ptv_http_requests_total{"))
            .map(str::to_owned)
            .collect()
    }

    #[test]
    fn labels_come_from_bounded_sets() {
        let metrics = Metrics::default();
        for i in 0..300 {
            metrics.request(&format!("X{i}"), "unmatched", 405);
            metrics.request("GET", "/healthz", 200 + (i % 100) as u16);
            metrics.request("GET", "/healthz", 600 + i as u16);
        }
        let lines = request_lines(&metrics);
        assert!(
            lines.contains(
                &"ptv_http_requests_total{method=\"OTHER\",route=\"unmatched\",status=\"405\"} 300"
                    .to_owned()
            ),
            "{lines:#?}"
        );
        // 200, 201, 202, 204, 206 and 2xx; 6xx, 7xx, 8xx; OTHER's 405.
        assert_eq!(lines.len(), 6 + 3 + 1, "{lines:#?}");
        assert!(
            lines.iter().any(|l| l.contains("status=\"2xx\"} 285")),
            "{lines:#?}"
        );
    }
}
