//! The image store: uploaded camera images (and every other stored file:
//! job inputs, backgrounds, masks), named by the SHA-256 of their bytes,
//! in one of two backends behind this one type, so that the HTTP layer and
//! the jobs do not know which runs:
//!
//! - **the local directory** (the default): files under the data
//!   directory (`images/ab/abcdef...`);
//! - **an S3-compatible object store** (`--object-store s3://bucket/prefix`:
//!   AWS, MinIO, Ceph; objects `PREFIX/images/ab/abcdef...`), through
//!   apache arrow-rs's `object_store` crate (request signing, retries with
//!   backoff, multipart uploads, the usual AWS variables).
//!
//! The local backend stays our own code rather than `object_store`'s
//! `LocalFileSystem`: that one would have to keep the guarantees below
//! (the `flock`, a full disk told apart as 507, the temporary files'
//! cleanup) around it anyway, and a rename into place is what it does too.
//!
//! In both, an upload streams into a temporary file under the data
//! directory (`tmp/`) while it is hashed, so no image is ever held whole in
//! memory by the HTTP layer; the data directory stays the place of such
//! scratch files whatever the backend. The database holds which frame
//! (or job, or background) uses which hash.
//!
//! # Persist, then commit; delete only what no row refers to
//!
//! Invariant: **no object is deleted while a committed row refers to it**,
//! and an object a failed or crashed upload left is removed eventually
//! (by [`ImageStore::sweep`], at every `ptv serve` start and every
//! [`SWEEP_INTERVAL`] while it runs).
//!
//! [`ImageStore::lock`] orders the two critical sections:
//!
//! - *storing* (the request that uploads, or a job storing a background):
//!   [`ImageStore::stage`] each file first, without the lock (the local
//!   backend does nothing here; S3 puts the object, multipart above
//!   [`MULTIPART_ABOVE`]); then, holding the lock, [`ImageStore::persist`]
//!   each (local: rename into place; S3: check that the object is there
//!   and put it again from the temporary file, still kept, if not) and
//!   commit the rows;
//! - *deleting*: holding the lock, check that no row refers to the hash
//!   ([`crate::service::store::Store::image_in_use`]), then [`ImageStore::remove`].
//!
//! Why this is enough: a deletion of hash `h` either ends before a storing
//! section for `h` starts, and then that section finds the object missing
//! and puts it again before committing; or it starts after the section
//! committed, and then it sees the row and deletes nothing. The object put
//! before the section (S3's `stage`) may be deleted meanwhile: that is the
//! first case. Only the check and the commit wait for the lock, never an
//! upload's transfer, so uploads to S3 proceed in parallel.
//!
//! The lock must be held by one process at a time among all that share
//! the database. It is the process's own mutex, then an exclusive `flock`
//! on `images.lock` in the data directory: exact for every process on one
//! SQLite database, which lie on one host by construction (SQLite is not
//! shared across hosts), whatever the image backend; then, on PostgreSQL,
//! whose processes may run on any host, a transaction-level advisory lock
//! in the database ([`Store::lock_across_hosts`], [`IMAGES_LOCK_KEY`]),
//! held by one connection per process (the mutex comes first). The
//! protocol above stays as it is. S3 offers no conditional delete
//! that could replace it (an object's ETag is the same for the same
//! content, so `If-Match` cannot tell a re-upload from the old object).
//!
//! # Errors
//!
//! [`ImageStoreError`] says by type what went wrong: a full local disk
//! (507 to a client, a job waiting for space), an object store that cannot
//! be reached or answers 5xx after `object_store`'s own retries (503 with
//! `Retry-After`, a job attempt given back uncounted), an object missing
//! that a committed row refers to (an internal error that says so).

use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use futures_util::StreamExt;
use object_store::path::Path as ObjectPath;
use object_store::ObjectStore;
use sha2::{Digest, Sha256};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{Mutex, MutexGuard};

use crate::service::infra::urls::ObjectStoreUrl;
use crate::service::store::{HostsLock, Store};

/// Files larger than this go to S3 as multipart uploads, in parts of this
/// size (S3's smallest part is 5 MiB); smaller ones in one request, read
/// whole from their temporary file.
pub const MULTIPART_ABOVE: usize = 8 << 20;

