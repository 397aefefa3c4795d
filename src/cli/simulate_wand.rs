//! `ptv simulate --wand MM`: a wand calibration's inputs with their truth
//! ([`crate::photogrammetry::simulate::wand`]). The rig is
//! [`RigSpec::convergent`] in water with each camera's random lens errors
//! ([`simulate::lens_errors`]: 5-15 px of radial distortion at the corners)
//! and a principal point up to 0.1 mm off the centre. Into `--out`:
//!
//! - `truth.json`: the true rig (with its distortion);
//! - `setup.json`: the lab's setup before calibration: the cameras where a
//!   drawing puts them (to 5 mm and 10 mrad), the design's principal
//!   distance, no distortion;
//! - `plate_control.txt` and per camera `plate_camN.txt`: a stepped plate
//!   (two grids 10 mm apart, 162 marks) over the central 60% of the
//!   volume's width and height, and its marks' image positions with
//!   `--noise`: `ptv calibrate --calibration setup.json --control
//!   plate_control.txt --observations plate_cam1.txt ...` calibrates it, the
//!   start for the wand;
//! - per camera and frame `camN_targets.FFFFF.csv`: the wand's two marks
//!   with `--noise`, in random order, a fraction `--wand-gross` of frames
//!   with one mark of one camera displaced by 5-20 px;
//! - per camera and frame `camN.FFFFF.png` (unless `--no-images`): the
//!   marks rendered as spots of `--diameter` px;
//! - `wand_truth.csv`: `frame,ax,ay,az,bx,by,bz,gross` per frame (mm).

use std::io::Write;

use nalgebra::{Point3, Vector3};
use rand::Rng;

use super::simulate::{write_png, SimulateArgs};
use super::{write_stderr_line, CliError};
use crate::formats::{self, FormatError};
use crate::photogrammetry::simulate::wand::{wand_frames, wand_positions, WandFrame};
use crate::photogrammetry::simulate::{self, RenderSpec, RigSpec, TargetShape};
use crate::photogrammetry::{Camera, Volume};

/// Most wand positions: labs record 200-2,000.
const MAX_POSITIONS: usize = 20_000;

/// Writes the wand experiment of `args`.
pub(super) fn run(
    args: &SimulateArgs,
    length: f64,
    stderr: &mut dyn Write,
) -> Result<(), CliError> {
    let spec = RigSpec::convergent(args.cameras);
    check_args(args, length, &spec.volume)?;
    let mut rng = simulate::rng(args.seed);
    let (truth, setup) = rigs(&spec, &mut rng)?;
    std::fs::create_dir_all(&args.out).map_err(|reason| FormatError::Io {
        path: args.out.clone(),
        reason,
    })?;
    let mut lines = Vec::new();
    let mut write = |name: String, text: String| -> Result<(), CliError> {
        let path = args.out.join(&name);
        formats::write_text(&path, &text)?;
        lines.push(path.display().to_string());
        Ok(())
    };
    write("truth.json".into(), formats::calibration::to_json(&truth))?;
    write("setup.json".into(), formats::calibration::to_json(&setup))?;
    write_plate(args, &spec.volume, &truth, &mut rng, &mut write)?;
    let wands =
        wand_positions(&spec.volume, length, args.wand_positions, &mut rng).ok_or_else(|| {
            CliError::Flag {
                flag: "--wand",
                reason: format!("a {length} mm wand does not fit the volume"),
            }
        })?;
    let frames = wand_frames(&truth, &wands, args.noise, args.wand_gross, &mut rng);
    let table = write_wand_frames(args, &truth, (&frames, &wands), &mut rng)?;
    write("wand_truth.csv".into(), table)?;
    let last = frames.len() - 1;
    for camera in &truth {
        lines.push(format!(
            "{}/{}_targets.%05d.csv (frames 0..{last})",
            args.out.display(),
            camera.name()
        ));
        if !args.no_images {
            lines.push(format!(
                "{}/{}.%05d.png (frames 0..{last})",
                args.out.display(),
                camera.name()
            ));
        }
    }
    for line in lines {
        write_stderr_line(stderr, &line)?;
    }
    let v = &spec.volume;
    write_stderr_line(
        stderr,
        &format!(
            "wand {length} mm, {} positions ({} with a gross error); volume {},{},{},{},{},{} (mm)",
            frames.len(),
            frames.iter().filter(|f| f.gross).count(),
            v.min.x,
            v.max.x,
            v.min.y,
            v.max.y,
            v.min.z,
            v.max.z
        ),
    )
}

