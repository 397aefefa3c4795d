//! `ptv background`, run as a real process: the median of a static scene
//! with moving particles is the scene itself, the minimum is the
//! per-pixel minimum, 8- and 16-bit, PNG and TIFF out; frames that do not
//! fit are refused with the file named.

use std::path::Path;

use image::{ExtendedColorType, ImageEncoder};
use ptv::formats::image::read_image;
use ptv::photogrammetry::{GreyImage, GreyPixels};

use crate::common::{fails, ptv, succeeds};

const WIDTH: u32 = 64;
const HEIGHT: u32 = 48;

/// The static scene: a sloping background with a bright window (brighter
/// than some particles), in 16 bits.
fn scene() -> Vec<u16> {
    (0..HEIGHT)
        .flat_map(|y| {
            (0..WIDTH).map(move |x| {
                if (20..40).contains(&x) && (10..30).contains(&y) {
                    50_000
                } else {
                    1_000 + 40 * x as u16 + 25 * y as u16
                }
            })
        })
        .collect()
}

/// Frame `t`: the scene with four 3x3 particles that move 4 px right and
/// 3 px down per frame, so that a pixel is covered in at most a few of
/// the frames. Grey 20,000: darker than the window, brighter than the rest.
fn frame(t: u32) -> Vec<u16> {
    let mut pixels = scene();
    for particle in 0..4u32 {
        let cx = (t * 4 + particle * 17) % (WIDTH - 3);
        let cy = (t * 3 + particle * 11) % (HEIGHT - 3);
        for y in cy..cy + 3 {
            for x in cx..cx + 3 {
                pixels[(y * WIDTH + x) as usize] = 20_000;
            }
        }
    }
    pixels
}

fn write_png16(path: &Path, pixels: &[u16]) {
    let bytes: Vec<u8> = pixels.iter().flat_map(|v| v.to_ne_bytes()).collect();
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(&bytes, WIDTH, HEIGHT, ExtendedColorType::L16)
        .unwrap();
    std::fs::write(path, out).unwrap();
}

fn write_png8(path: &Path, width: u32, height: u32, pixels: &[u8]) {
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(pixels, width, height, ExtendedColorType::L8)
        .unwrap();
    std::fs::write(path, out).unwrap();
}

/// `--image NAME` for each name.
fn image_flags(names: &[String]) -> Vec<&str> {
    names.iter().flat_map(|n| ["--image", n.as_str()]).collect()
}

#[test]
fn the_median_of_a_static_scene_with_moving_particles_is_the_scene() {
    let dir = tempfile::tempdir().unwrap();
    // 40 frames: more than the 32 a median keeps, so the sample is thinned.
    let names: Vec<String> = (0..40).map(|t| format!("cam0.{t:04}.png")).collect();
    for (t, name) in names.iter().enumerate() {
        write_png16(&dir.path().join(name), &frame(t as u32));
    }
    for output in ["bg.png", "bg.tif"] {
        let mut args = vec!["background", "--mode", "median", "-o", output];
        args.extend(image_flags(&names));
        let out = ptv(&args, dir.path());
        succeeds(&out);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains("median of 20 of 40 frames"), "{stderr}");
        let background = read_image(&dir.path().join(output), None).unwrap();
        // Exact: the median's values are grey values the frames had, and
        // no pixel is covered by a particle in half the kept frames.
        assert_eq!(
            background.pixels(),
            &GreyPixels::Sixteen(scene()),
            "{output}"
        );
    }
}

#[test]
fn the_minimum_is_the_per_pixel_minimum_of_every_frame() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (7u32, 5u32);
    let frames: Vec<Vec<u8>> = (0..6u32)
        .map(|t| {
            (0..w * h)
                .map(|i| ((i * 37 + t * 91) % 256) as u8)
                .collect()
        })
        .collect();
    let names: Vec<String> = (0..frames.len()).map(|t| format!("f{t}.png")).collect();
    for (name, pixels) in names.iter().zip(&frames) {
        write_png8(&dir.path().join(name), w, h, pixels);
    }
    let mut args = vec!["background", "--mode", "min", "-o", "min.tiff"];
    args.extend(image_flags(&names));
    succeeds(&ptv(&args, dir.path()));
    let expected: Vec<u8> = (0..(w * h) as usize)
        .map(|i| frames.iter().map(|f| f[i]).min().unwrap())
        .collect();
    let background = read_image(&dir.path().join("min.tiff"), None).unwrap();
    assert_eq!(
        background,
        GreyImage::from_u8(w, h, expected).unwrap(),
        "8-bit in, 8-bit out"
    );
}

#[test]
fn frames_that_do_not_fit_are_refused_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    write_png8(&dir.path().join("a.png"), 4, 3, &[1; 12]);
    write_png8(&dir.path().join("b.png"), 3, 4, &[1; 12]);
    write_png16(&dir.path().join("c.png"), &scene());
    let run = |args: &[&str]| ptv(args, dir.path());
    fails(
        &run(&[
            "background",
            "--image",
            "a.png",
            "--image",
            "b.png",
            "-o",
            "bg.png",
        ]),
        &["b.png", "frame 1 is 3x4 but the background is 4x3"],
    );
    fails(
        &run(&[
            "background",
            "--image",
            "c.png",
            "--image",
            "a.png",
            "-o",
            "bg.png",
        ]),
        &["a.png", "frame 1 is 4x3 but the background is 64x48"],
    );
    fails(
        &run(&[
            "background",
            "--image",
            "a.png",
            "--image",
            "gone.png",
            "-o",
            "bg.png",
        ]),
        &["gone.png"],
    );
    fails(
        &run(&["background", "--image", "a.png", "-o", "bg.jpg"]),
        &["--output", "bg.jpg", ".png or .tif"],
    );
    fails(
        &run(&[
            "background",
            "--image",
            "a.png",
            "--sample-frames",
            "3",
            "-o",
            "bg.png",
        ]),
        &["--sample-frames", "even number"],
    );
    assert!(!dir.path().join("bg.png").exists(), "no output on failure");
}
