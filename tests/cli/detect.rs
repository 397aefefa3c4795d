//! Camera image files and `ptv detect`, run as a real process.
//!
//! A rendered frame written as PNG, as TIFF (uncompressed and LZW, 8 and 16
//! bits) and as raw little-endian samples must give exactly the targets the
//! library finds in the image itself: the files are lossless and the
//! writers print numbers that read back bit for bit. Files the detector
//! cannot use fail with exit code 1 and one `error:` line naming the file
//! and the problem.

use std::io::Cursor;

use image::ImageEncoder;
use nalgebra::Point2;
use ptv::formats::image::{decode_image, decode_raw, RawLayout};
use ptv::formats::{csv, openptv};
use ptv::photogrammetry::simulate::{self, RenderSpec};
use ptv::photogrammetry::{
    detect, detect_preprocessed, Centroid, DetectionParameters, GreyImage, GreyPixels, Mask,
    Preprocessing, Sensor,
};

use crate::common::{fails, ptv, succeeds_silently, text};

/// A 320x240 frame with 150 particles.
fn frame(spec: &RenderSpec) -> GreyImage {
    let mut rng = simulate::rng(9);
    let positions: Vec<Point2<f64>> = (0..150)
        .map(|_| {
            Point2::new(
                rng_coordinate(&mut rng, 320.0),
                rng_coordinate(&mut rng, 240.0),
            )
        })
        .collect();
    simulate::render(320, 240, &positions, spec, &mut rng)
}

fn rng_coordinate(rng: &mut impl rand::Rng, max: f64) -> f64 {
    rng.random_range(0.0..max)
}

fn png(image: &GreyImage) -> Vec<u8> {
    let mut bytes = Vec::new();
    let encoder = image::codecs::png::PngEncoder::new(&mut bytes);
    let (w, h) = (image.width(), image.height());
    match image.pixels() {
        GreyPixels::Eight(p) => encoder.write_image(p, w, h, image::ExtendedColorType::L8),
        GreyPixels::Sixteen(p) => {
            let native: Vec<u8> = p.iter().flat_map(|v| v.to_ne_bytes()).collect();
            encoder.write_image(&native, w, h, image::ExtendedColorType::L16)
        }
    }
    .unwrap();
    bytes
}

fn tiff(image: &GreyImage, compression: tiff::encoder::Compression) -> Vec<u8> {
    use tiff::encoder::{colortype, TiffEncoder};
    let mut bytes = Cursor::new(Vec::new());
    let mut encoder = TiffEncoder::new(&mut bytes)
        .unwrap()
        .with_compression(compression);
    let (w, h) = (image.width(), image.height());
    match image.pixels() {
        GreyPixels::Eight(p) => encoder.write_image::<colortype::Gray8>(w, h, p),
        GreyPixels::Sixteen(p) => encoder.write_image::<colortype::Gray16>(w, h, p),
    }
    .unwrap();
    bytes.into_inner()
}