/// How often a running `ptv serve` removes the objects no row refers to
/// (left by crashed uploads), besides at its start.
pub const SWEEP_INTERVAL: Duration = Duration::from_secs(3600);

/// How long one request to the object store may take, retries included
/// (`object_store`'s retry timeout), before the store counts as
/// unavailable: short enough that a client gets its 503 well within the
/// request timeout, long enough to ride out a server's restart.
pub const OBJECT_STORE_RETRY_TIMEOUT: Duration = Duration::from_secs(15);

/// What went wrong in the image store, by kind.
#[derive(Debug, thiserror::Error)]
pub enum ImageStoreError {
    /// A local file operation failed (a full disk among them:
    /// [`is_storage_full`]).
    #[error("the image store: {0}")]
    Io(#[from] io::Error),
    /// The object store cannot be reached: connection refused or reset,
    /// timeouts, or 5xx answers after `object_store`'s own retries. The
    /// same operation may succeed later.
    #[error("the object store cannot be reached (try again later): {0}")]
    Unavailable(String),
    /// An image that should be there is not.
    #[error("image {sha256} is missing from the image store")]
    Missing {
        /// Its hash.
        sha256: String,
    },
    /// The object store refused the operation otherwise (credentials,
    /// a missing bucket, a malformed answer).
    #[error("the object store: {0}")]
    Other(String),
}

impl ImageStoreError {
    /// Sorts an `object_store` error: a missing object, the store out of
    /// reach, or anything else. `object_store` 0.12 keeps its retry
    /// error's type private, so a 5xx after its retries is told by the
    /// status in its message; connection and timeout errors by the HTTP
    /// client's own error in the chain.
    fn from_object_store(error: object_store::Error, sha256: Option<&str>) -> ImageStoreError {
        if let (object_store::Error::NotFound { .. }, Some(sha256)) = (&error, sha256) {
            return ImageStoreError::Missing {
                sha256: sha256.to_owned(),
            };
        }
        let message = crate::service::infra::errors::error_chain(&error);
        if unreachable(&error) {
            ImageStoreError::Unavailable(message)
        } else {
            ImageStoreError::Other(message)
        }
    }
}

/// Whether an `object_store` error means the server could not be reached
/// or failed on its side (see [`ImageStoreError::Unavailable`]).
fn unreachable(error: &object_store::Error) -> bool {
    use object_store::client::HttpErrorKind;
    let mut source: Option<&(dyn std::error::Error + 'static)> = Some(error);
    while let Some(error) = source {
        if let Some(http) = error.downcast_ref::<object_store::client::HttpError>() {
            if matches!(
                http.kind(),
                HttpErrorKind::Connect
                    | HttpErrorKind::Request
                    | HttpErrorKind::Timeout
                    | HttpErrorKind::Interrupted
            ) {
                return true;
            }
        }
        if let Some(http) = error.downcast_ref::<reqwest::Error>() {
            if http.is_connect() || http.is_timeout() || http.is_request() {
                return true;
            }
        }
        if let Some(io) = error.downcast_ref::<io::Error>() {
            if matches!(
                io.kind(),
                io::ErrorKind::ConnectionRefused
                    | io::ErrorKind::ConnectionReset
                    | io::ErrorKind::ConnectionAborted
                    | io::ErrorKind::TimedOut
                    | io::ErrorKind::BrokenPipe
            ) {
                return true;
            }
        }
        let text = error.to_string();
        if text.contains("status code: 5") || text.contains("error sending request") {
            return true;
        }
        source = error.source();
    }
    false
}

/// Where the bytes live.
#[derive(Debug)]
enum Backend {
    /// `images/` under the data directory.
    Local { root: PathBuf },
    /// An S3-compatible object store, under `PREFIX/images/`.
    Objects {
        store: Arc<dyn ObjectStore>,
        root: ObjectPath,
    },
}

/// The stored files, in their backend.
#[derive(Debug)]
pub struct ImageStore {
    backend: Backend,
    /// `tmp/` under the data directory: uploads in progress.
    tmp: PathBuf,
    /// Held while files are persisted and their rows committed, or while
    /// unused files are deleted.
    lock: Mutex<()>,
    /// The file locked for the same across processes.
    lock_file: PathBuf,
    /// Whether a local file is flushed to the disk when its upload is
    /// finished, and its directory when it is persisted (`ptv serve
    /// --fsync`), so that it survives a power loss before the rows naming
    /// it commit; only the directory's flush is under the lock.
    fsync: bool,
}

/// The image store's lock, held until dropped (closing the locked file
/// releases its `flock`; ending the transaction, PostgreSQL's advisory
/// lock).
#[derive(Debug)]
pub struct ImageLock<'a> {
    _guard: MutexGuard<'a, ()>,
    _file: Option<std::fs::File>,
    _hosts: HostsLock,
}

/// The key of the image store's advisory lock on PostgreSQL ("ptvimage"
/// in ASCII): one lock for every process on the database.
pub const IMAGES_LOCK_KEY: i64 = 0x7074_7669_6d61_6765;

/// An upload being written.
#[derive(Debug)]
pub struct Upload {
    file: tokio::fs::File,
    path: PathBuf,
    hasher: Sha256,
    size: u64,
    /// `--fsync`: the file is flushed to the disk when it is finished,
    /// before the image lock is taken to persist it.
    fsync: bool,
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

/// The S3 client of `--object-store`: endpoint from `endpoint` (else
/// `AWS_ENDPOINT_URL` / `AWS_ENDPOINT`), region and credentials from the
/// usual AWS variables (`AWS_REGION`, `AWS_ACCESS_KEY_ID`,
/// `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`; `AWS_ALLOW_HTTP=true`
/// for a plain-http endpoint such as a lab's MinIO); path-style requests
/// when an endpoint is given (what MinIO and most self-hosted servers
/// need). Retries end after [`OBJECT_STORE_RETRY_TIMEOUT`].
fn s3_client(
    url: &ObjectStoreUrl,
    endpoint: Option<&str>,
) -> Result<Arc<dyn ObjectStore>, ImageStoreError> {
    use object_store::aws::AmazonS3Builder;
    use object_store::{ClientOptions, RetryConfig};
    let mut builder = AmazonS3Builder::from_env().with_bucket_name(&url.bucket);
    let endpoint = endpoint.map(str::to_owned).or_else(|| {
        std::env::var("AWS_ENDPOINT_URL")
            .ok()
            .or_else(|| std::env::var("AWS_ENDPOINT").ok())
    });
    if let Some(endpoint) = endpoint {
        builder = builder
            .with_endpoint(endpoint)
            .with_virtual_hosted_style_request(false);
    }
    if std::env::var_os("AWS_REGION").is_none() && std::env::var_os("AWS_DEFAULT_REGION").is_none()
    {
        builder = builder.with_region("us-east-1");
    }
    let retry = RetryConfig {
        retry_timeout: OBJECT_STORE_RETRY_TIMEOUT,
        max_retries: 6,
        ..RetryConfig::default()
    };
    let allow_http = std::env::var("AWS_ALLOW_HTTP").is_ok_and(|v| v == "true" || v == "1");
    let options = ClientOptions::new()
        .with_allow_http(allow_http)
        .with_connect_timeout(Duration::from_secs(5))
        .with_timeout(Duration::from_secs(120));
    let store = builder
        .with_retry(retry)
        .with_client_options(options)
        .build()
        .map_err(|e| ImageStoreError::Other(crate::service::infra::errors::error_chain(&e)))?;
    Ok(Arc::new(store))
}

impl ImageStore {
    /// Opens the store under `data_dir`, creating its directories and
    /// removing the uploads and scratch files that stopped processes left
    /// in `tmp/` (`ptv serve`, which takes the uploads); `objects`: the
    /// object store's URL and endpoint, if the images go there.
    pub async fn open(
        data_dir: &Path,
        objects: Option<(&ObjectStoreUrl, Option<&str>)>,
    ) -> Result<ImageStore, ImageStoreError> {
        remove_abandoned(
            &data_dir.join("tmp"),
            crate::service::infra::process::process_exists,
        )?;
        ImageStore::open_shared(data_dir, objects).await
    }

