//! The legacy `parameters/` folder read into the experiment's sections:
//! one function per `.par` file (`ptv`, `cal_ori`, `criteria`,
//! `targ_rec`, `sequence`, `track`), each line under `section.key` as
//! liboptv's `parameters.c` reads it.

use super::*;

/// One `.par` file of the `parameters/` folder, read by OpenPTV's line
/// reader ([`openptv::ParLines`]) under `section.key`, each key's line
/// recorded for errors found later.
pub(super) struct ParFile<'a> {
    pub(super) path: PathBuf,
    pub(super) lines: openptv::ParLines,
    pub(super) section: &'static str,
    pub(super) places: &'a mut BTreeMap<String, (PathBuf, usize)>,
}

impl<'a> ParFile<'a> {
    pub(super) fn open(
        files: &dyn ExperimentFiles,
        dir: &Path,
        name: &str,
        section: &'static str,
        places: &'a mut BTreeMap<String, (PathBuf, usize)>,
    ) -> Result<Self, ExperimentError> {
        let path = dir.join("parameters").join(name);
        let text = files.read_text(&path)?;
        let lines =
            openptv::ParLines::new(&text, &path.display().to_string(), &format!("{section}."));
        Ok(ParFile {
            path,
            lines,
            section,
            places,
        })
    }

    /// Records where `key` was read.
    pub(super) fn record(&mut self, key: &str) {
        if let Some(line) = self.lines.line_of(key) {
            self.places
                .insert(format!("{}.{key}", self.section), (self.path.clone(), line));
        }
    }

    pub(super) fn text(&mut self, key: &str) -> Result<String, ExperimentError> {
        let value = self.lines.text(key)?;
        self.record(key);
        Ok(value)
    }

    pub(super) fn number(&mut self, key: &str) -> Result<f64, ExperimentError> {
        let value = self.lines.number(key)?;
        self.record(key);
        Ok(value)
    }

    pub(super) fn integer(&mut self, key: &str) -> Result<i64, ExperimentError> {
        let value = self.lines.integer(key)?;
        self.record(key);
        Ok(value)
    }

    pub(super) fn unsigned(&mut self, key: &str) -> Result<u64, ExperimentError> {
        let value = self.lines.unsigned(key)?;
        self.record(key);
        Ok(value)
    }
}

pub(super) fn read_legacy(
    files: &dyn ExperimentFiles,
    dir: &Path,
) -> Result<Experiment, ExperimentError> {
    let mut places = BTreeMap::new();
    let mut section_files = BTreeMap::new();
    let mut unmapped = Vec::new();
    let par = |name: &str| dir.join("parameters").join(name);
    for (section, file) in LEGACY_FILES {
        section_files.insert(section.to_owned(), par(file));
    }
    let ptv = read_legacy_ptv(files, &par("ptv.par"), &mut places, &mut unmapped)?;
    let n = ptv.n_img.unwrap_or_default();
    let cal_ori = read_legacy_cal_ori(files, dir, n, &mut places, &mut unmapped)?;
    let criteria = read_legacy_criteria(files, dir, &mut places, &mut unmapped)?;
    let targ_rec = read_legacy_targ_rec(files, dir, n, &mut places, &mut unmapped)?;
    let sequence = read_legacy_sequence(files, dir, n, &mut places)?;
    let track = if files.is_file(&par("track.par")) {
        Some(read_legacy_track(files, dir, &mut places, &mut unmapped)?)
    } else {
        None
    };
    // The other files are calibration's or the GUI's.
    let others: Vec<String> = files
        .list(&dir.join("parameters"))
        .into_iter()
        .filter(|name| name.ends_with(".par"))
        .filter(|name| !LEGACY_FILES.iter().any(|(_, file)| file == name))
        .collect();
    for name in others {
        let section = name.trim_end_matches(".par").to_owned();
        unmapped.push(UnmappedSetting {
            file: par(&name).display().to_string(),
            key: section.clone(),
            value: "(the whole file)".into(),
            reason: unmapped_reason(&section, "").unwrap_or_default().into(),
        });
    }

    let sections = Sections {
        num_cams: Some(n),
        ptv,
        cal_ori,
        criteria,
        targ_rec,
        sequence,
        masking: None,
        track,
    };
    let locator = Locator {
        places,
        section_files,
    };
    map(files, sections, dir, &locator, unmapped)
}

