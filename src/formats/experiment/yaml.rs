//! pyptv's `parameters_*.yaml` read into the experiment's sections
//! (`Sections`, named as pyptv names them), with the line of each key for
//! errors, its flow brackets, depth and items bounded before and while it
//! is parsed, and what `ptv` does not map listed with the reason.

use super::*;

/// The most `[` and `{` a pyptv YAML may hold: 256. The YAML parser
/// (libyaml) scans every token against each flow collection open around it,
/// so flow nesting costs quadratic time before any depth check can run (a
/// 200 KB `[[[[...` took 20 s); counting the characters, in the text as
/// written, bounds that whatever the nesting. pyptv writes its lists as
/// `- item` lines (no brackets); a hand-written `[a, b]` per list of its
/// some 30 lists stays far below.
pub const MAX_YAML_FLOW: usize = 256;

/// The deepest nesting a pyptv YAML may have: 16 levels (sections are the
/// first, their keys' mappings or lists the second and third; pyptv's YAML
/// nests 3 deep).
pub const MAX_YAML_DEPTH: usize = 16;

/// Refuses a YAML text with more than [`MAX_YAML_FLOW`] flow brackets,
/// before it is parsed. Every `[` and `{` counts (inside strings too: an
/// over-count can only refuse, never let a nesting through), except on
/// comment lines, which the parser skips whatever they hold.
pub(super) fn check_yaml_flow(text: &str, path: &Path) -> Result<(), ExperimentError> {
    let mut count = 0;
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with('#') {
            continue;
        }
        count += line.bytes().filter(|&b| b == b'[' || b == b'{').count();
        if count > MAX_YAML_FLOW {
            return Err(ExperimentError::Invalid {
                file: path.to_owned(),
                location: format!("line {}", i + 1),
                reason: format!(
                    "more than {MAX_YAML_FLOW} `[` and `{{` (flow lists and mappings), the most a \
                     pyptv YAML may have; write lists as `- item` lines, as pyptv does"
                ),
            });
        }
    }
    Ok(())
}

/// The most items (scalars, lists and mappings) a pyptv YAML may have,
/// an alias counted each time it is used: 32,768. pyptv's has about 400;
/// 64 KiB of text without aliases hold at most about 32k (`1,` each), so
/// this bounds what aliases may expand to (15 KB of `&a [1,1,...]` and
/// `[*a,*a,...]` made 640 MiB and 4 s of values) at what the largest plain
/// YAML costs.
pub const MAX_YAML_ITEMS: usize = 32_768;

/// Walks a YAML document as its parsers will (aliases expanded), building
/// nothing, and stops as soon as it has more than [`MAX_YAML_ITEMS`] items
/// or nests deeper than [`MAX_YAML_DEPTH`].
#[derive(Clone, Copy)]
pub(super) struct YamlBudget<'a> {
    pub(super) items: &'a std::cell::Cell<usize>,
    pub(super) depth: usize,
}

/// The start of [`YamlBudget`]'s refusals (the YAML library appends the
/// position).
pub(super) const YAML_LIMIT: &str = "beyond the limits of a pyptv YAML: ";

impl YamlBudget<'_> {
    pub(super) fn item<E: serde::de::Error>(self) -> Result<(), E> {
        self.items.set(self.items.get() + 1);
        if self.items.get() > MAX_YAML_ITEMS {
            return Err(E::custom(format!(
                "{YAML_LIMIT}more than {MAX_YAML_ITEMS} items (values, lists and mappings, an \
                 alias counted each time it is used; pyptv's YAML has some 400)"
            )));
        }
        Ok(())
    }

    pub(super) fn inner<E: serde::de::Error>(self) -> Result<Self, E> {
        self.item()?;
        if self.depth >= MAX_YAML_DEPTH {
            return Err(E::custom(format!(
                "{YAML_LIMIT}nested more than {MAX_YAML_DEPTH} levels deep (pyptv's nests 3: \
                 section, key, list)"
            )));
        }
        Ok(YamlBudget {
            depth: self.depth + 1,
            ..self
        })
    }
}

impl<'de> serde::de::DeserializeSeed<'de> for YamlBudget<'_> {
    type Value = ();

    fn deserialize<D: serde::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_any(self)
    }
}