    /// Opens the store under `data_dir` next to a `ptv serve` that may be
    /// taking uploads into it (`ptv worker`): nothing is removed. With an
    /// object store, its bucket is listed once, so that a wrong bucket or
    /// credentials show at the start.
    pub async fn open_shared(
        data_dir: &Path,
        objects: Option<(&ObjectStoreUrl, Option<&str>)>,
    ) -> Result<ImageStore, ImageStoreError> {
        let tmp = data_dir.join("tmp");
        std::fs::create_dir_all(&tmp)?;
        let backend = match objects {
            None => {
                let root = data_dir.join("images");
                std::fs::create_dir_all(&root)?;
                Backend::Local { root }
            }
            Some((url, endpoint)) => {
                let store = s3_client(url, endpoint)?;
                let root = if url.prefix.is_empty() {
                    ObjectPath::from("images")
                } else {
                    ObjectPath::from(format!("{}/images", url.prefix))
                };
                store
                    .list_with_delimiter(Some(&root))
                    .await
                    .map_err(|e| ImageStoreError::from_object_store(e, None))?;
                Backend::Objects { store, root }
            }
        };
        Ok(ImageStore {
            backend,
            tmp,
            lock: Mutex::new(()),
            lock_file: data_dir.join("images.lock"),
            fsync: false,
        })
    }

