//! The experiment's sections mapped onto `ptv`'s settings: the cameras
//! (calibration), detection, matching and its volume, the sequence, the
//! masks and tracking, as the table in the module above says.

use super::*;

pub(super) fn map(
    files: &dyn ExperimentFiles,
    s: Sections,
    root: &Path,
    at: &Locator,
    unmapped: Vec<UnmappedSetting>,
) -> Result<Experiment, ExperimentError> {
    let (n, splitter) = camera_count(&s, at)?;
    let cameras = map_cameras(files, &s, root, at, n)?;
    let detection = map_detection(&s, at, n)?;
    let matching = map_matching(&s, at, &cameras, n)?;
    let sequence = map_sequence(&s, at, splitter)?;
    let masks = map_masks(files, &s, root, at, n)?;
    let tracking = s.track.as_ref().map(|t| map_tracking(t, at)).transpose()?;

    Ok(Experiment {
        root: root.to_owned(),
        cameras,
        splitter,
        detection,
        matching,
        tracking,
        sequence,
        masks,
        unmapped,
    })
}

/// The number of cameras, and pyptv's splitter if the images are its
/// quadrants; each per-camera list checked against the number.
pub(super) fn camera_count(
    s: &Sections,
    at: &Locator,
) -> Result<(usize, Option<Splitter>), ExperimentError> {
    let n = match (s.num_cams, s.ptv.n_img) {
        (Some(n), _) | (None, Some(n)) => n,
        (None, None) => return Err(at.invalid("num_cams", "the number of cameras is missing")),
    };
    if !(1..=calibration::MAX_CAMERAS).contains(&n) {
        return Err(at.invalid(
            "num_cams",
            format!(
                "the number of cameras must be 1..{}, got {n}",
                calibration::MAX_CAMERAS
            ),
        ));
    }
    if s.ptv.chfield != 0 {
        return Err(at.invalid(
            "ptv.chfield",
            format!(
                "field-interlaced images (chfield {}) are not supported; set it to 0",
                s.ptv.chfield
            ),
        ));
    }
    let count = |key: &str, len: usize, at_least: bool| {
        if len == n || (at_least && len > n) {
            Ok(())
        } else {
            Err(at.invalid(
                key,
                format!("gives {len} values for {n} cameras; give one per camera, in camera order"),
            ))
        }
    };
    count("cal_ori.img_ori", s.cal_ori.img_ori.len(), false)?;
    count("targ_rec.gvthres", s.targ_rec.gvthres.len(), true)?;
    let splitter = s.ptv.splitter.then(Splitter::quadrants);
    if let Some(splitter) = splitter {
        if splitter.views() != n {
            return Err(at.invalid(
                "ptv.splitter",
                format!(
                    "pyptv's splitter makes {} views of one image, but the experiment has {n} \
                     cameras",
                    splitter.views()
                ),
            ));
        }
    } else {
        count("sequence.base_name", s.sequence.base_name.len(), false)?;
    }
    if s.sequence.base_name.is_empty() {
        return Err(at.invalid("sequence.base_name", "no image name pattern is given"));
    }

    Ok((n, splitter))
}

