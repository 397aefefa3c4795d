//! Where an experiment's files come from: the one place the importer
//! opens anything.
//!
//! An experiment's files name other files: `cal_ori`'s `.ori` files (and
//! the `.addpar` beside each), pyptv's `masking.mask_base_name`. Whether
//! such a name may be followed is decided once, by the caller, in the
//! [`ExperimentFiles`] it gives the importer:
//!
//! - [`LocalFiles`] (the command line): the user's own directory; names
//!   resolve as the operating system resolves them from the experiment's
//!   root, absolute names, `..` and symbolic links included.
//! - [`UploadedFiles`] (the service): the set of files a client sent, under
//!   the paths it gave them. A name resolves only to a file of the set:
//!   absolute names, `..`, and anything that is not a plain relative path
//!   are refused ([`Refused`]), a clean name that was not sent is missing,
//!   and the files are stored under names of the set's own choosing (no
//!   client path ever becomes a path on disk), opened without following
//!   symbolic links. Errors name the files by their paths in the set.
//!
//! Every text file is read up to [`MAX_TEXT_BYTES`]; OpenPTV's parameter
//! and calibration files are a few hundred bytes, pyptv's YAML a few KB.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Component, Path, PathBuf};

use crate::formats::FormatError;

/// The largest parameter file (`.par`, `.yaml`, `.ori`, `.addpar`) read:
/// 64 KiB. OpenPTV's `.par`, `.ori` and `.addpar` files are under 1 KB
/// and pyptv's `parameters_*.yaml` 3-5 KB (the test_cavity one is 3.3 KB),
/// so this leaves 13 times the largest; it bounds what parsing one file may
/// cost: a YAML's events and value take a few hundred bytes per item, up to
/// about 220 times the text for a list of one-digit numbers (14 MiB here;
/// the 60 MB list of issue 29 took 3.7 GiB).
pub const MAX_TEXT_BYTES: u64 = 64 * 1024;

/// Why a name written in an experiment's file is not followed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Refused(pub String);

/// The files an experiment is read from.
pub trait ExperimentFiles {
    /// The path of `name`, as written in one of the experiment's files,
    /// relative to `root` (the directory the experiment's names are
    /// relative to).
    fn resolve(&self, root: &Path, name: &str) -> Result<PathBuf, Refused>;
    /// Whether `path` is a file.
    fn is_file(&self, path: &Path) -> bool;
    /// Whether `path` is a directory (for an uploaded set: the root, or a
    /// prefix of some file's path).
    fn is_dir(&self, path: &Path) -> bool;
    /// The names of the files directly in `dir`, sorted.
    fn list(&self, dir: &Path) -> Vec<String>;
    /// The whole content of the file at `path`, or an error naming it.
    fn read(&self, path: &Path) -> Result<Vec<u8>, FormatError>;

    /// A text file of at most [`MAX_TEXT_BYTES`], as UTF-8.
    fn read_text(&self, path: &Path) -> Result<String, FormatError> {
        let bytes = self.read_limited(path, MAX_TEXT_BYTES)?;
        String::from_utf8(bytes).map_err(|_| FormatError::Io {
            path: path.to_owned(),
            reason: std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "stream did not contain valid UTF-8",
            ),
        })
    }

    /// At most `limit` bytes of the file at `path`; an error naming the
    /// limit if it has more.
    fn read_limited(&self, path: &Path, limit: u64) -> Result<Vec<u8>, FormatError>;
}

/// An error for a file above `limit`.
fn too_large(path: &Path, limit: u64) -> FormatError {
    FormatError::invalid(
        &path.display().to_string(),
        "size",
        format!(
            "the file is larger than {} KiB, the most a parameter or calibration file may have \
             (OpenPTV's are under 1 KB, pyptv's YAML a few KB); is it the right file?",
            limit / 1024
        ),
    )
}