/// The flags' ranges: the positions, the fraction of gross errors, and a
/// wand that fits the volume.
fn check_args(args: &SimulateArgs, length: f64, volume: &Volume) -> Result<(), CliError> {
    let flag = |flag: &'static str, reason: String| CliError::Flag { flag, reason };
    if !(1..=MAX_POSITIONS).contains(&args.wand_positions) {
        return Err(flag(
            "--wand-positions",
            format!("expected 1 to {MAX_POSITIONS}, got {}", args.wand_positions),
        ));
    }
    if !(0.0..=1.0).contains(&args.wand_gross) {
        return Err(flag(
            "--wand-gross",
            format!("expected a fraction from 0 to 1, got {}", args.wand_gross),
        ));
    }
    let extent = volume.max - volume.min;
    if !(length > 0.0 && length < extent.min()) {
        return Err(flag(
            "--wand",
            format!(
                "the wand must be longer than 0 and shorter than the volume's shortest side \
                 ({} mm), got {length}",
                extent.min()
            ),
        ));
    }
    Ok(())
}

/// The true rig (the spec's cameras with lens errors and an off-centre
/// principal point) and the setup a lab would start from (no distortion,
/// the principal point centred, positions off by up to 5 mm and angles by
/// up to 10 mrad).
fn rigs(spec: &RigSpec, rng: &mut impl Rng) -> Result<(Vec<Camera>, Vec<Camera>), CliError> {
    let truth: Vec<Camera> = spec
        .build()?
        .into_iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            p.distortion = simulate::lens_errors(rng);
            p.interior.xh = rng.random_range(-0.1..0.1);
            p.interior.yh = rng.random_range(-0.1..0.1);
            Camera::new(p)
        })
        .collect::<Result<_, _>>()?;
    let setup: Vec<Camera> = truth
        .iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            p.interior.xh = 0.0;
            p.interior.yh = 0.0;
            p.distortion = Default::default();
            p.exterior.position += Vector3::from_fn(|_, _| rng.random_range(-5.0..5.0));
            p.exterior.omega += rng.random_range(-0.01..0.01);
            p.exterior.phi += rng.random_range(-0.01..0.01);
            p.exterior.kappa += rng.random_range(-0.01..0.01);
            Camera::new(p)
        })
        .collect::<Result<_, _>>()?;
    Ok((truth, setup))
}

/// A two-plane plate across the middle of the volume, its control points
/// and each camera's marks (`plate_control.txt`, `plate_CAM.txt`): the
/// plate calibration the wand's is compared with.
fn write_plate(
    args: &SimulateArgs,
    v: &Volume,
    truth: &[Camera],
    rng: &mut impl Rng,
    write: &mut impl FnMut(String, String) -> Result<(), CliError>,
) -> Result<(), CliError> {
    let plate = Volume {
        min: Point3::new(0.6 * v.min.x, 0.6 * v.min.y, -5.0),
        max: Point3::new(0.6 * v.max.x, 0.6 * v.max.y, 5.0),
    };
    let control = simulate::calibration_target(TargetShape::TwoPlanes, &plate, 162, rng);
    let marks = simulate::observe_target(truth, &control, args.noise, rng);
    write(
        "plate_control.txt".into(),
        control
            .iter()
            .map(|p| {
                format!(
                    "{} {} {} {}\n",
                    p.id, p.position.x, p.position.y, p.position.z
                )
            })
            .collect(),
    )?;
    for (camera, marks) in truth.iter().zip(&marks) {
        write(
            format!("plate_{}.txt", camera.name()),
            marks
                .iter()
                .map(|m| format!("{} {} {}\n", m.id, m.pixel.x, m.pixel.y))
                .collect(),
        )?;
    }
    Ok(())
}

/// Each frame's targets per camera (`CAM_targets.FFFFF.csv`) and, unless
/// `--no-images`, its rendered images; returns the wand's true ends per
/// frame as `wand_truth.csv`'s text.
fn write_wand_frames(
    args: &SimulateArgs,
    truth: &[Camera],
    (frames, wands): (&[WandFrame], &[[Point3<f64>; 2]]),
    rng: &mut impl Rng,
) -> Result<String, CliError> {
    let render = RenderSpec::eight_bit(args.diameter);
    let mut table = String::from("frame,ax,ay,az,bx,by,bz,gross\n");
    for (f, (frame, w)) in frames.iter().zip(wands).enumerate() {
        for (camera, targets) in truth.iter().zip(&frame.targets) {
            let path = args
                .out
                .join(format!("{}_targets.{f:05}.csv", camera.name()));
            formats::write_text(&path, &formats::csv::format_targets(targets))?;
            if !args.no_images {
                let positions: Vec<_> = targets
                    .iter()
                    .map(|t| nalgebra::Point2::new(t.x, t.y))
                    .collect();
                let sensor = camera.sensor();
                let image = simulate::render(sensor.width, sensor.height, &positions, &render, rng);
                write_png(
                    &args.out.join(format!("{}.{f:05}.png", camera.name())),
                    &image,
                )?;
            }
        }
        table.push_str(&format!(
            "{f},{},{},{},{},{},{},{}\n",
            w[0].x, w[0].y, w[0].z, w[1].x, w[1].y, w[1].z, frame.gross as u8
        ));
    }
    Ok(table)
}
