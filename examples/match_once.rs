//! Matches the correspondence benchmark's 4-camera scene (`benches/correspond.rs`)
//! and prints the quality and the fastest and median time: a harness for
//! profilers, whose figures can be counted where wall-clock time is noisy.
//!
//! ```text
//! cargo build --release --example match_once
//! target/release/examples/match_once 10000 25          # particles, repetitions
//! target/release/examples/match_once 10000 25 2        # ... and the band (px, default 0.5)
//! valgrind --tool=callgrind --cache-sim=yes --LL=1048576,16,64 \
//!     --toggle-collect='*Matcher::match_frame_until*' target/release/examples/match_once 10000 1 2
//! ```
//!
//! (`*Matcher::match_frame*` would toggle twice, in `match_frame` and the
//! `match_frame_until` it calls, and collect nothing.) Instructions of
//! `match_frame_until` at 10,000 particles: 334 M at 0.5 px, 395 M at 2 px,
//! 501 M at 4 px, 1,614 M at 10 px (before the band was narrowed to the
//! frame's noise: 326 M, 2,311 M, 11,177 M, and about 14 s at 10 px).

use std::time::{Duration, Instant};

use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
use ptv::photogrammetry::simulate::{self, MatchScore, RigSpec};

fn main() {
    let mut args = std::env::args().skip(1);
    const USAGE: &str = "usage: match_once [PARTICLES] [REPETITIONS] [BAND_PX]";
    let mut number = |default: usize| {
        args.next()
            .map_or(Ok(default), |s| s.parse())
            .unwrap_or_else(|e| {
                eprintln!("{USAGE}: {e}");
                std::process::exit(2)
            })
    };
    let (particles, repetitions) = (number(10_000), number(1).max(1));
    let tolerance: f64 = args
        .next()
        .map_or(Ok(0.5), |s| s.parse())
        .unwrap_or_else(|e| {
            eprintln!("{USAGE}: the band: {e}");
            std::process::exit(2)
        });
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().expect("the simulator's rig is valid");
    let mut rng = simulate::rng(particles as u64);
    let points = simulate::particles(&spec.volume, particles, &mut rng);
    let frame = simulate::target_frame(&cameras, &points, 0.1, 0.1, &mut rng);
    let parameters = MatchingParameters {
        tolerance,
        volume: Some(spec.volume),
        ..MatchingParameters::default()
    };
    let matcher = Matcher::new(&cameras, &parameters).unwrap_or_else(|e| {
        eprintln!("{USAGE}: {e}");
        std::process::exit(2)
    });
    let mut times: Vec<Duration> = Vec::with_capacity(repetitions);
    let mut found = Vec::new();
    for _ in 0..repetitions {
        let start = Instant::now();
        found = matcher.match_frame(&frame.targets).expect("matching runs");
        times.push(start.elapsed());
    }
    times.sort();
    let score = MatchScore::of(&found, &frame, &points);
    println!(
        "{particles} particles, band {tolerance} px: {} correct, {} ghosts (4/3/2 cameras {}/{}/{}), RMS error {:.5} mm; \
         fastest {:.1} ms, median {:.1} ms of {repetitions}",
        score.correct,
        score.ghosts,
        score.by_cameras[4],
        score.by_cameras[3],
        score.by_cameras[2],
        score.rms_error,
        times[0].as_secs_f64() * 1e3,
        times[times.len() / 2].as_secs_f64() * 1e3,
    );
}
