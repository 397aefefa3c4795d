//! The plot routes: status, content type, PNG decoded at the size its
//! layout says, SVG text, and marks where the data are: target rings on
//! the targets (with the image and on a blank sensor), particles in their
//! views, residual arrows starting where the control points were measured,
//! disparity arrows in their cells, trajectories on their points. And the
//! refusals: unknown ids 404, unknown `format` 400, the image not kept or
//! the wrong kind of report 409, each a problem+json that says why.

use std::collections::HashSet;

use image::RgbImage;
use nalgebra::Point3;
use serde_json::Value;

use ptv::plot::overlay::{self, LEGEND, MATCHED, MATCHED_RADIUS, UNMATCHED, UNMATCHED_RADIUS};
use ptv::plot::residuals::{ResidualLayout, ResidualReport, EXCLUDED, SENSOR, USED};
use ptv::plot::views::{ParticlePoint, TrajectoryPoint, ViewsLayout, PANEL, VIEWS};
use ptv::plot::{cameras_colour, WHITE};

use crate::helpers::{content_type, image_form, png, raw8, rig, spawn_app, targets_form, TestApp};

/// GETs a picture: status, content type and body.
pub async fn picture(app: &TestApp, path: &str) -> (u16, String, Vec<u8>) {
    let response = app.client.get(app.api(path)).send().await.unwrap();
    let status = response.status().as_u16();
    let content_type = content_type(&response);
    (
        status,
        content_type,
        response.bytes().await.unwrap().to_vec(),
    )
}

/// GETs a PNG that must be there; decoded.
pub async fn png_picture(app: &TestApp, path: &str) -> RgbImage {
    let (status, content_type, body) = picture(app, path).await;
    assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&body));
    assert_eq!(content_type, "image/png", "{path}");
    image::load_from_memory(&body)
        .unwrap_or_else(|e| panic!("{path}: {e}"))
        .to_rgb8()
}

/// GETs an SVG that must be there; its text.
pub async fn svg_picture(app: &TestApp, path: &str) -> String {
    let (status, content_type, body) = picture(app, path).await;
    assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&body));
    assert_eq!(content_type, "image/svg+xml", "{path}");
    let text = String::from_utf8(body).unwrap();
    assert!(
        text.starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\""),
        "{path}"
    );
    assert!(text.trim_end().ends_with("</svg>"), "{path}");
    text
}

/// Asserts a problem+json answer of `status` whose detail contains every
/// one of `words`.
pub async fn refused(app: &TestApp, path: &str, status: u16, words: &[&str]) {
    let (got, content_type, body) = picture(app, path).await;
    let text = String::from_utf8_lossy(&body);
    assert_eq!(got, status, "{path}: {text}");
    assert_eq!(content_type, "application/problem+json", "{path}: {text}");
    let problem: Value = serde_json::from_str(&text).unwrap();
    let detail = problem["detail"].as_str().unwrap();
    for word in words {
        assert!(detail.contains(word), "{path}: {detail}");
    }
}

/// The pixel nearest a drawing point.
fn at(image: &RgbImage, (x, y): (f64, f64)) -> image::Rgb<u8> {
    *image.get_pixel(x.round() as u32, y.round() as u32)
}