    /// The store, with local files flushed to the disk as they are
    /// finished and persisted where `fsync` (`--fsync`; an object store's PUT is
    /// durable once acknowledged, and this changes nothing there).
    pub fn with_fsync(self, fsync: bool) -> ImageStore {
        ImageStore { fsync, ..self }
    }

    /// Whether the store answers within `limit`: the local directory
    /// always does (a full disk shows on a write); an object store must
    /// answer a listing of its prefix (one request, no retries counted
    /// beyond the limit).
    pub async fn ready(&self, limit: Duration) -> Result<(), ImageStoreError> {
        let Backend::Objects { store, root } = &self.backend else {
            return Ok(());
        };
        match tokio::time::timeout(limit, store.list_with_delimiter(Some(root))).await {
            Ok(Ok(_)) => Ok(()),
            Ok(Err(error)) => Err(ImageStoreError::from_object_store(error, None)),
            Err(_) => Err(ImageStoreError::Unavailable(format!(
                "no answer within {limit:?}"
            ))),
        }
    }

    /// The directory of uploads in progress, for scratch files of a
    /// request too, in a directory of their own named `KIND-PID-...` (what
    /// a stopped process left is removed at the next `ptv serve` start).
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
            fsync: self.fsync,
        })
    }

    /// The local file of an image (`images/ab/abcdef...`).
    fn local_path(root: &Path, sha256: &str) -> PathBuf {
        let prefix = sha256.get(..2).unwrap_or("00");
        root.join(prefix).join(sha256)
    }

    /// The object of an image (`PREFIX/images/ab/abcdef...`).
    fn object_path(root: &ObjectPath, sha256: &str) -> ObjectPath {
        let prefix = sha256.get(..2).unwrap_or("00");
        root.child(prefix).child(sha256)
    }

    /// Holds the store's lock, for every process on `database`; see the
    /// module's doc. Where the lock file cannot be opened or locked (a
    /// file system without `flock`), the process's own mutex stands in for
    /// it, with a warning. Fails only where the database's lock cannot be
    /// taken (PostgreSQL out of reach).
    pub async fn lock(
        &self,
        database: &Store,
    ) -> Result<ImageLock<'_>, crate::service::store::StoreError> {
        let guard = self.lock.lock().await;
        let file = match crate::service::infra::file_lock::exclusive(self.lock_file.clone()).await {
            Ok(file) => Some(file),
            Err(error) => {
                tracing::warn!(%error, "cannot lock the image store across processes");
                None
            }
        };
        let hosts = database.lock_across_hosts(IMAGES_LOCK_KEY).await?;
        Ok(ImageLock {
            _guard: guard,
            _file: file,
            _hosts: hosts,
        })
    }

    /// The first step of storing a file, before the lock: S3 puts the
    /// object (the file stays in `tmp/` until persisted); the local
    /// backend does nothing. See the module's doc.
    pub async fn stage(&self, upload: &UploadedFile) -> Result<(), ImageStoreError> {
        match (&self.backend, &upload.path) {
            (Backend::Objects { store, root }, Some(path)) => {
                put_file(
                    store.as_ref(),
                    &Self::object_path(root, &upload.sha256),
                    path,
                )
                .await
            }
            _ => Ok(()),
        }
    }

    /// Puts an upload in its place (one of the same content may be there
    /// already): local: renamed into `images/`; S3: the object staged is
    /// checked and put again if a deletion removed it meanwhile. Call
    /// with the lock held, then commit the rows.
    pub async fn persist(&self, mut upload: UploadedFile) -> Result<(), ImageStoreError> {
        match &self.backend {
            Backend::Local { root } => {
                let target = Self::local_path(root, &upload.sha256);
                let parent = target.parent().unwrap_or(root);
                let new_directory = !parent.exists();
                tokio::fs::create_dir_all(parent).await?;
                if let Some(path) = upload.path.take() {
                    // With `--fsync` its bytes were flushed when it was
                    // finished (`Upload::finish`), outside the lock.
                    tokio::fs::rename(&path, &target).await?;
                    if self.fsync {
                        // The rename and, for a new directory, its entry.
                        sync_directory(parent).await?;
                        if new_directory {
                            sync_directory(root).await?;
                        }
                    }
                }
                Ok(())
            }
            Backend::Objects { store, root } => {
                let location = Self::object_path(root, &upload.sha256);
                match store.head(&location).await {
                    Ok(_) => Ok(()),
                    Err(object_store::Error::NotFound { .. }) => match &upload.path {
                        Some(path) => put_file(store.as_ref(), &location, path).await,
                        None => Err(ImageStoreError::Missing {
                            sha256: upload.sha256.clone(),
                        }),
                    },
                    Err(error) => Err(ImageStoreError::from_object_store(error, None)),
                }
            }
        }
    }

    /// The hashes of every stored image.
    pub async fn stored(&self) -> Result<Vec<String>, ImageStoreError> {
        match &self.backend {
            Backend::Local { root } => {
                // tokio::fs, as the store's other file operations: the
                // hourly sweep runs on the serving runtime.
                let mut hashes = Vec::new();
                let mut prefixes = tokio::fs::read_dir(root).await?;
                while let Some(prefix) = prefixes.next_entry().await? {
                    if prefix.file_type().await?.is_dir() {
                        let mut files = tokio::fs::read_dir(prefix.path()).await?;
                        while let Some(file) = files.next_entry().await? {
                            hashes.push(file.file_name().to_string_lossy().into_owned());
                        }
                    }
                }
                Ok(hashes)
            }
            Backend::Objects { store, root } => {
                let mut hashes = Vec::new();
                let mut listing = store.list(Some(root));
                while let Some(object) = listing.next().await {
                    let object = object.map_err(|e| ImageStoreError::from_object_store(e, None))?;
                    if let Some(name) = object.location.filename() {
                        hashes.push(name.to_owned());
                    }
                }
                Ok(hashes)
            }
        }
    }

    /// Reads an image's bytes; [`ImageStoreError::Missing`] if it is not
    /// stored.
    pub async fn read(&self, sha256: &str) -> Result<Vec<u8>, ImageStoreError> {
        match &self.backend {
            Backend::Local { root } => {
                match tokio::fs::read(Self::local_path(root, sha256)).await {
                    Err(e) if e.kind() == io::ErrorKind::NotFound => {
                        Err(ImageStoreError::Missing {
                            sha256: sha256.to_owned(),
                        })
                    }
                    read => Ok(read?),
                }
            }
            Backend::Objects { store, root } => {
                let location = Self::object_path(root, sha256);
                let fetched = async {
                    let result = store.get(&location).await?;
                    result.bytes().await
                }
                .await;
                fetched
                    .map(|bytes| bytes.to_vec())
                    .map_err(|e| ImageStoreError::from_object_store(e, Some(sha256)))
            }
        }
    }

    /// Deletes an image; call with the lock held, after checking that no
    /// row refers to it. Deleting one that is not there is no error.
    pub async fn remove(&self, sha256: &str) -> Result<(), ImageStoreError> {
        match &self.backend {
            Backend::Local { root } => {
                match tokio::fs::remove_file(Self::local_path(root, sha256)).await {
                    Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e.into()),
                    _ => Ok(()),
                }
            }
            Backend::Objects { store, root } => {
                match store.delete(&Self::object_path(root, sha256)).await {
                    Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
                    Err(error) => Err(ImageStoreError::from_object_store(error, None)),
                }
            }
        }
    }

    /// Deletes every stored image that no row refers to (left by a process
    /// killed between storing and committing, or between committing a
    /// frame's results and deleting its images); how many. The listing
    /// runs without the lock; each check and deletion holds it (see the
    /// module's doc), so uploads go on meanwhile.
    pub async fn sweep(&self, store: &Store) -> Result<usize, SweepError> {
        let mut swept = 0;
        for hash in self.stored().await? {
            let _guard = self.lock(store).await?;
            if !store.image_in_use(&hash).await? {
                self.remove(&hash).await?;
                swept += 1;
            }
        }
        Ok(swept)
    }
}

