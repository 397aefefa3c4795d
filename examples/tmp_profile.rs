use nalgebra::Point2;
use ptv::photogrammetry::simulate::{self, RenderSpec};
use ptv::photogrammetry::{
    detect, detect_preprocessed, DetectionParameters, GreyImage, Preprocessing,
};
use rand::Rng;
fn frame(w: u32, h: u32, n: usize, seed: u64) -> GreyImage {
    let mut rng = simulate::rng(seed);
    let positions: Vec<Point2<f64>> = (0..n)
        .map(|_| {
            Point2::new(
                rng.random_range(0.0..f64::from(w)),
                rng.random_range(0.0..f64::from(h)),
            )
        })
        .collect();
    simulate::render(w, h, &positions, &RenderSpec::eight_bit(2.5), &mut rng)
}
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let big = args.get(1).map(|s| s == "big").unwrap_or(false);
    let bg = args.get(2).map(|s| s == "bg").unwrap_or(false);
    let split = args.get(3).map(|s| s != "nosplit").unwrap_or(true);
    let (w, h, n) = if big {
        (2304, 1720, 6000)
    } else {
        (1280, 1024, 2000)
    };
    let f = frame(w, h, n, 1);
    let b = {
        let mut rng = simulate::rng(3);
        simulate::render(w, h, &[], &RenderSpec::eight_bit(2.5), &mut rng)
    };
    let p = DetectionParameters {
        split,
        ..Default::default()
    };
    let pre = Preprocessing {
        background: Some(b),
        mask: None,
    };
    let iters: usize = std::env::var("ITERS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(300);
    let t = std::time::Instant::now();
    let mut count = 0;
    for _ in 0..iters {
        count += if bg {
            detect_preprocessed(&f, &pre, &p).unwrap().len()
        } else {
            detect(&f, &p).len()
        };
    }
    let dt = t.elapsed().as_secs_f64() / iters as f64;
    println!("{} targets, {:.3} ms per frame", count / iters, dt * 1e3);
}