/// A frame's targets of one camera and, per target, whether a particle
/// uses it; the particles' positions and camera counts.
async fn frame_data(
    app: &TestApp,
    sequence: i64,
    frame: i64,
    camera: usize,
) -> (Vec<(f64, f64)>, Vec<bool>, Vec<ParticlePoint>) {
    let (status, targets) = app
        .get_json(&format!(
            "/sequences/{sequence}/frames/{frame}/targets?camera={camera}"
        ))
        .await;
    assert_eq!(status, 200, "{targets}");
    let targets: Vec<(f64, f64)> = targets["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| (t["x"].as_f64().unwrap(), t["y"].as_f64().unwrap()))
        .collect();
    let (status, particles) = app
        .get_json(&format!("/sequences/{sequence}/frames/{frame}/particles"))
        .await;
    assert_eq!(status, 200, "{particles}");
    let mut matched = vec![false; targets.len()];
    let mut points = Vec::new();
    for p in particles["particles"].as_array().unwrap() {
        let seen: Vec<Option<usize>> = p["targets"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t.as_u64().map(|t| t as usize))
            .collect();
        if let Some(Some(t)) = seen.get(camera) {
            matched[*t] = true;
        }
        points.push(ParticlePoint {
            position: Point3::new(
                p["x"].as_f64().unwrap(),
                p["y"].as_f64().unwrap(),
                p["z"].as_f64().unwrap(),
            ),
            cameras: seen.iter().flatten().count(),
        });
    }
    (targets, matched, points)
}

/// Checks the rings of an overlay: every target with no other target
/// within 20 px has its ring's colour (matched or not) on its ring, a
/// disc's width outside its centre; pixels 25 px from every target carry
/// no mark. Returns how many targets were checked.
fn check_rings(image: &RgbImage, targets: &[(f64, f64)], matched: &[bool]) -> usize {
    let mut checked = 0;
    for (i, &(x, y)) in targets.iter().enumerate() {
        let isolated = targets
            .iter()
            .enumerate()
            .all(|(j, &(u, v))| j == i || (u - x).hypot(v - y) > 20.0);
        if !isolated {
            continue;
        }
        let (cx, cy) = overlay::point(x, y);
        let (colour, radius) = if matched[i] {
            (MATCHED, MATCHED_RADIUS)
        } else {
            (UNMATCHED, UNMATCHED_RADIUS)
        };
        // Left, above and below the centre on the ring (a reprojection's
        // "+" lies within 3.5 px of it, its arms along these axes).
        for (dx, dy) in [(-radius, 0.0), (0.0, -radius), (0.0, radius)] {
            assert_eq!(
                at(image, (cx + dx, cy + dy)),
                colour,
                "target {i} at ({x}, {y}), matched {}",
                matched[i]
            );
        }
        checked += 1;
    }
    // Far from every target: no ring, no cross.
    let marks: HashSet<image::Rgb<u8>> = [MATCHED, UNMATCHED]
        .into_iter()
        .chain((2..6).map(cameras_colour))
        .collect();
    let (w, h) = image.dimensions();
    let mut far = 0;
    for y in (5..h - LEGEND - 5).step_by(23) {
        for x in (5..w.min(1280) - 5).step_by(29) {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            if targets.iter().all(|&(u, v)| (u - px).hypot(v - py) > 25.0) {
                let colour = *image.get_pixel(x, y);
                assert!(!marks.contains(&colour), "a mark at ({x}, {y}): {colour:?}");
                far += 1;
            }
        }
    }
    assert!(far > 100, "too few empty pixels checked: {far}");
    checked
}

#[tokio::test]
async fn frame_pictures_mark_the_targets_and_particles_where_they_are() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    // Images kept; and a frame that came as targets (no image at all).
    let kept = app.create_sequence(calibration, &rig.volume, true).await;
    let rendered = rig.render(300, 7);
    let files: Vec<Vec<u8>> = rendered.images.iter().map(png).collect();
    let (status, body) = app.upload(kept, image_form(3, &files)).await;
    assert_eq!(status, 202, "{body}");
    // The same images as raw samples: read back with the frame's layout.
    let raw: Vec<Vec<u8>> = rendered.images.iter().map(raw8).collect();
    let form = image_form(4, &raw)
        .text("width", "1280")
        .text("height", "1024")
        .text("bits", "8");
    let (status, body) = app.upload(kept, form).await;
    assert_eq!(status, 202, "{body}");
    let targets_only = app.create_sequence(calibration, &rig.volume, true).await;
    let (status, body) = app
        .upload(targets_only, targets_form(3, &rig.targets(300, 8)))
        .await;
    assert_eq!(status, 202, "{body}");
    assert_eq!(app.wait_for_sequence(kept).await["frames"]["done"], 2);
    assert_eq!(
        app.wait_for_sequence(targets_only).await["frames"]["done"],
        1
    );
    let sensor = rig.cameras[1].sensor();
    let size = (sensor.width.max(480), sensor.height + LEGEND);

    // The image with its marks.
    let path = format!("/sequences/{kept}/frames/3/overlay.png?camera=1");
    let image = png_picture(&app, &path).await;
    assert_eq!(image.dimensions(), size);
    let (targets, matched, particles) = frame_data(&app, kept, 3, 1).await;
    assert!(targets.len() > 250, "{}", targets.len());
    let checked = check_rings(&image, &targets, &matched);
    assert!(checked > 20, "only {checked} isolated targets");
    // The camera image under the marks: the rendered image's own grey at
    // a pixel far from every target.
    let far = (0..sensor.height)
        .step_by(7)
        .flat_map(|y| (0..sensor.width).step_by(11).map(move |x| (x, y)))
        .find(|&(x, y)| {
            targets
                .iter()
                .all(|&(u, v)| (u - x as f64).hypot(v - y as f64) > 30.0)
        })
        .unwrap();
    let grey = rendered.images[1].get(far.0, far.1).unwrap() as u8;
    assert_eq!(*image.get_pixel(far.0, far.1), image::Rgb([grey; 3]));
    // The raw frame's overlay: the same picture above the legend.
    let raw = png_picture(
        &app,
        &format!("/sequences/{kept}/frames/4/overlay.png?camera=1"),
    )
    .await;
    let crop =
        |i: &RgbImage| image::imageops::crop_imm(i, 0, 0, sensor.width, sensor.height).to_image();
    assert!(
        crop(&raw) == crop(&image),
        "the raw frame's overlay differs"
    );
    // SVG: the image embedded, one ring per target and one per legend key.
    let svg = svg_picture(&app, &format!("{path}&format=svg")).await;
    assert!(svg.contains("href=\"data:image/png;base64,"));
    let unmatched = matched.iter().filter(|m| !**m).count();
    assert_eq!(svg.matches("stroke=\"#ff00ff\"").count(), unmatched + 1);
    assert_eq!(
        svg.matches("stroke=\"#2896ff\"").count(),
        targets.len() - unmatched + 1
    );

    // No image kept: said, unless image=false, which draws on a blank
    // sensor.
    let blank = format!("/sequences/{targets_only}/frames/3/overlay.png?camera=1");
    refused(&app, &blank, 409, &["not kept", "image=false"]).await;
    let image = png_picture(&app, &format!("{blank}&image=false")).await;
    assert_eq!(image.dimensions(), size);
    let (targets, matched, _) = frame_data(&app, targets_only, 3, 1).await;
    assert!(check_rings(&image, &targets, &matched) > 20);
    assert_eq!(*image.get_pixel(far.0, far.1), overlay::BLANK);

    // The particles in three views: each drawn in its camera count's
    // colour, or under a particle seen by more cameras (drawn later).
    let path = format!("/sequences/{kept}/frames/3/particles.png");
    let image = png_picture(&app, &path).await;
    let layout = ViewsLayout::of(particles.iter().map(|p| p.position));
    assert_eq!(image.dimensions(), (layout.width, layout.height));
    for view in 0..3 {
        for p in &particles {
            let colour = at(&image, layout.point(view, &p.position));
            assert!(
                (p.cameras..6).any(|c| cameras_colour(c) == colour),
                "view {view}: {p:?} drawn {colour:?}"
            );
        }
    }
    // Inside the XY view, far from every particle: white.
    let (px, py) = layout.panel(0);
    let drawn: Vec<(f64, f64)> = particles
        .iter()
        .map(|p| layout.point(0, &p.position))
        .collect();
    let mut empty = 0;
    for y in (py + 3..py + PANEL - 3).step_by(7) {
        for x in (px + 3..px + PANEL - 3).step_by(7) {
            if drawn
                .iter()
                .all(|d| (d.0 - x as f64).hypot(d.1 - y as f64) > 4.0)
            {
                assert_eq!(*image.get_pixel(x as u32, y as u32), WHITE, "({x}, {y})");
                empty += 1;
            }
        }
    }
    assert!(empty > 500, "{empty}");
    let svg = svg_picture(&app, &format!("{path}?format=svg")).await;
    assert_eq!(
        svg.matches("<circle").count(),
        3 * particles.len(),
        "a disc per particle and view"
    );

    // The plain kept image (the page's frame viewer draws its own marks
    // on it): the camera's samples, grey, at the sensor's size, the same
    // from the PNG frame and the raw one; not kept, a 409.
    for frame in [3, 4] {
        let response = app
            .client
            .get(app.api(&format!(
                "/sequences/{kept}/frames/{frame}/image.png?camera=1"
            )))
            .send()
            .await
            .unwrap();
        assert_eq!(response.status(), 200);
        assert_eq!(content_type(&response), "image/png");
        let plain = image::load_from_memory(&response.bytes().await.unwrap()).unwrap();
        assert_eq!(plain.color(), image::ColorType::L8);
        let plain = plain.to_luma8();
        assert_eq!(plain.dimensions(), (sensor.width, sensor.height));
        for (x, y) in [
            (far.0, far.1),
            (10, 10),
            (sensor.width - 1, sensor.height - 1),
        ] {
            let grey = rendered.images[1].get(x, y).unwrap() as u8;
            assert_eq!(plain.get_pixel(x, y).0[0], grey, "frame {frame} ({x}, {y})");
        }
        let (tx, ty) = targets[0];
        let grey = rendered.images[1].get(tx as u32, ty as u32).unwrap() as u8;
        assert_eq!(
            plain.get_pixel(tx as u32, ty as u32).0[0],
            grey,
            "no mark on a target"
        );
    }
    refused(
        &app,
        &format!("/sequences/{targets_only}/frames/3/image.png"),
        409,
        &["not kept"],
    )
    .await;
    refused(
        &app,
        &format!("/sequences/{kept}/frames/3/image.png?camera=7"),
        404,
        &["camera 7"],
    )
    .await;
    refused(
        &app,
        &format!("/sequences/{kept}/frames/9/image.png"),
        404,
        &["no frame 9"],
    )
    .await;
    refused(&app, "/sequences/999/frames/3/image.png", 404, &["999"]).await;
    refused(
        &app,
        &format!("/sequences/{kept}/frames/3/image.png?format=svg"),
        400,
        &[],
    )
    .await;

    // Bad requests.
    refused(&app, "/sequences/999/frames/3/overlay.png", 404, &["999"]).await;
    refused(
        &app,
        &format!("/sequences/{kept}/frames/9/overlay.png"),
        404,
        &["no frame 9"],
    )
    .await;
    refused(
        &app,
        &format!("/sequences/{kept}/frames/9/particles.png"),
        404,
        &["no frame 9"],
    )
    .await;
    refused(&app, "/sequences/999/frames/3/particles.png", 404, &["999"]).await;
    refused(
        &app,
        &format!("/sequences/{kept}/frames/3/overlay.png?camera=7"),
        404,
        &["camera 7"],
    )
    .await;
    for path in [
        format!("/sequences/{kept}/frames/3/overlay.png?format=jpg"),
        format!("/sequences/{kept}/frames/3/particles.png?format=gif"),
        format!("/sequences/{kept}/frames/3/particles.png?colour=red"),
        format!("/sequences/{kept}/trajectories.png?format=bmp"),
    ] {
        refused(&app, &path, 400, &[]).await;
    }
    refused(
        &app,
        &format!("/sequences/{kept}/trajectories.png"),
        409,
        &["not tracked"],
    )
    .await;
    refused(&app, "/sequences/999/trajectories.png", 404, &["999"]).await;
    app.stop().await;
}