/// Removes the entries of `tmp` whose process has stopped: each is named
/// `KIND-PID-...` by the process that made it (an upload, a request's
/// scratch directory); one whose process `alive` says still runs (a
/// `ptv worker` on the same data directory, or this process) is kept, and
/// one whose name says no process is removed.
fn remove_abandoned(tmp: &Path, alive: impl Fn(u32) -> bool) -> io::Result<()> {
    let entries = match std::fs::read_dir(tmp) {
        Ok(entries) => entries,
        Err(error) if error.kind() == io::ErrorKind::NotFound => return Ok(()),
        Err(error) => return Err(error),
    };
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name();
        let owner = name
            .to_str()
            .and_then(|name| name.split('-').nth(1))
            .and_then(|pid| pid.parse::<u32>().ok());
        if owner.is_some_and(&alive) {
            continue;
        }
        let path = entry.path();
        let removed = if entry.file_type()?.is_dir() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        match removed {
            Err(error) if error.kind() != io::ErrorKind::NotFound => return Err(error),
            _ => {}
        }
    }
    Ok(())
}

/// Flushes a directory's entries to the disk (`fsync` on the directory),
/// so that a rename into it survives a power loss.
async fn sync_directory(directory: &Path) -> io::Result<()> {
    tokio::fs::File::open(directory).await?.sync_all().await
}