/// A setting of a `.par` file that `ptv` reads but does not use, with the
/// module table's reason.
pub(super) fn legacy_unmapped(
    file: &Path,
    section: &str,
    key: &str,
    value: String,
) -> UnmappedSetting {
    UnmappedSetting {
        file: file.display().to_string(),
        key: format!("{section}.{key}"),
        value,
        reason: unmapped_reason(section, key).unwrap_or_default().into(),
    }
}

/// The `.par` files read as the sections of pyptv's YAML.
pub(super) const LEGACY_FILES: [(&str, &str); 6] = [
    ("ptv", "ptv.par"),
    ("cal_ori", "cal_ori.par"),
    ("criteria", "criteria.par"),
    ("targ_rec", "targ_rec.par"),
    ("sequence", "sequence.par"),
    ("track", "track.par"),
];

/// ptv.par: OpenPTV's one reader of it, keys as pyptv's YAML names them.
pub(super) fn read_legacy_ptv(
    files: &dyn ExperimentFiles,
    ptv_path: &Path,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<PtvSection, ExperimentError> {
    let ptv_par = openptv::read_ptv_par(
        &files.read_text(ptv_path)?,
        &ptv_path.display().to_string(),
        "ptv.",
    )?;
    for (key, line) in ptv_par.lines() {
        places.insert(format!("ptv.{key}"), (ptv_path.to_owned(), line));
    }
    let n = ptv_par.num_cams();
    let ptv = PtvSection {
        n_img: Some(n),
        img_name: ptv_par.img_name,
        hp_flag: ptv_par.hp_flag,
        allcam_flag: ptv_par.allcam_flag,
        tiff_flag: ptv_par.tiff_flag,
        imx: ptv_par.imx,
        imy: ptv_par.imy,
        pix_x: ptv_par.pix_x,
        pix_y: ptv_par.pix_y,
        chfield: ptv_par.chfield,
        mmp_n1: ptv_par.mmp_n1,
        mmp_n2: ptv_par.mmp_n2,
        mmp_n3: ptv_par.mmp_n3,
        mmp_d: ptv_par.mmp_d,
        splitter: false,
    };
    let img_name = ptv.img_name.join(" ");
    unmapped.push(legacy_unmapped(ptv_path, "ptv", "img_name", img_name));
    let tiff_flag = u8::from(ptv.tiff_flag).to_string();
    unmapped.push(legacy_unmapped(ptv_path, "ptv", "tiff_flag", tiff_flag));
    Ok(ptv)
}

/// cal_ori.par: the `.ori` file of each camera.
pub(super) fn read_legacy_cal_ori(
    files: &dyn ExperimentFiles,
    dir: &Path,
    n: usize,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<CalOriSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "cal_ori.par", "cal_ori", places)?;
    let fixp_name = f.text("fixp_name")?;
    let mut img_ori = Vec::new();
    for i in 0..n {
        f.text(&format!("img_cal_name[{i}]"))?;
        img_ori.push(f.text(&format!("img_ori[{i}]"))?);
    }
    let cal_ori_path = f.path.clone();
    unmapped.push(legacy_unmapped(
        &cal_ori_path,
        "cal_ori",
        "fixp_name",
        fixp_name,
    ));
    Ok(CalOriSection { img_ori })
}

