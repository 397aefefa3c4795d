//! The image store: uploaded camera images as files under the data
//! directory, named by the SHA-256 of their bytes (`images/ab/abcdef...`).
//!
//! An upload streams into a temporary file (`tmp/`) while it is hashed, so
//! no image is ever held whole in memory by the HTTP layer; once the
//! request is complete the file is renamed to its hash. The database holds
//! which frame uses which hash. [`ImageStore::lock`] orders "rename, then
//! commit the rows" against "no row left, so delete the file", so a file
//! is never deleted while a frame being stored refers to it; across
//! processes too (`ptv serve` and `ptv worker` on one data directory): it
//! holds an exclusive `flock` on `images.lock` in the data directory
//! besides the process's own mutex.

use std::io;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;
use tokio::sync::{Mutex, MutexGuard};

/// The operating system's "no space left on device" (ENOSPC: 28 on Linux
/// and the BSDs) and "disk quota exceeded" (EDQUOT) codes;
/// `io::ErrorKind::StorageFull` would say it by kind, but needs a newer
/// Rust than this crate's minimum.
#[cfg(target_os = "linux")]
const STORAGE_FULL_CODES: &[i32] = &[28, 122];
#[cfg(all(unix, not(target_os = "linux")))]
const STORAGE_FULL_CODES: &[i32] = &[28, 69];
/// Windows' ERROR_HANDLE_DISK_FULL and ERROR_DISK_FULL.
#[cfg(windows)]
const STORAGE_FULL_CODES: &[i32] = &[39, 112];
#[cfg(not(any(unix, windows)))]
const STORAGE_FULL_CODES: &[i32] = &[];

/// Whether an I/O error means that the disk is full (or the quota used
/// up): what an upload or the database answers with a 507.
pub fn is_storage_full(error: &io::Error) -> bool {
    error
        .raw_os_error()
        .is_some_and(|code| STORAGE_FULL_CODES.contains(&code))
}

/// The files of uploaded images.
#[derive(Debug)]
pub struct ImageStore {
    /// `images/` under the data directory.
    root: PathBuf,
    /// `tmp/` under the data directory: uploads in progress.
    tmp: PathBuf,
    /// Held while files are persisted and their rows committed, or while
    /// unused files are deleted.
    lock: Mutex<()>,
    /// The file locked for the same across processes.
    lock_file: PathBuf,
}

/// The image store's lock, held until dropped (closing the locked file
/// releases its `flock`).
#[derive(Debug)]
pub struct ImageLock<'a> {
    _guard: MutexGuard<'a, ()>,
    _file: Option<std::fs::File>,
}

/// An upload being written.
#[derive(Debug)]
pub struct Upload {
    file: tokio::fs::File,
    path: PathBuf,
    hasher: Sha256,
    size: u64,
}

/// A complete upload, in its temporary file until persisted; the file is
/// removed if it is dropped unpersisted.
#[derive(Debug)]
pub struct UploadedFile {
    path: Option<PathBuf>,
    /// The hex SHA-256 of the bytes.
    pub sha256: String,
    /// Bytes.
    pub size: u64,
}

impl Drop for UploadedFile {
    fn drop(&mut self) {
        if let Some(path) = self.path.take() {
            let _ = std::fs::remove_file(path);
        }
    }
}

impl UploadedFile {
    /// The temporary file.
    pub fn temp_path(&self) -> Option<&Path> {
        self.path.as_deref()
    }
}