impl<'de> serde::de::Visitor<'de> for YamlBudget<'_> {
    type Value = ();

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("any YAML value")
    }

    fn visit_bool<E: serde::de::Error>(self, _: bool) -> Result<(), E> {
        self.item()
    }

    fn visit_i64<E: serde::de::Error>(self, _: i64) -> Result<(), E> {
        self.item()
    }

    fn visit_u64<E: serde::de::Error>(self, _: u64) -> Result<(), E> {
        self.item()
    }

    fn visit_f64<E: serde::de::Error>(self, _: f64) -> Result<(), E> {
        self.item()
    }

    fn visit_i128<E: serde::de::Error>(self, _: i128) -> Result<(), E> {
        self.item()
    }

    fn visit_u128<E: serde::de::Error>(self, _: u128) -> Result<(), E> {
        self.item()
    }

    fn visit_char<E: serde::de::Error>(self, _: char) -> Result<(), E> {
        self.item()
    }

    fn visit_str<E: serde::de::Error>(self, _: &str) -> Result<(), E> {
        self.item()
    }

    fn visit_bytes<E: serde::de::Error>(self, _: &[u8]) -> Result<(), E> {
        self.item()
    }

    fn visit_unit<E: serde::de::Error>(self) -> Result<(), E> {
        self.item()
    }

    fn visit_none<E: serde::de::Error>(self) -> Result<(), E> {
        self.item()
    }

    fn visit_some<D: serde::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_any(self)
    }

    fn visit_newtype_struct<D: serde::Deserializer<'de>>(
        self,
        deserializer: D,
    ) -> Result<(), D::Error> {
        deserializer.deserialize_any(self)
    }

    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        let inner = self.inner()?;
        while seq.next_element_seed(inner)?.is_some() {}
        Ok(())
    }

    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        let inner = self.inner()?;
        while map.next_key_seed(inner)?.is_some() {
            map.next_value_seed(inner)?;
        }
        Ok(())
    }

    fn visit_enum<A: serde::de::EnumAccess<'de>>(self, data: A) -> Result<(), A::Error> {
        // A tagged value (`!tag value`): the tag, then the value.
        use serde::de::VariantAccess;
        let ((), variant) = data.variant_seed(self)?;
        variant.newtype_variant_seed(self)
    }
}

/// The YAML library's message for nesting beyond its own limit (128), in
/// this importer's words.
pub(super) fn yaml_reason(message: String) -> String {
    if let Some(limit) = message.find(YAML_LIMIT) {
        message[limit + YAML_LIMIT.len()..].to_owned()
    } else if message.starts_with("recursion limit exceeded") {
        format!(
            "nested more than {MAX_YAML_DEPTH} levels deep, the most a pyptv YAML may be \
             (pyptv's nests 3: section, key, list)"
        )
    } else {
        message
    }
}

/// The lines (1-based) of a YAML text's top-level `section:` lines and of
/// the `key:` lines inside each, found in one pass (the first of each).
#[derive(Default)]
pub(super) struct YamlLines {
    pub(super) sections: BTreeMap<String, usize>,
    pub(super) keys: BTreeMap<(String, String), usize>,
}

impl YamlLines {
    pub(super) fn new(text: &str) -> Self {
        let mut lines = YamlLines::default();
        let mut section: Option<String> = None;
        for (i, line) in text.lines().enumerate() {
            let indented = line.starts_with(' ') || line.starts_with('\t');
            let trimmed = line.trim_start();
            if trimmed.is_empty() {
                continue;
            }
            if !indented {
                let name = trimmed.split(':').next().unwrap_or(trimmed).to_owned();
                lines.sections.entry(name.clone()).or_insert(i + 1);
                section = Some(name);
            } else if let (Some(section), Some((key, _))) = (&section, trimmed.split_once(':')) {
                lines
                    .keys
                    .entry((section.clone(), key.to_owned()))
                    .or_insert(i + 1);
            }
        }
        lines
    }

    /// The line of `key:` inside `section:`, or of `section:` itself for an
    /// empty key.
    pub(super) fn line(&self, section: &str, key: &str) -> Option<usize> {
        if key.is_empty() {
            self.sections.get(section).copied()
        } else {
            self.keys
                .get(&(section.to_owned(), key.to_owned()))
                .copied()
        }
    }
}