fn read_up_to(mut reader: impl Read, path: &Path, limit: u64) -> Result<Vec<u8>, FormatError> {
    let mut bytes = Vec::new();
    reader
        .by_ref()
        .take(limit + 1)
        .read_to_end(&mut bytes)
        .map_err(|reason| FormatError::Io {
            path: path.to_owned(),
            reason,
        })?;
    if bytes.len() as u64 > limit {
        return Err(too_large(path, limit));
    }
    Ok(bytes)
}

/// The local file system: a user's own experiment (`ptv experiment
/// import`, `ptv process-sequence --experiment`). Names resolve from the
/// root as the operating system resolves them.
#[derive(Clone, Copy, Debug, Default)]
pub struct LocalFiles;

impl ExperimentFiles for LocalFiles {
    fn resolve(&self, root: &Path, name: &str) -> Result<PathBuf, Refused> {
        Ok(root.join(name))
    }

    fn is_file(&self, path: &Path) -> bool {
        path.is_file()
    }

    fn is_dir(&self, path: &Path) -> bool {
        path.is_dir()
    }

    fn list(&self, dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .map(|entries| {
                entries
                    .filter_map(|e| e.ok())
                    .filter_map(|e| e.file_name().to_str().map(str::to_owned))
                    .collect()
            })
            .unwrap_or_default();
        names.sort();
        names
    }

    fn read(&self, path: &Path) -> Result<Vec<u8>, FormatError> {
        std::fs::read(path).map_err(|reason| FormatError::Io {
            path: path.to_owned(),
            reason,
        })
    }

    fn read_limited(&self, path: &Path, limit: u64) -> Result<Vec<u8>, FormatError> {
        let file = std::fs::File::open(path).map_err(|reason| FormatError::Io {
            path: path.to_owned(),
            reason,
        })?;
        read_up_to(file, path, limit)
    }
}

/// Where an uploaded file's bytes are.
#[derive(Clone, Debug)]
enum Stored {
    /// In memory.
    Memory(Vec<u8>),
    /// In a file the service wrote (under a name of its own).
    Disk(PathBuf),
}

/// The files a client uploaded, by their paths inside the experiment
/// (`parameters/ptv.par`, `cal/cam1.tif.ori`). Nothing outside the set is
/// ever opened.
#[derive(Clone, Debug, Default)]
pub struct UploadedFiles {
    files: BTreeMap<String, Stored>,
}

/// The most directory levels of an uploaded file's path.
pub const MAX_UPLOAD_DEPTH: usize = 8;
/// The longest path of an uploaded file, or name inside one, in bytes.
pub const MAX_UPLOAD_PATH: usize = 512;

impl UploadedFiles {
    /// An empty set.
    pub fn new() -> Self {
        UploadedFiles::default()
    }

    /// `name` (a client's path inside the experiment, or a name written in
    /// one of its files) as the set's key: its plain components joined by
    /// `/`, `.` and empty components dropped. Refuses anything else.
    pub fn key(name: &str) -> Result<String, Refused> {
        let refuse = |why: &str| Err(Refused(why.to_owned()));
        if name.is_empty() {
            return refuse("an empty name");
        }
        if name.len() > MAX_UPLOAD_PATH {
            return refuse(&format!("a name longer than {MAX_UPLOAD_PATH} bytes"));
        }
        if name.chars().any(|c| c.is_control()) {
            return refuse("a name with control characters");
        }
        if name.contains('\\') {
            return refuse("a name with a backslash; separate directories with `/`");
        }
        let path = Path::new(name);
        let mut parts = Vec::new();
        for component in path.components() {
            match component {
                Component::Normal(part) => match part.to_str() {
                    Some(part) => parts.push(part),
                    None => return refuse("a name that is not UTF-8"),
                },
                Component::CurDir => {}
                Component::ParentDir => {
                    return refuse("a name with `..`, which leaves the experiment directory")
                }
                Component::RootDir | Component::Prefix(_) => return refuse("an absolute path"),
            }
        }
        if parts.is_empty() {
            return refuse("not a file's path");
        }
        if parts.len() > MAX_UPLOAD_DEPTH {
            return refuse(&format!(
                "a path deeper than {MAX_UPLOAD_DEPTH} directory levels"
            ));
        }
        Ok(parts.join("/"))
    }