fn raw(image: &GreyImage) -> Vec<u8> {
    match image.pixels() {
        GreyPixels::Eight(p) => p.clone(),
        GreyPixels::Sixteen(p) => p.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

#[test]
fn every_file_kind_decodes_to_the_same_image() {
    use tiff::encoder::Compression;
    for spec in [RenderSpec::eight_bit(2.5), RenderSpec::sixteen_bit(2.5)] {
        let image = frame(&spec);
        let layout = RawLayout {
            width: 320,
            height: 240,
            bit_depth: spec.bit_depth,
        };
        assert_eq!(decode_image(&png(&image), "f.png").unwrap(), image);
        for (compression, name) in [
            (Compression::Uncompressed, "uncompressed.tif"),
            (Compression::Lzw, "lzw.tif"),
        ] {
            let bytes = tiff(&image, compression);
            assert_eq!(decode_image(&bytes, name).unwrap(), image, "{name}");
        }
        assert_eq!(decode_raw(&raw(&image), &layout, "f.raw").unwrap(), image);
    }
}

#[test]
fn images_that_cannot_be_used_are_refused_by_name() {
    let image = frame(&RenderSpec::eight_bit(2.5));
    // Colour.
    let mut rgb = Vec::new();
    let GreyPixels::Eight(grey) = image.pixels() else {
        unreachable!("an 8-bit render")
    };
    let triple: Vec<u8> = grey.iter().flat_map(|&g| [g, g, g]).collect();
    image::codecs::png::PngEncoder::new(&mut rgb)
        .write_image(&triple, 320, 240, image::ExtendedColorType::Rgb8)
        .unwrap();
    let message = decode_image(&rgb, "rgb.png").unwrap_err().to_string();
    assert!(
        message.starts_with("rgb.png: PNG: the image is colour"),
        "{message}"
    );
    // Grey with alpha.
    let pairs: Vec<u8> = grey.iter().flat_map(|&g| [g, 255]).collect();
    let mut la = Vec::new();
    image::codecs::png::PngEncoder::new(&mut la)
        .write_image(&pairs, 320, 240, image::ExtendedColorType::La8)
        .unwrap();
    let message = decode_image(&la, "la.png").unwrap_err().to_string();
    assert!(message.contains("alpha"), "{message}");
    // Floating point.
    let mut float = Cursor::new(Vec::new());
    let samples: Vec<f32> = grey.iter().map(|&g| f32::from(g)).collect();
    tiff::encoder::TiffEncoder::new(&mut float)
        .unwrap()
        .write_image::<tiff::encoder::colortype::Gray32Float>(320, 240, &samples)
        .unwrap();
    let message = decode_image(float.get_ref(), "float.tif")
        .unwrap_err()
        .to_string();
    assert!(
        message.starts_with("float.tif: TIFF:") && message.contains("greyscale"),
        "{message}"
    );
    // Truncated files.
    for (bytes, name) in [
        (png(&image), "cut.png"),
        (tiff(&image, tiff::encoder::Compression::Lzw), "cut.tif"),
    ] {
        let cut = &bytes[..bytes.len() / 2];
        let message = decode_image(cut, name).unwrap_err().to_string();
        assert!(
            message.starts_with(name) && message.contains("truncated or corrupt"),
            "{message}"
        );
    }
    // Corrupt: a valid signature followed by garbage.
    let mut garbage = b"\x89PNG\r\n\x1a\n".to_vec();
    garbage.extend(std::iter::repeat_n(0xA5, 100));
    assert!(decode_image(&garbage, "g.png").is_err());
}

#[test]
fn images_are_checked_against_the_sensor() {
    let image = frame(&RenderSpec::eight_bit(2.5));
    let mut sensor = Sensor {
        width: 320,
        height: 240,
        pixel_size_x: 0.012,
        pixel_size_y: 0.012,
    };
    assert!(image.check_sensor(&sensor).is_ok());
    sensor.height = 256;
    let message = image.check_sensor(&sensor).unwrap_err().to_string();
    assert!(
        message.contains("320x240") && message.contains("320x256"),
        "{message}"
    );
}

#[test]
fn detect_writes_the_library_targets_from_every_file_kind() {
    let dir = tempfile::tempdir().unwrap();
    let eight = frame(&RenderSpec::eight_bit(2.5));
    let expected = detect(&eight, &DetectionParameters::default());
    assert!(expected.len() > 100, "{}", expected.len());
    std::fs::write(dir.path().join("f.png"), png(&eight)).unwrap();
    std::fs::write(
        dir.path().join("f.tif"),
        tiff(&eight, tiff::encoder::Compression::Lzw),
    )
    .unwrap();
    std::fs::write(dir.path().join("f.raw"), raw(&eight)).unwrap();
    for args in [
        vec!["detect", "--image", "f.png"],
        vec!["detect", "--image", "f.tif"],
        vec![
            "detect", "--image", "f.raw", "--width", "320", "--height", "240", "--bits", "8",
        ],
    ] {
        let out = succeeds_silently(&ptv(&args, dir.path()));
        assert_eq!(
            csv::parse_targets(&out, "stdout").unwrap(),
            expected,
            "{args:?}"
        );
    }
    let out = succeeds_silently(&ptv(
        &["detect", "--image", "f.png", "--format", "openptv"],
        dir.path(),
    ));
    assert_eq!(openptv::parse_targets(&out, "stdout").unwrap(), expected);

    // 16 bits, with every parameter given.
    let sixteen = frame(&RenderSpec::sixteen_bit(2.5));
    std::fs::write(dir.path().join("g.raw"), raw(&sixteen)).unwrap();
    let parameters = DetectionParameters {
        threshold: 2570,
        highpass_radius: 6,
        min_pixels: 3,
        max_pixels: 40,
        min_sumg: 20_000,
        split: false,
        centroid: Centroid::Gaussian,
        ..DetectionParameters::default()
    };
    let out = succeeds_silently(&ptv(
        &[
            "detect",
            "--image",
            "g.raw",
            "--width",
            "320",
            "--height",
            "240",
            "--bits",
            "16",
            "--threshold",
            "2570",
            "--highpass-radius",
            "6",
            "--min-pixels",
            "3",
            "--max-pixels",
            "40",
            "--min-sumg",
            "20000",
            "--no-split",
            "--centroid",
            "gaussian",
        ],
        dir.path(),
    ));
    assert_eq!(
        csv::parse_targets(&out, "stdout").unwrap(),
        detect(&sixteen, &parameters)
    );
    // Without a threshold a 16-bit image gets a warning, not an error.
    let output = ptv(
        &[
            "detect", "--image", "g.raw", "--width", "320", "--height", "240", "--bits", "16",
        ],
        dir.path(),
    );
    assert!(output.status.success());
    assert!(text(&output.stderr).starts_with("warning: g.raw is a 16-bit image"));
}

#[test]
fn detect_failures_print_one_error_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let image = frame(&RenderSpec::eight_bit(2.5));
    std::fs::write(d.join("f.raw"), raw(&image)).unwrap();
    std::fs::write(d.join("f.pgm"), b"P5\n320 240\n255\n").unwrap();
    let bytes = png(&image);
    std::fs::write(d.join("cut.png"), &bytes[..bytes.len() - 100]).unwrap();
    fails(
        &ptv(&["detect", "--image", "missing.png"], d),
        &["missing.png"],
    );
    fails(
        &ptv(&["detect", "--image", "f.pgm"], d),
        &[
            "f.pgm",
            "neither a PNG nor a TIFF",
            "width, height and bit depth",
        ],
    );
    fails(
        &ptv(&["detect", "--image", "cut.png"], d),
        &["cut.png", "truncated or corrupt"],
    );
    fails(
        &ptv(
            &[
                "detect", "--image", "f.raw", "--width", "321", "--height", "240", "--bits", "8",
            ],
            d,
        ),
        &["f.raw", "needs 77040 bytes", "76800"],
    );
    fails(
        &ptv(
            &[
                "detect", "--image", "f.raw", "--width", "0", "--height", "240", "--bits", "8",
            ],
            d,
        ),
        &["f.raw", "empty"],
    );
    fails(
        &ptv(
            &[
                "detect",
                "--image",
                "f.png",
                "--min-pixels",
                "9",
                "--max-pixels",
                "4",
            ],
            d,
        ),
        &["min_pixels", "max_pixels"],
    );
    // Usage errors keep clap's exit code 2.
    for args in [
        vec!["detect", "--image", "f.raw", "--width", "320"],
        vec![
            "detect", "--image", "f.raw", "--width", "320", "--height", "240", "--bits", "12",
        ],
        vec!["detect", "--image", "f.png", "--format", "xml"],
        vec!["detect", "--image", "f.png", "--centroid", "gauss"],
    ] {
        assert_eq!(ptv(&args, d).status.code(), Some(2), "{args:?}");
    }
}

#[test]
fn detect_subtracts_a_background_and_applies_a_mask() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let image = frame(&RenderSpec::eight_bit(2.5));
    std::fs::write(d.join("f.png"), png(&image)).unwrap();
    // The frame as its own background: nothing is left.
    let out = succeeds_silently(&ptv(
        &["detect", "--image", "f.png", "--background", "f.png"],
        d,
    ));
    assert_eq!(csv::parse_targets(&out, "stdout").unwrap(), Vec::new());
    // A mask of the left half: the library's targets with that mask, all
    // on the left.
    let mask = GreyImage::from_u8(
        320,
        240,
        (0..320 * 240)
            .map(|i| if i % 320 < 160 { 255 } else { 0 })
            .collect(),
    )
    .unwrap();
    std::fs::write(d.join("mask.png"), png(&mask)).unwrap();
    let preprocessing = Preprocessing {
        background: None,
        mask: Some(Mask::from_image(&mask)),
    };
    let expected =
        detect_preprocessed(&image, &preprocessing, &DetectionParameters::default()).unwrap();
    assert!(expected.len() > 40, "{}", expected.len());
    assert!(expected.iter().all(|t| t.x < 160.0));
    let out = succeeds_silently(&ptv(
        &["detect", "--image", "f.png", "--mask", "mask.png"],
        d,
    ));
    assert_eq!(csv::parse_targets(&out, "stdout").unwrap(), expected);

    // Misfits name the flag, the file and the size expected.
    let small = GreyImage::from_u8(100, 80, vec![0; 8000]).unwrap();
    std::fs::write(d.join("small.png"), png(&small)).unwrap();
    let deep = GreyImage::from_u16(320, 240, vec![0; 320 * 240]).unwrap();
    std::fs::write(d.join("deep.png"), png(&deep)).unwrap();
    fails(
        &ptv(
            &["detect", "--image", "f.png", "--background", "small.png"],
            d,
        ),
        &["--background", "small.png", "100x80", "320x240"],
    );
    fails(
        &ptv(
            &["detect", "--image", "f.png", "--background", "deep.png"],
            d,
        ),
        &["--background", "deep.png", "16-bit", "8-bit"],
    );
    fails(
        &ptv(&["detect", "--image", "f.png", "--mask", "small.png"], d),
        &["--mask", "small.png", "100x80", "320x240"],
    );
    fails(
        &ptv(&["detect", "--image", "f.png", "--mask", "missing.png"], d),
        &["missing.png"],
    );
}