/// The cameras: each `.ori` (and `.addpar`) of `cal_ori` on `ptv.par`'s
/// sensor and media.
pub(super) fn map_cameras(
    files: &dyn ExperimentFiles,
    s: &Sections,
    root: &Path,
    at: &Locator,
    n: usize,
) -> Result<Vec<Camera>, ExperimentError> {
    let sensor = Sensor {
        width: s.ptv.imx,
        height: s.ptv.imy,
        pixel_size_x: s.ptv.pix_x,
        pixel_size_y: s.ptv.pix_y,
    };
    let mut parameters = Vec::with_capacity(n);
    for (i, ori) in s.cal_ori.img_ori.iter().enumerate() {
        let key = format!("cal_ori.img_ori[{i}]");
        let ori_path = files
            .resolve(root, ori)
            .map_err(|reason| ExperimentError::Refused {
                file: at.file_of(&key),
                location: at.location(&key),
                name: ori.clone(),
                reason,
            })?;
        if !files.is_file(&ori_path) {
            return Err(ExperimentError::Missing {
                file: at.file_of(&key),
                location: at.location(&key),
                missing: ori_path,
            });
        }
        let source = ori_path.display().to_string();
        let (exterior, interior, glass_vector) =
            openptv::parse_ori(&files.read_text(&ori_path)?, &source)?;
        let addpar = openptv::addpar_path(&ori_path);
        let distortion = if files.is_file(&addpar) {
            openptv::parse_addpar(&files.read_text(&addpar)?, &addpar.display().to_string())?
        } else {
            Distortion::default()
        };
        let name = Path::new(ori)
            .file_name()
            .and_then(|n| n.to_str())
            .map(|n| n.split('.').next().unwrap_or(n).to_owned())
            .filter(|n| !n.is_empty())
            .unwrap_or_else(|| format!("cam{}", i + 1));
        parameters.push(CameraParameters {
            name,
            sensor: sensor.clone(),
            exterior,
            interior,
            distortion,
            media: Media {
                n_air: s.ptv.mmp_n1,
                walls: vec![Wall {
                    n: s.ptv.mmp_n2,
                    thickness: s.ptv.mmp_d,
                }],
                n_object: s.ptv.mmp_n3,
                glass_vector,
            },
        });
    }
    Ok(calibration::from_parameters(
        parameters,
        &format!(
            "{} with the .ori files of cal_ori",
            at.file_of("ptv.imx").display()
        ),
    )?)
}

/// Detection per camera from `targ_rec.par` (and `ptv.par`'s high-pass
/// flag).
pub(super) fn map_detection(
    s: &Sections,
    at: &Locator,
    n: usize,
) -> Result<Vec<DetectionParameters>, ExperimentError> {
    let t = &s.targ_rec;
    let range = |key: &str, value: i64, max: i64| -> Result<i64, ExperimentError> {
        if (0..=max).contains(&value) {
            Ok(value)
        } else {
            Err(at.invalid(key, format!("must be 0..{max}, got {value}")))
        }
    };
    let u16_max = i64::from(u16::MAX);
    let u32_max = i64::from(u32::MAX);
    let base = DetectionParameters {
        threshold: 0,
        highpass_radius: if s.ptv.hp_flag {
            OPENPTV_HIGHPASS_RADIUS
        } else {
            0
        },
        min_pixels: range("targ_rec.nnmin", t.nnmin, u32_max)? as u32,
        max_pixels: range("targ_rec.nnmax", t.nnmax, u32_max)? as u32,
        min_nx: range("targ_rec.nxmin", t.nxmin, u32_max)? as u32,
        max_nx: range("targ_rec.nxmax", t.nxmax, u32_max)? as u32,
        min_ny: range("targ_rec.nymin", t.nymin, u32_max)? as u32,
        max_ny: range("targ_rec.nymax", t.nymax, u32_max)? as u32,
        // liboptv keeps `sumg > sumg_min`; ours keeps `sumg >= min_sumg`.
        min_sumg: range("targ_rec.sumg_min", t.sumg_min, i64::MAX - 1)? as u64 + 1,
        split: true,
        split_depth: Some(range("targ_rec.disco", t.disco, u16_max)? as u16),
        // OpenPTV's targ_rec: the grey value weighted centroid.
        centroid: Centroid::Weighted,
        // OpenPTV has no noise-relative test: its `sumg_min` decides.
        min_snr: 0,
    };
    let mut detection = Vec::with_capacity(n);
    for (i, &threshold) in t.gvthres.iter().take(n).enumerate() {
        let parameters = DetectionParameters {
            threshold: range(&format!("targ_rec.gvthres[{i}]"), threshold, u16_max)? as u16,
            ..base.clone()
        };
        parameters.validate().map_err(|e| {
            let key = match e.field {
                "min_pixels" => "nnmin",
                "min_nx" => "nxmin",
                "min_ny" => "nymin",
                other => other,
            };
            at.invalid(&format!("targ_rec.{key}"), e.reason)
        })?;
        detection.push(parameters);
    }
    Ok(detection)
}