    /// Adds a file held in memory under `name`; false if the set has it.
    pub fn insert_bytes(&mut self, name: &str, bytes: Vec<u8>) -> Result<bool, Refused> {
        self.insert(name, Stored::Memory(bytes))
    }

    /// Adds a file the caller wrote at `stored` (a path of its own
    /// choosing, never the client's) under `name`; false if the set has it.
    pub fn insert_stored(&mut self, name: &str, stored: PathBuf) -> Result<bool, Refused> {
        self.insert(name, Stored::Disk(stored))
    }

    fn insert(&mut self, name: &str, stored: Stored) -> Result<bool, Refused> {
        let key = Self::key(name)?;
        if self.files.contains_key(&key) {
            return Ok(false);
        }
        self.files.insert(key, stored);
        Ok(true)
    }

    /// Whether the set has `key` (a path as [`UploadedFiles::key`] gives).
    pub fn contains(&self, key: &str) -> bool {
        self.files.contains_key(key)
    }

    /// The number of files.
    pub fn len(&self) -> usize {
        self.files.len()
    }

    /// Whether the set is empty.
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    fn get(&self, path: &Path) -> Option<&Stored> {
        path.to_str().and_then(|key| self.files.get(key))
    }

    fn not_sent(path: &Path) -> FormatError {
        FormatError::Io {
            path: path.to_owned(),
            reason: std::io::Error::new(std::io::ErrorKind::NotFound, "not among the files sent"),
        }
    }

    /// Opens a stored file without following a symbolic link (the set's
    /// files are regular files the service wrote; anything else is refused).
    fn open(path: &Path, stored: &Path) -> Result<std::fs::File, FormatError> {
        use std::os::unix::fs::OpenOptionsExt;
        let refused = |reason: std::io::Error| FormatError::Io {
            path: path.to_owned(),
            reason,
        };
        let file = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(rustix::fs::OFlags::NOFOLLOW.bits() as i32)
            .open(stored)
            .map_err(|error| {
                // The operating system's message would name the stored path.
                refused(std::io::Error::new(
                    error.kind(),
                    "cannot be opened (a symbolic link, or not stored)",
                ))
            })?;
        let metadata = file.metadata().map_err(refused)?;
        if !metadata.is_file() {
            return Err(refused(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "not a regular file",
            )));
        }
        Ok(file)
    }
}

impl ExperimentFiles for UploadedFiles {
    fn resolve(&self, root: &Path, name: &str) -> Result<PathBuf, Refused> {
        let key = Self::key(name)?;
        let root = root.to_str().unwrap_or_default();
        Ok(PathBuf::from(if root.is_empty() {
            key
        } else {
            Self::key(&format!("{root}/{key}"))?
        }))
    }

    fn is_file(&self, path: &Path) -> bool {
        self.get(path).is_some()
    }

    fn is_dir(&self, path: &Path) -> bool {
        let Some(dir) = path.to_str() else {
            return false;
        };
        let dir = dir.trim_end_matches('/');
        dir.is_empty()
            || self.files.keys().any(|key| {
                key.strip_prefix(dir)
                    .is_some_and(|rest| rest.starts_with('/'))
            })
    }

    fn list(&self, dir: &Path) -> Vec<String> {
        let dir = dir.to_str().unwrap_or_default().trim_end_matches('/');
        self.files
            .keys()
            .filter_map(|key| {
                let rest = if dir.is_empty() {
                    key.as_str()
                } else {
                    key.strip_prefix(dir)?.strip_prefix('/')?
                };
                (!rest.contains('/')).then(|| rest.to_owned())
            })
            .collect()
    }

    fn read(&self, path: &Path) -> Result<Vec<u8>, FormatError> {
        self.read_limited(path, u64::MAX - 1)
    }