impl ImageStore {
    /// Opens the store under `data_dir`, creating its directories and
    /// removing uploads a stopped process left half-written (`ptv serve`,
    /// which takes the uploads).
    pub fn open(data_dir: &Path) -> io::Result<ImageStore> {
        let tmp = data_dir.join("tmp");
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp)?;
        }
        ImageStore::open_shared(data_dir)
    }

    /// Opens the store under `data_dir` next to a `ptv serve` that may be
    /// taking uploads into it (`ptv worker`): nothing is removed.
    pub fn open_shared(data_dir: &Path) -> io::Result<ImageStore> {
        let root = data_dir.join("images");
        let tmp = data_dir.join("tmp");
        std::fs::create_dir_all(&root)?;
        std::fs::create_dir_all(&tmp)?;
        Ok(ImageStore {
            root,
            tmp,
            lock: Mutex::new(()),
            lock_file: data_dir.join("images.lock"),
        })
    }

    /// The directory of uploads in progress (emptied at every start): for
    /// scratch files of a request, in a directory of their own.
    pub fn temp_dir(&self) -> &Path {
        &self.tmp
    }

    /// Starts an upload.
    pub async fn create_upload(&self) -> io::Result<Upload> {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let path = self.tmp.join(format!("upload-{}-{n}", std::process::id()));
        let file = tokio::fs::File::create(&path).await?;
        Ok(Upload {
            file,
            path,
            hasher: Sha256::new(),
            size: 0,
        })
    }

    /// The file of an image.
    pub fn path(&self, sha256: &str) -> PathBuf {
        let prefix = sha256.get(..2).unwrap_or("00");
        self.root.join(prefix).join(sha256)
    }

    /// Holds the store's lock; see the module's doc. Where the lock file
    /// cannot be opened or locked (a file system without `flock`), only
    /// the process's own mutex is held, with a warning.
    pub async fn lock(&self) -> ImageLock<'_> {
        let guard = self.lock.lock().await;
        let file = match super::file_lock::exclusive(self.lock_file.clone()).await {
            Ok(file) => Some(file),
            Err(error) => {
                tracing::warn!(%error, "cannot lock the image store across processes");
                None
            }
        };
        ImageLock {
            _guard: guard,
            _file: file,
        }
    }

    /// Moves an upload to its place (a file of the same content may be
    /// there already). Call with the lock held, then commit the rows.
    pub async fn persist(&self, mut upload: UploadedFile) -> io::Result<()> {
        let target = self.path(&upload.sha256);
        if let Some(parent) = target.parent() {
            tokio::fs::create_dir_all(parent).await?;
        }
        if let Some(path) = upload.path.take() {
            tokio::fs::rename(&path, &target).await?;
        }
        Ok(())
    }

    /// The hashes of every stored image file.
    pub fn stored(&self) -> io::Result<Vec<String>> {
        let mut hashes = Vec::new();
        for prefix in std::fs::read_dir(&self.root)? {
            let prefix = prefix?;
            if prefix.file_type()?.is_dir() {
                for file in std::fs::read_dir(prefix.path())? {
                    hashes.push(file?.file_name().to_string_lossy().into_owned());
                }
            }
        }
        Ok(hashes)
    }

    /// Reads an image's bytes.
    pub async fn read(&self, sha256: &str) -> io::Result<Vec<u8>> {
        tokio::fs::read(self.path(sha256)).await
    }

    /// Deletes an image file; call with the lock held, after checking that
    /// no row refers to it.
    pub async fn remove(&self, sha256: &str) -> io::Result<()> {
        match tokio::fs::remove_file(self.path(sha256)).await {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }
}

impl Upload {
    /// Appends bytes.
    pub async fn write(&mut self, chunk: &[u8]) -> io::Result<()> {
        self.hasher.update(chunk);
        self.size += chunk.len() as u64;
        self.file.write_all(chunk).await
    }

    /// Flushes and closes the file.
    pub async fn finish(mut self) -> io::Result<UploadedFile> {
        self.file.flush().await?;
        let path = std::mem::take(&mut self.path);
        let digest = std::mem::take(&mut self.hasher).finalize();
        let sha256 = digest.iter().map(|b| format!("{b:02x}")).collect();
        Ok(UploadedFile {
            path: Some(path),
            sha256,
            size: self.size,
        })
    }

    /// Bytes so far.
    pub fn size(&self) -> u64 {
        self.size
    }
}

impl Drop for Upload {
    fn drop(&mut self) {
        // An upload dropped before `finish` (a failed request) leaves no file.
        if !self.path.as_os_str().is_empty() {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_disk_is_told_from_other_io_errors() {
        assert!(is_storage_full(&io::Error::from_raw_os_error(28)));
        assert!(!is_storage_full(&io::Error::from_raw_os_error(13)));
        assert!(!is_storage_full(&io::Error::other("no space")));
    }

    /// Writes to `/dev/full` fail with ENOSPC, as on a full disk.
    #[cfg(target_os = "linux")]
    #[tokio::test]
    async fn an_upload_to_a_full_disk_fails_as_storage_full() {
        let mut upload = Upload {
            file: tokio::fs::OpenOptions::new()
                .write(true)
                .open("/dev/full")
                .await
                .unwrap(),
            path: PathBuf::new(),
            hasher: Sha256::new(),
            size: 0,
        };
        let mut error = upload.write(&[0; 1 << 16]).await.err();
        if error.is_none() {
            error = upload.finish().await.err();
        }
        let error = error.expect("a write to /dev/full fails");
        assert!(is_storage_full(&error), "{error:?}");
    }
}
