//! Locks between the processes that share a data directory (`ptv serve`
//! and any number of `ptv worker`): an exclusive `flock` on a file of the
//! directory, held while its `File` lives. Taken on a blocking thread, as
//! it waits for the holder.

use std::fs::File;
use std::io;
use std::path::PathBuf;

/// Waits for and takes the exclusive lock on `path` (created if missing).
/// Dropping the file releases it; so does the holder's death.
pub async fn exclusive(path: PathBuf) -> io::Result<File> {
    tokio::task::spawn_blocking(move || {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)?;
        #[cfg(unix)]
        rustix::fs::flock(&file, rustix::fs::FlockOperation::LockExclusive)?;
        Ok(file)
    })
    .await
    .map_err(io::Error::other)?
}