pub(super) fn read_yaml(
    files: &dyn ExperimentFiles,
    path: &Path,
    root: &Path,
) -> Result<Experiment, ExperimentError> {
    let text = files.read_text(path)?;
    check_yaml_flow(&text, path)?;
    // The items and depth first, aliases expanded, nothing built: the
    // sections skip what they ignore at any depth, and the value would
    // expand aliases without bound.
    let yaml_error = |error: serde_norway::Error| {
        let line = error.location().map(|l| l.line());
        let mut reason = yaml_reason(error.to_string());
        if let Some(at) = reason.find(" at line ") {
            reason.truncate(at);
        }
        ExperimentError::Invalid {
            file: path.to_owned(),
            location: line.map_or_else(|| "the whole file".to_owned(), |l| format!("line {l}")),
            reason,
        }
    };
    let items = std::cell::Cell::new(0);
    serde::de::DeserializeSeed::deserialize(
        YamlBudget {
            items: &items,
            depth: 0,
        },
        serde_norway::Deserializer::from_str(&text),
    )
    .or_else(|error| {
        // A text that does not parse fails before any item is walked: the
        // sections' own reading names the key where it breaks. Anything
        // else (a limit passed, a value the walk cannot take) is refused
        // here, before a parser that expands aliases runs.
        if items.get() == 0 && !error.to_string().contains(YAML_LIMIT) {
            Ok(())
        } else {
            Err(yaml_error(error))
        }
    })?;
    let value = serde_norway::from_str::<serde_norway::Value>(&text);
    let deserializer = serde_norway::Deserializer::from_str(&text);
    let sections: Sections = serde_path_to_error::deserialize(deserializer).map_err(|err| {
        let key = err.path().to_string();
        let inner = err.into_inner();
        let line = inner.location().map(|l| l.line());
        // The YAML library's message ends with its own position; the
        // location says it once.
        let mut reason = yaml_reason(inner.to_string());
        if let Some(at) = reason.find(" at line ") {
            reason.truncate(at);
        }
        // ... and may start with the key, which the location also names.
        if let Some(rest) = reason.strip_prefix(&format!("{key}: ")) {
            reason = rest.to_owned();
        }
        ExperimentError::Invalid {
            file: path.to_owned(),
            location: match (line, key.as_str()) {
                (Some(line), ".") => format!("line {line}"),
                (Some(line), key) => format!("line {line}, {key}"),
                (None, key) => key.to_owned(),
            },
            reason,
        }
    })?;
    let mut places = BTreeMap::new();
    let mut section_files = BTreeMap::new();
    // The sections read, the value may still have failed: a key given
    // twice in a section they ignore.
    let value = value.map_err(yaml_error)?;
    let lines = YamlLines::new(&text);
    let mut unmapped = Vec::new();
    if let serde_norway::Value::Mapping(top) = &value {
        for (section, body) in top {
            let Some(section) = section.as_str() else {
                continue;
            };
            section_files.insert(section.to_owned(), path.to_owned());
            if let Some(line) = lines.line(section, "") {
                places.insert(section.to_owned(), (path.to_owned(), line));
            }
            let per_key = matches!(
                section,
                "ptv" | "cal_ori" | "criteria" | "targ_rec" | "sequence" | "masking" | "track"
            );
            match body {
                serde_norway::Value::Mapping(keys) if per_key => {
                    for (key, value) in keys {
                        let Some(key) = key.as_str() else { continue };
                        let full = format!("{section}.{key}");
                        if let Some(line) = lines.line(section, key) {
                            places.insert(full.clone(), (path.to_owned(), line));
                        }
                        if let Some(reason) = unmapped_reason(section, key) {
                            unmapped.push(UnmappedSetting {
                                file: path.display().to_string(),
                                key: full,
                                value: yaml_value_text(value),
                                reason: reason.to_owned(),
                            });
                        }
                    }
                }
                other => {
                    if let Some(reason) = unmapped_reason(section, "") {
                        unmapped.push(UnmappedSetting {
                            file: path.display().to_string(),
                            key: section.to_owned(),
                            value: match other {
                                serde_norway::Value::Mapping(_) => "(the whole section)".into(),
                                other => yaml_value_text(other),
                            },
                            reason: reason.to_owned(),
                        });
                    }
                }
            }
        }
    }
    let locator = Locator {
        places,
        section_files,
    };
    map(files, sections, root, &locator, unmapped)
}