/// criteria.par: the layers, the band; the similarity terms are not used.
pub(super) fn read_legacy_criteria(
    files: &dyn ExperimentFiles,
    dir: &Path,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<CriteriaSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "criteria.par", "criteria", places)?;
    let mut lay = [[0.0; 3]; 2];
    for (i, layer) in lay.iter_mut().enumerate() {
        layer[0] = f.number(&format!("X_lay[{i}]"))?;
        layer[1] = f.number(&format!("Zmin_lay[{i}]"))?;
        layer[2] = f.number(&format!("Zmax_lay[{i}]"))?;
    }
    let mut similarity = Vec::new();
    for key in ["cnx", "cny", "cn", "csumg", "corrmin"] {
        similarity.push((key, f.number(key)?));
    }
    let criteria = CriteriaSection {
        X_lay: vec![lay[0][0], lay[1][0]],
        Zmin_lay: vec![lay[0][1], lay[1][1]],
        Zmax_lay: vec![lay[0][2], lay[1][2]],
        eps0: f.number("eps0")?,
    };
    let criteria_path = f.path.clone();
    for (key, value) in similarity {
        unmapped.push(legacy_unmapped(
            &criteria_path,
            "criteria",
            key,
            value.to_string(),
        ));
    }
    Ok(criteria)
}

/// targ_rec.par: detection. liboptv reads four thresholds whatever the
/// camera count.
pub(super) fn read_legacy_targ_rec(
    files: &dyn ExperimentFiles,
    dir: &Path,
    n: usize,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<TargRecSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "targ_rec.par", "targ_rec", places)?;
    let mut gvthres = Vec::new();
    for i in 0..n.max(4) {
        gvthres.push(f.integer(&format!("gvthres[{i}]"))?);
    }
    let targ_rec = TargRecSection {
        gvthres,
        disco: f.integer("disco")?,
        nnmin: f.integer("nnmin")?,
        nnmax: f.integer("nnmax")?,
        nxmin: f.integer("nxmin")?,
        nxmax: f.integer("nxmax")?,
        nymin: f.integer("nymin")?,
        nymax: f.integer("nymax")?,
        sumg_min: f.integer("sumg_min")?,
    };
    let cr_sz = f.integer("cr_sz")?;
    unmapped.push(legacy_unmapped(
        &f.path,
        "targ_rec",
        "cr_sz",
        cr_sz.to_string(),
    ));
    Ok(targ_rec)
}

/// sequence.par: the image names and the frames.
pub(super) fn read_legacy_sequence(
    files: &dyn ExperimentFiles,
    dir: &Path,
    n: usize,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
) -> Result<SequenceSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "sequence.par", "sequence", places)?;
    let mut base_name = Vec::new();
    for i in 0..n {
        let name = f.text(&format!("base_name[{i}]"))?;
        if name == "--" {
            return Err(ExperimentError::Invalid {
                file: f.path.clone(),
                location: format!("base_name[{i}]"),
                reason: "names `--` for this camera: pyptv's splitter, whose cameras are views \
                         of the first camera's image, which the .par files cannot say; give \
                         pyptv's YAML of the experiment (parameters_*.yaml, with ptv.splitter: \
                         true)"
                    .into(),
            });
        }
        base_name.push(name);
    }
    Ok(SequenceSection {
        base_name,
        first: f.unsigned("first")?,
        last: f.unsigned("last")?,
    })
}

/// track.par: nine values, liboptv's `read_track_par` (pyptv's later
/// lines, one per camera, are not read by liboptv either).
pub(super) fn read_legacy_track(
    files: &dyn ExperimentFiles,
    dir: &Path,
    places: &mut BTreeMap<String, (PathBuf, usize)>,
    unmapped: &mut Vec<UnmappedSetting>,
) -> Result<TrackSection, ExperimentError> {
    let mut f = ParFile::open(files, dir, "track.par", "track", places)?;
    let mut dv = [0.0; 6];
    for (value, key) in dv
        .iter_mut()
        .zip(["dvxmin", "dvxmax", "dvymin", "dvymax", "dvzmin", "dvzmax"])
    {
        *value = f.number(key)?;
    }
    let angle = f.number("angle")?;
    let dacc = f.number("dacc")?;
    let new_particles = f.integer("flagNewParticles")?;
    unmapped.push(legacy_unmapped(
        &f.path,
        "track",
        "angle",
        angle.to_string(),
    ));
    Ok(TrackSection {
        dvxmin: dv[0],
        dvxmax: dv[1],
        dvymin: dv[2],
        dvymax: dv[3],
        dvzmin: dv[4],
        dvzmax: dv[5],
        angle: Some(angle),
        dacc,
        flagNewParticles: new_particles != 0,
    })
}
