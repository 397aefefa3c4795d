//! Helpers shared by the test binaries: running the `ptv` binary, reading
//! golden JSON.

// Each test binary compiles this module and uses only some of it.
#![allow(dead_code)]

pub mod target_match;

use std::path::Path;
use std::process::{Command, Output};

/// Runs `ptv` with `args` in `dir`.
pub fn ptv(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ptv"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("the ptv binary runs")
}

/// Output bytes as text.
pub fn text(bytes: &[u8]) -> &str {
    std::str::from_utf8(bytes).expect("UTF-8 output")
}

/// Asserts success without warnings and returns standard output.
pub fn succeeds(output: &Output) -> String {
    let stderr = text(&output.stderr);
    assert!(output.status.success(), "{:?}: {stderr}", output.status);
    assert!(!stderr.contains("warning"), "{stderr}");
    text(&output.stdout).to_owned()
}

/// Asserts the failure contract: exit code 1, nothing on standard output and
/// one line `error: ...` on standard error that contains every `needle`.
pub fn fails(output: &Output, needles: &[&str]) {
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(output.stdout.is_empty(), "stdout: {}", text(&output.stdout));
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        stderr.starts_with("error: ") && stderr.ends_with('\n'),
        "{stderr}"
    );
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    for needle in needles {
        assert!(stderr.contains(needle), "`{needle}` not in: {stderr}");
    }
}

/// Asserts success with nothing at all on standard error and returns
/// standard output.
pub fn succeeds_silently(output: &Output) -> String {
    assert!(output.stderr.is_empty(), "{}", text(&output.stderr));
    succeeds(output)
}

/// A JSON array `[x, y, z]` as a point (golden files).
pub fn json_point3(v: &serde_json::Value) -> nalgebra::Point3<f64> {
    let coordinate = |i: usize| v[i].as_f64().expect("a number");
    nalgebra::Point3::new(coordinate(0), coordinate(1), coordinate(2))
}

/// A JSON array of `[x, y, z]` arrays as points.
pub fn json_points(v: &serde_json::Value) -> Vec<nalgebra::Point3<f64>> {
    v.as_array()
        .expect("an array of points")
        .iter()
        .map(json_point3)
        .collect()
}
