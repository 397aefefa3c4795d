//! Multipart uploads fuzzed: every route that reads multipart fields (frame
//! uploads, calibration solving, OpenPTV calibrations) gets bodies built
//! from valid ones by random edits: parts renamed, dropped, repeated or
//! reordered, their contents mutated (images with bytes flipped or cut,
//! targets and text files with tokens that break parsers), and the raw
//! multipart framing itself damaged (boundaries cut or corrupted).
//!
//! What must hold for every body: an answer below 500 (the service never
//! fails on what a client sends), problem+json on every error, and the
//! database consistent afterwards (every frame has exactly one job, no
//! job refers to a missing frame). The random generator is seeded, so a
//! failure repeats; `PTV_FUZZ_CASES` (default 48 per route) runs longer.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use reqwest::multipart::{Form, Part};

use crate::helpers::*;

/// Cases per route: the environment's `PTV_FUZZ_CASES`, else 48 (about a
/// second each route here).
fn cases() -> usize {
    std::env::var("PTV_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(48)
}

/// Tokens that break careless parsers.
const TOKENS: &[&[u8]] = &[
    b"NaN",
    b"inf",
    b"-1e308",
    b"99999999999999999999",
    b"\r\n",
    b"\0",
    b",",
    b"\"",
    b"{",
    b"]",
    b"--",
    b"\r\n--",
];

/// A few random edits of `bytes`.
fn mutate(rng: &mut StdRng, bytes: &[u8]) -> Vec<u8> {
    let mut out = bytes.to_vec();
    for _ in 0..rng.random_range(0..6) {
        let at = if out.is_empty() {
            0
        } else {
            rng.random_range(0..out.len())
        };
        match rng.random_range(0..4) {
            0 if !out.is_empty() => out[at] = rng.random(),
            1 => {
                let token = TOKENS[rng.random_range(0..TOKENS.len())];
                out.splice(at..at, token.iter().copied());
            }
            2 => {
                let end = (at + rng.random_range(1..64)).min(out.len());
                out.drain(at..end);
            }
            _ => out.truncate(at),
        }
    }
    out
}

/// One part of a form before it is fuzzed.
struct Piece {
    name: String,
    bytes: Vec<u8>,
}

/// The valid pieces, fuzzed: renamed, dropped, repeated, reordered,
/// mutated.
fn fuzz_pieces(rng: &mut StdRng, valid: &[Piece], names: &[&str]) -> Vec<Piece> {
    let mut pieces = Vec::new();
    for piece in valid {
        match rng.random_range(0..10) {
            0 => {} // dropped
            1 => {
                pieces.push(Piece {
                    name: piece.name.clone(),
                    bytes: piece.bytes.clone(),
                });
                pieces.push(Piece {
                    name: piece.name.clone(),
                    bytes: mutate(rng, &piece.bytes),
                });
            }
            2 => pieces.push(Piece {
                name: names[rng.random_range(0..names.len())].to_owned(),
                bytes: piece.bytes.clone(),
            }),
            3..=5 => pieces.push(Piece {
                name: piece.name.clone(),
                bytes: mutate(rng, &piece.bytes),
            }),
            _ => pieces.push(Piece {
                name: piece.name.clone(),
                bytes: piece.bytes.clone(),
            }),
        }
    }
    if rng.random_bool(0.3) && pieces.len() > 1 {
        let i = rng.random_range(0..pieces.len());
        let j = rng.random_range(0..pieces.len());
        pieces.swap(i, j);
    }
    pieces
}

/// The pieces as a multipart body with `boundary`.
fn encode(pieces: &[Piece], boundary: &str) -> Vec<u8> {
    let mut body = Vec::new();
    for piece in pieces {
        body.extend_from_slice(format!("--{boundary}\r\n").as_bytes());
        body.extend_from_slice(
            format!(
                "Content-Disposition: form-data; name=\"{}\"; filename=\"f\"\r\n\r\n",
                piece.name
            )
            .as_bytes(),
        );
        body.extend_from_slice(&piece.bytes);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    body
}

/// Sends fuzzed versions of `valid` to `path`; every answer must be below
/// 500 and problem+json when it is an error. Returns how many were
/// accepted (2xx).
async fn fuzz_route(
    app: &TestApp,
    rng: &mut StdRng,
    path: &str,
    valid: &[Piece],
    names: &[&str],
) -> usize {
    let boundary = "fuzzboundary7MA4YWxkTrZu0gW";
    let mut accepted = 0;
    for case in 0..cases() {
        let pieces = fuzz_pieces(rng, valid, names);
        let mut body = encode(&pieces, boundary);
        // Now and then the framing itself is damaged.
        if rng.random_bool(0.15) {
            body = mutate(rng, &body);
        }
        let response = app
            .client
            .post(app.api(path))
            .header(
                "content-type",
                format!("multipart/form-data; boundary={boundary}"),
            )
            .body(body)
            .send()
            .await
            .expect("the service answers");
        // `status_and_json` also asserts problem+json on every error.
        let (status, body) = status_and_json(response).await;
        assert!(
            status < 500,
            "{path}, case {case}: {status} {body} for parts {:?}",
            pieces.iter().map(|p| p.name.as_str()).collect::<Vec<_>>()
        );
        if status < 400 {
            accepted += 1;
        }
    }
    accepted
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fuzzed_multipart_uploads_get_4xx_or_are_stored_whole() {
    let app = spawn_app().await;
    let mut rng = StdRng::seed_from_u64(20_261_123);
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sequence = app.create_sequence(calibration, &rig.volume, true).await;

    // Frame uploads: images, and targets as CSV.
    let rendered = rig.render(30, 5);
    let mut images: Vec<Piece> = vec![Piece {
        name: "frame".into(),
        bytes: b"0".to_vec(),
    }];
    for (camera, image) in rendered.images.iter().enumerate() {
        images.push(Piece {
            name: format!("cam{camera}"),
            bytes: png(image),
        });
    }
    let names = [
        "frame", "cam0", "cam1", "cam2", "cam3", "cam4", "targets0", "width", "height", "bits",
        "colour", "",
    ];
    let frames = format!("/sequences/{sequence}/frames");
    let accepted_images = fuzz_route(&app, &mut rng, &frames, &images, &names).await;
    let targets = rig.targets(40, 6);
    let mut target_pieces: Vec<Piece> = vec![Piece {
        name: "frame".into(),
        bytes: b"1000".to_vec(),
    }];
    for (camera, list) in targets.targets.iter().enumerate() {
        target_pieces.push(Piece {
            name: format!("targets{camera}"),
            bytes: ptv::formats::csv::format_targets(list).into_bytes(),
        });
    }
    let accepted_targets = fuzz_route(&app, &mut rng, &frames, &target_pieces, &names).await;

    // Calibration solving.
    let solve = rig.solve_input(60, 0.05, 7);
    let mut solve_pieces = vec![
        Piece {
            name: "setup".into(),
            bytes: solve.setup.clone().into_bytes(),
        },
        Piece {
            name: "control".into(),
            bytes: solve.control.clone().into_bytes(),
        },
    ];
    for text in &solve.observations {
        solve_pieces.push(Piece {
            name: "observations".into(),
            bytes: text.clone().into_bytes(),
        });
    }
    solve_pieces.push(Piece {
        name: "options".into(),
        bytes: br#"{"fix": ["k3"], "check_every": 5}"#.to_vec(),
    });
    let solve_names = [
        "setup",
        "control",
        "observations",
        "image",
        "reference",
        "options",
        "other",
    ];
    fuzz_route(
        &app,
        &mut rng,
        "/calibrations/solve",
        &solve_pieces,
        &solve_names,
    )
    .await;

    // OpenPTV calibrations.
    let dir = repository().join("tests/data/openptv/test_cavity");
    let read = |name: &str| std::fs::read(dir.join(name)).unwrap();
    let mut openptv = vec![Piece {
        name: "ptv_par".into(),
        bytes: read("parameters/ptv.par"),
    }];
    for camera in 1..=4 {
        openptv.push(Piece {
            name: "ori".into(),
            bytes: read(&format!("cal/cam{camera}.tif.ori")),
        });
        openptv.push(Piece {
            name: "addpar".into(),
            bytes: read(&format!("cal/cam{camera}.tif.addpar")),
        });
    }
    fuzz_route(
        &app,
        &mut rng,
        "/calibrations/openptv",
        &openptv,
        &["ptv_par", "ori", "addpar", "par"],
    )
    .await;

    // Whatever was accepted is whole: every frame has its job, and every
    // frame job its frame.
    let db = app.database().await;
    let frames_stored = count(&db, "SELECT count(*) FROM frames").await;
    let frame_jobs = count(
        &db,
        "SELECT count(*) FROM jobs WHERE kind = 'process_frame'",
    )
    .await;
    let orphans = count(
        &db,
        "SELECT count(*) FROM jobs j WHERE kind = 'process_frame' \
         AND NOT EXISTS (SELECT 1 FROM frames f WHERE f.job_id = j.id)",
    )
    .await;
    assert_eq!(frames_stored, frame_jobs);
    assert_eq!(orphans, 0);
    assert_eq!(
        frames_stored as usize,
        accepted_images + accepted_targets,
        "each accepted upload is one frame"
    );
    // The generator reaches the accepting path too, or the test would only
    // exercise refusals.
    assert!(accepted_images + accepted_targets > 0);
    app.wait_for_sequence(sequence).await;
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_calibration_of_ten_thousand_cameras_is_refused() {
    // Issue 12's first defect: 10,000 cameras were accepted, and projecting
    // points on them took gigabytes.
    let app = spawn_app().await;
    let rig = rig();
    let mut model: serde_json::Value =
        serde_json::from_str(&ptv::formats::calibration::to_json(&rig.cameras)).unwrap();
    let camera = model["cameras"][0].clone();
    let cameras: Vec<serde_json::Value> = (0..10_000)
        .map(|i| {
            let mut c = camera.clone();
            c["name"] = serde_json::json!(format!("c{i}"));
            c
        })
        .collect();
    model["cameras"] = serde_json::Value::Array(cameras);
    let (status, body) = app.post_json("/calibrations", &model).await;
    let shown: String = body.to_string().chars().take(300).collect();
    assert_eq!(status, 422, "{shown}");
    assert!(
        body["detail"].as_str().unwrap().contains("16"),
        "the detail names the limit: {body}"
    );
    let db = app.database().await;
    assert_eq!(count(&db, "SELECT count(*) FROM calibrations").await, 0);
    app.stop().await;
}

/// Forms are built by hand above; this keeps the helper's `Form` path
/// covered too: a form whose every part is empty is refused, not stored.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn empty_parts_are_refused() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sequence = app.create_sequence(calibration, &rig.volume, true).await;
    let mut form = Form::new().text("frame", "3");
    for camera in 0..4 {
        form = form.part(format!("cam{camera}"), Part::bytes(Vec::new()));
    }
    let (status, body) = app.upload(sequence, form).await;
    assert!((400..500).contains(&status), "{status} {body}");
    let db = app.database().await;
    assert_eq!(count(&db, "SELECT count(*) FROM frames").await, 0);
    app.stop().await;
}