    fn read_limited(&self, path: &Path, limit: u64) -> Result<Vec<u8>, FormatError> {
        match self.get(path) {
            None => Err(Self::not_sent(path)),
            Some(Stored::Memory(bytes)) => {
                if bytes.len() as u64 > limit {
                    Err(too_large(path, limit))
                } else {
                    Ok(bytes.clone())
                }
            }
            Some(Stored::Disk(stored)) => read_up_to(Self::open(path, stored)?, path, limit),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_plain_relative_paths() {
        assert_eq!(
            UploadedFiles::key("parameters/ptv.par").unwrap(),
            "parameters/ptv.par"
        );
        assert_eq!(
            UploadedFiles::key("./cal//cam1.tif.ori").unwrap(),
            "cal/cam1.tif.ori"
        );
        for name in [
            "",
            "/proc/self/environ",
            "../secret",
            "cal/../../x",
            "cal/../cal/cam1.tif.ori",
            ".",
            "a\0b",
            "a\nb",
            "c:\\x",
            "a/b/c/d/e/f/g/h/i",
        ] {
            assert!(UploadedFiles::key(name).is_err(), "{name:?} is refused");
        }
        assert!(UploadedFiles::key(&"a".repeat(MAX_UPLOAD_PATH + 1)).is_err());
        assert!(UploadedFiles::key("a/b/c/d/e/f/g/h").is_ok());
    }

    #[test]
    fn an_uploaded_set_reads_only_its_files() {
        let mut files = UploadedFiles::new();
        assert!(files
            .insert_bytes("parameters/ptv.par", b"4\n".to_vec())
            .unwrap());
        assert!(!files
            .insert_bytes("./parameters/ptv.par", Vec::new())
            .unwrap());
        let root = Path::new("");
        let ptv = files.resolve(root, "parameters/ptv.par").unwrap();
        assert_eq!(files.read_text(&ptv).unwrap(), "4\n");
        assert!(files.resolve(root, "/etc/passwd").is_err());
        assert!(files
            .resolve(root, "parameters/../parameters/ptv.par")
            .is_err());
        // A clean name that was not sent is missing, and reading it reads
        // nothing from the disk, whatever is there.
        let missing = files.resolve(root, "etc/passwd").unwrap();
        assert!(!files.is_file(&missing));
        assert!(files.read(&missing).is_err());
        assert!(files.is_dir(root) && files.is_dir(Path::new("parameters")));
        assert!(!files.is_dir(Path::new("param")));
        assert_eq!(files.list(Path::new("parameters")), vec!["ptv.par"]);
        assert_eq!(files.list(root), Vec::<String>::new());
    }

    #[test]
    fn stored_files_are_not_followed_through_symbolic_links() {
        let dir = tempfile::tempdir().unwrap();
        let secret = dir.path().join("secret");
        std::fs::write(&secret, "AWS_SECRET_ACCESS_KEY=canary").unwrap();
        let link = dir.path().join("0");
        std::os::unix::fs::symlink(&secret, &link).unwrap();
        let mut files = UploadedFiles::new();
        files.insert_stored("cal/cam1.tif.ori", link).unwrap();
        let error = files
            .read_text(Path::new("cal/cam1.tif.ori"))
            .unwrap_err()
            .to_string();
        assert!(error.starts_with("cal/cam1.tif.ori: "), "{error}");
        assert!(!error.contains("canary") && !error.contains(dir.path().to_str().unwrap()));
    }

    #[test]
    fn text_files_are_read_up_to_the_limit() {
        let mut files = UploadedFiles::new();
        let big = vec![b'1'; MAX_TEXT_BYTES as usize + 1];
        files.insert_bytes("parameters_Run1.yaml", big).unwrap();
        let error = files
            .read_text(Path::new("parameters_Run1.yaml"))
            .unwrap_err()
            .to_string();
        assert!(error.contains("64 KiB"), "{error}");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ptv.par");
        std::fs::write(&path, vec![b' '; MAX_TEXT_BYTES as usize + 1]).unwrap();
        assert!(LocalFiles
            .read_text(&path)
            .unwrap_err()
            .to_string()
            .contains("64 KiB"));
    }
}