/// Matching from `criteria.par`: the band, and the volume between its
/// layers that the cameras see.
pub(super) fn map_matching(
    s: &Sections,
    at: &Locator,
    cameras: &[Camera],
    n: usize,
) -> Result<MatchingParameters, ExperimentError> {
    let c = &s.criteria;
    for key in ["X_lay", "Zmin_lay", "Zmax_lay"] {
        let len = match key {
            "X_lay" => c.X_lay.len(),
            "Zmin_lay" => c.Zmin_lay.len(),
            _ => c.Zmax_lay.len(),
        };
        if len != 2 {
            return Err(at.invalid(
                &format!("criteria.{key}"),
                format!("must have 2 values (the two layers), got {len}"),
            ));
        }
    }
    if c.X_lay[0] >= c.X_lay[1] {
        return Err(at.invalid(
            "criteria.X_lay",
            format!(
                "X_lay[0] ({}) must be smaller than X_lay[1] ({})",
                c.X_lay[0], c.X_lay[1]
            ),
        ));
    }
    for i in 0..2 {
        if c.Zmin_lay[i] >= c.Zmax_lay[i] {
            return Err(at.invalid(
                &format!("criteria.Zmin_lay[{i}]"),
                format!(
                    "Zmin_lay[{i}] ({}) must be smaller than Zmax_lay[{i}] ({})",
                    c.Zmin_lay[i], c.Zmax_lay[i]
                ),
            ));
        }
    }
    if !(c.eps0.is_finite() && c.eps0 > 0.0) {
        return Err(at.invalid(
            "criteria.eps0",
            format!("must be a positive length (mm), got {}", c.eps0),
        ));
    }
    let z_min = c.Zmin_lay[0].min(c.Zmin_lay[1]);
    let z_max = c.Zmax_lay[0].max(c.Zmax_lay[1]);
    let (y_min, y_max) = seen_y_range(cameras, z_min, z_max).ok_or_else(|| {
        at.invalid(
            "criteria.Zmin_lay",
            "no camera sees the depth range Zmin_lay..Zmax_lay; check the volume and the \
             calibration",
        )
    })?;
    Ok(MatchingParameters {
        tolerance: c.eps0 / ((s.ptv.pix_x + s.ptv.pix_y) / 2.0),
        volume: Some(Volume {
            min: Point3::new(c.X_lay[0], y_min, z_min),
            max: Point3::new(c.X_lay[1], y_max, z_max),
        }),
        min_cameras: if s.ptv.allcam_flag { n.max(2) } else { 2 },
        ..MatchingParameters::default()
    })
}