pub(super) fn yaml_value_text(value: &serde_norway::Value) -> String {
    match value {
        serde_norway::Value::String(s) => s.clone(),
        other => serde_norway::to_string(other)
            .map(|s| s.trim().replace('\n', " "))
            .unwrap_or_default(),
    }
}

/// Why a `section.key` is not used, or `None` for the keys that are.
pub(super) fn unmapped_reason(section: &str, key: &str) -> Option<&'static str> {
    let used = match section {
        "num_cams" => return None,
        "ptv" => matches!(
            key,
            "n_img"
                | "hp_flag"
                | "allcam_flag"
                | "imx"
                | "imy"
                | "pix_x"
                | "pix_y"
                | "mmp_n1"
                | "mmp_n2"
                | "mmp_n3"
                | "mmp_d"
                | "splitter"
        ),
        "cal_ori" => key == "img_ori",
        "criteria" => matches!(key, "X_lay" | "Zmin_lay" | "Zmax_lay" | "eps0"),
        "targ_rec" => matches!(
            key,
            "gvthres"
                | "disco"
                | "nnmin"
                | "nnmax"
                | "nxmin"
                | "nxmax"
                | "nymin"
                | "nymax"
                | "sumg_min"
        ),
        "sequence" => matches!(key, "base_name" | "first" | "last"),
        "masking" => matches!(key, "mask_flag" | "mask_base_name"),
        "track" => matches!(
            key,
            "dvxmin"
                | "dvxmax"
                | "dvymin"
                | "dvymax"
                | "dvzmin"
                | "dvzmax"
                | "dacc"
                | "flagNewParticles"
        ),
        _ => false,
    };
    if used {
        return None;
    }
    Some(match (section, key) {
        ("ptv", "img_name") => {
            "the images of one frame for pyptv's single-frame preview; ptv takes the sequence's"
        }
        ("ptv", "img_cal") => {
            "the calibration images; ptv takes each camera's orientation from the .ori that \
             cal_ori.img_ori names"
        }
        ("ptv", "tiff_flag") | ("cal_ori", "tiff_flag") => {
            "ptv reads the image format from the file itself"
        }
        ("ptv", "chfield") | ("cal_ori", "chfield") => {
            "field-interlaced images; ptv reads full frames (0 is the only value it supports)"
        }
        ("ptv", "inverse") => "inverted (negative) images are not supported; invert them first",
        ("criteria", "cnx" | "cny" | "cn" | "csumg") => {
            "OpenPTV's similarity limits on the targets' extent, size and brightness; ptv matches \
             by epipolar geometry alone here"
        }
        ("criteria", "corrmin") => {
            "OpenPTV's least correlation of a candidate; ptv ranks candidates by their \
             intersection residual"
        }
        ("targ_rec", "cr_sz") => {
            "the size of the cross OpenPTV draws on targets in its GUI; nothing to detect"
        }
        ("track", "angle") => {
            "OpenPTV's largest turning angle of a link (gon); ptv has no angle limit: it ranks a \
             trajectory's candidates by the change of acceleration over four positions (Malik et \
             al. 1993) within max_acceleration (dacc), which already refuses sharp turns at speed"
        }
        ("track", "") => {
            "the tracking settings (dv*, dacc, flagNewParticles are read; see the others' reasons)"
        }
        ("track", _) => "ptv's tracking has no such setting",
        (
            "cal_ori"
            | "detect_plate"
            | "man_ori"
            | "man_ori_coordinates"
            | "orient"
            | "shaking"
            | "multi_planes"
            | "dumbbell"
            | "sortgrid"
            | "examine",
            _,
        ) => {
            "a calibration setting; ptv calibrates with `ptv calibrate`, this import takes the \
             calibration from the .ori files"
        }
        ("unsharp_mask", _) => {
            "pyptv's unsharp-mask preprocessing; ptv's detection uses its high-pass filter \
             (hp_flag) only"
        }
        ("plugins", _) => "pyptv's Python plugins cannot run in ptv",
        ("pft_version", _) => {
            "reading existing targets instead of images; ptv detects from the images"
        }
        _ => "ptv has no such setting",
    })
}