#[tokio::test]
async fn residual_pictures_put_each_arrow_where_its_point_was_measured() {
    let app = spawn_app().await;
    let rig = rig();
    let input = rig.solve_input(150, 0.1, 3);
    let (status, accepted) = app.solve(input.form(None)).await;
    assert_eq!(status, 202, "{accepted}");
    let job = app.wait_for_job(accepted["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    let id: i64 = job["result"]
        .as_str()
        .unwrap()
        .strip_prefix("/api/v1/calibrations/")
        .unwrap()
        .parse()
        .unwrap();
    let (status, report) = app.get_json(&format!("/calibrations/{id}/report")).await;
    assert_eq!(status, 200, "{report}");
    let report = ResidualReport::from_json(&report.to_string(), "report").unwrap();

    for camera in [0, 3] {
        let path = format!("/calibrations/{id}/residuals.png?camera={camera}");
        let image = png_picture(&app, &path).await;
        let sensor = rig.cameras[camera].sensor();
        let residuals = &report.cameras[camera];
        let layout = ResidualLayout::new(residuals, (sensor.width, sensor.height));
        assert_eq!(image.dimensions(), (layout.width, layout.height));
        assert!(residuals.residuals.len() > 100);
        // Arrow starts, and how far their arrows reach (the longest used
        // one 40 px, an excluded one at most 120 px).
        let mut starts = Vec::new();
        for (r, reach) in residuals
            .residuals
            .iter()
            .map(|r| (r, 45.0))
            .chain(residuals.excluded.iter().map(|r| (r, 125.0)))
        {
            let [x, y] = r.image_px.unwrap();
            let from = layout.sensor_point(x, y);
            let colour = at(&image, from);
            assert!(colour == USED || colour == EXCLUDED, "{r:?}: {colour:?}");
            starts.push((from, reach));
        }
        // Sensor pixels far from every arrow are the sensor's background.
        let (sx, sy) = layout.sensor_origin;
        let (sw, sh) = layout.sensor_size;
        let mut empty = 0;
        for y in (sy + 2..sy + sh - 2).step_by(9) {
            for x in (sx + 2..sx + sw - 2).step_by(9) {
                let p = (x as f64, y as f64);
                if starts
                    .iter()
                    .all(|(s, reach)| (s.0 - p.0).hypot(s.1 - p.1) > *reach)
                {
                    assert_eq!(*image.get_pixel(x as u32, y as u32), SENSOR, "{p:?}");
                    empty += 1;
                }
            }
        }
        assert!(empty > 50, "{empty}");
        let svg = svg_picture(&app, &format!("{path}&format=svg")).await;
        assert!(svg.contains(&format!("Calibration residuals, camera {}", residuals.name)));
    }

    // The wrong kind of report, no report, unknown ids, bad queries.
    refused(
        &app,
        &format!("/calibrations/{id}/disparity.png"),
        409,
        &["not a self-calibration's report"],
    )
    .await;
    let given = app.create_calibration(&rig.cameras).await;
    for plot in ["residuals", "disparity"] {
        refused(
            &app,
            &format!("/calibrations/{given}/{plot}.png"),
            409,
            &["has no report"],
        )
        .await;
        refused(
            &app,
            &format!("/calibrations/999/{plot}.png"),
            404,
            &["999"],
        )
        .await;
        refused(
            &app,
            &format!("/calibrations/{id}/{plot}.png?format=pdf"),
            400,
            &[],
        )
        .await;
    }
    refused(
        &app,
        &format!("/calibrations/{id}/residuals.png?camera=4"),
        404,
        &["camera 4"],
    )
    .await;
    app.stop().await;
}

/// The disparity maps of a self-calibrated calibration (`report`, its
/// report): the layout's size, an arrow (the arrow colour) at the centre
/// of every cell with particles; and in SVG.
pub async fn check_disparity_picture(app: &TestApp, id: i64, report: &Value) {
    use ptv::plot::disparity::{DisparityLayout, DisparityMaps, ARROW};
    let maps = DisparityMaps::from_json(&report.to_string(), "the report").unwrap();
    let layout = DisparityLayout::of(&maps).unwrap();
    let path = format!("/calibrations/{id}/disparity.png");
    let image = png_picture(app, &path).await;
    assert_eq!(image.dimensions(), (layout.width, layout.height));
    let mut cells = 0;
    for (c, camera) in maps.cameras.iter().enumerate() {
        for (after, map) in [(false, &camera.map_before), (true, &camera.map_after)] {
            for cell in &map.cells {
                let (x, y) = layout.cell_centre(c, after, cell.index);
                let near = (-1..=1).any(|dy| {
                    (-1..=1).any(|dx| {
                        *image.get_pixel((x as i64 + dx) as u32, (y as i64 + dy) as u32) == ARROW
                    })
                });
                assert!(near, "camera {c} after {after} cell {:?}", cell.index);
                cells += 1;
            }
        }
    }
    assert!(cells > 0);
    let svg = svg_picture(app, &format!("{path}?format=svg")).await;
    assert!(svg.contains("Disparity maps"));
    refused(
        app,
        &format!("/calibrations/{id}/residuals.png"),
        409,
        &["self-calibration"],
    )
    .await;
}

/// The trajectories picture of a run: the layout's size, every point of
/// every trajectory of two or more points on a drawn segment (a pixel
/// within 1 px that is not white) in each view; and in SVG one line per
/// segment and view.
pub async fn check_trajectories_picture(app: &TestApp, sequence: i64, run: i64) {
    let (status, body) = app
        .get_json(&format!("/sequences/{sequence}/trajectories?run={run}"))
        .await;
    assert_eq!(status, 200, "{body}");
    let trajectories: Vec<Vec<TrajectoryPoint>> = body["trajectories"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            t["points"]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| {
                    let v = |k: &str| -> Vec<f64> {
                        p[k].as_array()
                            .map(|a| a.iter().map(|x| x.as_f64().unwrap()).collect())
                            .unwrap_or_default()
                    };
                    let position = v("position");
                    let velocity = v("velocity");
                    TrajectoryPoint {
                        frame: p["frame"].as_i64().unwrap(),
                        position: Point3::new(position[0], position[1], position[2]),
                        velocity: (velocity.len() == 3)
                            .then(|| nalgebra::Vector3::new(velocity[0], velocity[1], velocity[2])),
                    }
                })
                .collect()
        })
        .collect();
    assert!(!trajectories.is_empty());
    let path = format!("/sequences/{sequence}/trajectories.png?run={run}");
    let image = png_picture(app, &path).await;
    let layout = ViewsLayout::of(trajectories.iter().flatten().map(|p| p.position));
    assert_eq!(image.dimensions(), (layout.width, layout.height));
    let mut segments = 0;
    for t in trajectories.iter().filter(|t| t.len() > 1) {
        segments += t.len() - 1;
        for p in t {
            for view in 0..3 {
                let (x, y) = layout.point(view, &p.position);
                let near = (-1..=1).any(|dy| {
                    (-1..=1).any(|dx| {
                        *image.get_pixel(
                            (x.round() as i64 + dx) as u32,
                            (y.round() as i64 + dy) as u32,
                        ) != WHITE
                    })
                });
                assert!(near, "view {view}: {p:?}");
            }
        }
    }
    let svg = svg_picture(app, &format!("{path}&format=svg")).await;
    // Every segment once in each of the three views, besides one tick mark
    // per tick of each view's two axes.
    let ticks: usize = VIEWS
        .iter()
        .map(|(_, a, b)| layout.ticks(*a).1.len() + layout.ticks(*b).1.len())
        .sum();
    assert_eq!(svg.matches("<line").count(), 3 * segments + ticks);
}