/// The frames of `sequence.par`, and its image name patterns (one with a
/// splitter).
pub(super) fn map_sequence(
    s: &Sections,
    at: &Locator,
    splitter: Option<Splitter>,
) -> Result<SequenceFrames, ExperimentError> {
    if s.sequence.first > s.sequence.last {
        return Err(at.invalid(
            "sequence.first",
            format!(
                "the first frame ({}) is after the last ({})",
                s.sequence.first, s.sequence.last
            ),
        ));
    }
    let base_names = if splitter.is_some() {
        &s.sequence.base_name[..1]
    } else {
        &s.sequence.base_name[..]
    };
    let base_names = base_names
        .iter()
        .map(|name| {
            FramePattern::parse(name, WithoutNumber::AppendAfterDot)
                .map_err(|reason| at.invalid("sequence.base_name", reason))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(SequenceFrames {
        base_names,
        first: s.sequence.first,
        last: s.sequence.last,
    })
}

/// pyptv's masks, `mask_base_name % (camera + 1)`, each an existing
/// file.
pub(super) fn map_masks(
    files: &dyn ExperimentFiles,
    s: &Sections,
    root: &Path,
    at: &Locator,
    n: usize,
) -> Result<Option<Vec<PathBuf>>, ExperimentError> {
    Ok(match &s.masking {
        Some(m) if m.mask_flag => {
            let pattern = FramePattern::parse(&m.mask_base_name, WithoutNumber::AppendAfterDot)
                .map_err(|reason| at.invalid("masking.mask_base_name", reason))?;
            let mut list = Vec::with_capacity(n);
            for camera in 0..n {
                let name = pattern.format(camera as u64 + 1);
                let path =
                    files
                        .resolve(root, &name)
                        .map_err(|reason| ExperimentError::Refused {
                            file: at.file_of("masking.mask_base_name"),
                            location: at.location("masking.mask_base_name"),
                            name: name.clone(),
                            reason,
                        })?;
                if !files.is_file(&path) {
                    return Err(ExperimentError::Missing {
                        file: at.file_of("masking.mask_base_name"),
                        location: at.location("masking.mask_base_name"),
                        missing: path,
                    });
                }
                list.push(path);
            }
            Some(list)
        }
        _ => None,
    })
}

/// `track.par` in `ptv`'s terms (the module's table).
///
/// OpenPTV searches a trajectory's next particle in the box `dvmin..dvmax`
/// (per axis, mm per frame) around its position (a new trajectory) or its
/// prediction; `ptv` searches a new trajectory's first link within the
/// sphere of `max_velocity` around it. `max_velocity` is the radius of the
/// sphere around the box, `|(max(|dvxmin|, |dvxmax|), ...)|`: every link
/// OpenPTV can make, ptv can too (the box's corners are the farthest).
/// `dacc` is the same bound in both: the largest change of velocity
/// between two frames (mm per frame²), `ptv`'s `max_acceleration`.
pub(super) fn map_tracking(
    t: &TrackSection,
    at: &Locator,
) -> Result<ExperimentTracking, ExperimentError> {
    let axes = [
        ("dvxmin", t.dvxmin, "dvxmax", t.dvxmax),
        ("dvymin", t.dvymin, "dvymax", t.dvymax),
        ("dvzmin", t.dvzmin, "dvzmax", t.dvzmax),
    ];
    let mut reach = Vector3::zeros();
    for (i, (min_key, min, max_key, max)) in axes.into_iter().enumerate() {
        if min > max {
            return Err(at.invalid(
                &format!("track.{min_key}"),
                format!(
                    "{min_key} ({min}) is above {max_key} ({max}); give the smallest and largest \
                     displacement per frame along the axis (mm), e.g. -{0} and {0}",
                    max.abs().max(min.abs())
                ),
            ));
        }
        reach[i] = min.abs().max(max.abs());
    }
    let parameters = TrackingParameters {
        max_acceleration: t.dacc,
        ..TrackingParameters::new(reach.norm())
    };
    parameters.validate().map_err(|e| {
        let key = if e.to_string().contains("max_acceleration") {
            "track.dacc"
        } else {
            "track.dvxmax"
        };
        at.invalid(key, e.to_string())
    })?;
    Ok(ExperimentTracking {
        parameters,
        recovery: t.flagNewParticles,
    })
}

/// The Y range some camera sees between depths `z_min` and `z_max`: the
/// union over the cameras of where the rays through their image corners
/// meet those depths.
pub(super) fn seen_y_range(cameras: &[Camera], z_min: f64, z_max: f64) -> Option<(f64, f64)> {
    let mut range: Option<(f64, f64)> = None;
    for camera in cameras {
        let s = camera.sensor();
        let (w, h) = (f64::from(s.width), f64::from(s.height));
        for pixel in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
            let Ok(ray) = camera.ray(Point2::new(pixel.0, pixel.1)) else {
                continue;
            };
            for z in [z_min, z_max] {
                if let Some(point) = ray.at_z(z) {
                    let y = point.y;
                    if y.is_finite() {
                        range = Some(match range {
                            None => (y, y),
                            Some((lo, hi)) => (lo.min(y), hi.max(y)),
                        });
                    }
                }
            }
        }
    }
    range.filter(|(lo, hi)| hi > lo)
}