/// Why a sweep stopped.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    /// The image store.
    #[error(transparent)]
    Images(#[from] ImageStoreError),
    /// The database.
    #[error("the database: {0}")]
    Database(#[from] crate::service::store::StoreError),
}

/// Puts a local file as an object: in one request up to
/// [`MULTIPART_ABOVE`] bytes, else as a multipart upload read from the
/// file a part at a time (aborted if a part fails).
async fn put_file(
    store: &dyn ObjectStore,
    location: &ObjectPath,
    path: &Path,
) -> Result<(), ImageStoreError> {
    let unavailable = |e| ImageStoreError::from_object_store(e, None);
    let mut file = tokio::fs::File::open(path).await?;
    let size = file.metadata().await?.len();
    if size <= MULTIPART_ABOVE as u64 {
        let mut bytes = Vec::with_capacity(size as usize);
        file.read_to_end(&mut bytes).await?;
        store
            .put(location, bytes.into())
            .await
            .map_err(unavailable)?;
        return Ok(());
    }
    let upload = store.put_multipart(location).await.map_err(unavailable)?;
    let mut writer = object_store::WriteMultipart::new_with_chunk_size(upload, MULTIPART_ABOVE);
    let mut buffer = vec![0; 1 << 20];
    loop {
        let n = match file.read(&mut buffer).await {
            Ok(n) => n,
            Err(error) => {
                let _ = writer.abort().await;
                return Err(error.into());
            }
        };
        if n == 0 {
            break;
        }
        // At most two parts in flight: bounded memory per upload.
        if let Err(error) = writer.wait_for_capacity(2).await {
            let _ = writer.abort().await;
            return Err(unavailable(error));
        }
        writer.write(&buffer[..n]);
    }
    writer.finish().await.map_err(unavailable)?;
    Ok(())
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
        if self.fsync {
            self.file.sync_all().await?;
        }
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

/// Deletes the files of `hashes` that nothing refers to any more, each
/// checked under the image store's lock against what is committed.
pub async fn remove_unused_images(store: &Store, images: &ImageStore, hashes: &[String]) {
    if hashes.is_empty() {
        return;
    }
    let _guard = match images.lock(store).await {
        Ok(guard) => guard,
        Err(error) => {
            // The files stay; the next sweep removes them.
            tracing::warn!(%error, "cannot lock the image store to delete unused files");
            return;
        }
    };
    for hash in hashes {
        match store.image_in_use(hash).await {
            Ok(false) => {
                if let Err(error) = images.remove(hash).await {
                    tracing::warn!(%error, hash, "cannot delete an image file");
                }
            }
            Ok(true) => {}
            Err(error) => tracing::warn!(%error, "cannot check an image's use"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::infra::errors::is_storage_full;

    /// A starting `ptv serve` removes what stopped processes left in
    /// `tmp/` and keeps what running ones (a `ptv worker` on the same data
    /// directory) are writing.
    #[tokio::test]
    async fn a_start_removes_only_the_temporary_files_of_stopped_processes() {
        let dir = tempfile::tempdir().unwrap();
        let tmp = dir.path().join("tmp");
        std::fs::create_dir_all(tmp.join("experiment-7-123")).unwrap();
        std::fs::write(tmp.join("experiment-7-123").join("ptv.par"), "x").unwrap();
        std::fs::create_dir_all(tmp.join("experiment-9-456")).unwrap();
        for name in ["upload-7-0", "upload-9-0", "upload-9-1", "stray"] {
            std::fs::write(tmp.join(name), "x").unwrap();
        }
        // Process 7 runs; 9 stopped.
        remove_abandoned(&tmp, |pid| pid == 7).unwrap();
        let mut left: Vec<_> = std::fs::read_dir(&tmp)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        left.sort();
        assert_eq!(left, ["experiment-7-123", "upload-7-0"]);
        // A missing tmp/ is nothing to remove.
        remove_abandoned(&dir.path().join("none"), |_| true).unwrap();
        // Through the store: this process's own upload is kept.
        let store = ImageStore::open_shared(dir.path(), None).await.unwrap();
        let mut upload = store.create_upload().await.unwrap();
        upload.write(b"abc").await.unwrap();
        let again = ImageStore::open(dir.path(), None).await.unwrap();
        let file = upload.finish().await.unwrap();
        again.persist(file).await.unwrap();
        assert!(!tmp.join("upload-9-0").exists());
    }

    #[test]
    fn a_missing_object_is_told_from_an_unreachable_store() {
        let missing = object_store::Error::NotFound {
            path: "images/ab/abc".to_owned(),
            source: "404".into(),
        };
        assert!(matches!(
            ImageStoreError::from_object_store(missing, Some("abc")),
            ImageStoreError::Missing { sha256 } if sha256 == "abc"
        ));
        let refused = object_store::Error::Generic {
            store: "S3",
            source: Box::new(io::Error::from(io::ErrorKind::ConnectionRefused)),
        };
        assert!(matches!(
            ImageStoreError::from_object_store(refused, Some("abc")),
            ImageStoreError::Unavailable(_)
        ));
        let denied = object_store::Error::PermissionDenied {
            path: "images".to_owned(),
            source: "403 access denied".into(),
        };
        assert!(matches!(
            ImageStoreError::from_object_store(denied, None),
            ImageStoreError::Other(_)
        ));
    }

    /// A real request to a port where nothing listens: the error that
    /// `object_store` gives after its retries reads as unreachable.
    #[tokio::test]
    async fn a_refused_connection_reads_as_unavailable() {
        use object_store::aws::AmazonS3Builder;
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let store = AmazonS3Builder::new()
            .with_bucket_name("ptv-test")
            .with_region("us-east-1")
            .with_access_key_id("key")
            .with_secret_access_key("secret")
            .with_endpoint(format!("http://127.0.0.1:{port}"))
            .with_allow_http(true)
            .with_retry(object_store::RetryConfig {
                max_retries: 1,
                retry_timeout: Duration::from_secs(2),
                ..Default::default()
            })
            .build()
            .unwrap();
        let error = store
            .get(&ObjectPath::from("images/ab/abc"))
            .await
            .unwrap_err();
        let error = ImageStoreError::from_object_store(error, Some("abc"));
        assert!(
            matches!(error, ImageStoreError::Unavailable(_)),
            "{error:?}"
        );
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
            fsync: false,
        };
        let mut error = upload.write(&[0; 1 << 16]).await.err();
        if error.is_none() {
            error = upload.finish().await.err();
        }
        let error = error.expect("a write to /dev/full fails");
        assert!(is_storage_full(&error), "{error:?}");
    }
}
