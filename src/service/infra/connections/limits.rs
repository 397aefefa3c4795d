//! The default connection limit: the open-file limit, raised to its hard
//! value, less a reserve for the database, image files and workers
//! (module docs of [`super`]).

/// File descriptors kept for everything but connections: standard streams,
/// the listener, the runtime's, the log.
pub(super) const RESERVE_BASE: u64 = 64;

/// The default limit's ceiling: more idle connections than this cost more
/// memory than they are worth; `--max-connections` can go higher.
pub(super) const DEFAULT_CEILING: u64 = 65_536;

/// Raises the soft limit on open files to the hard one (on Unix) and
/// returns the soft limit then in force, if known.
pub fn raise_open_file_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        use rustix::process::{getrlimit, setrlimit, Resource, Rlimit};
        let limit = getrlimit(Resource::Nofile);
        if limit.current.is_some() && limit.current != limit.maximum {
            // An unlimited hard limit cannot be the soft one on Linux
            // (`fs.nr_open` caps it); try a large finite value instead.
            let target = limit.maximum.unwrap_or(1 << 20);
            let raised = Rlimit {
                current: Some(target),
                maximum: limit.maximum,
            };
            if let Err(error) = setrlimit(Resource::Nofile, raised) {
                tracing::debug!(%error, "cannot raise the open-file limit");
            }
        }
        getrlimit(Resource::Nofile).current
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// The default connection limit for `open_files` file descriptors: less a
/// reserve of 64, 4 per database connection (database, WAL, shared memory,
/// journal), 16 per worker (the image files of a frame) and a sixteenth of
/// the limit (uploads' temporary files), at most 65,536. Without a known
/// limit, 1,024.
pub fn default_max_connections(open_files: Option<u64>, workers: usize, database: u32) -> usize {
    let Some(open_files) = open_files else {
        return 1024;
    };
    let reserve = RESERVE_BASE + 4 * u64::from(database) + 16 * workers as u64 + open_files / 16;
    let max = if open_files > 2 * reserve {
        open_files - reserve
    } else {
        open_files / 2
    };
    usize::try_from(max.clamp(1, DEFAULT_CEILING)).unwrap_or(1)
}
